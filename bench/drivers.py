"""Driving particles: speed (K-Means, nearest drivers, interpolation) and accuracy.

Speed: K-Means of --points Gaussian centres (the synthetic plant) into --clusters drivers,
the 8 nearest drivers of every Gaussian, and one frame of interpolation of every Gaussian
(rigid forward, affine forward, rigid forward + backward). Targets on an H100: K-Means of
1M points into 50k clusters <= 10 s, interpolation of 1M Gaussians <= 5 ms per frame.

Accuracy: the synthetic plant (static pot, stiffness per region) under a poke at the top.
Every Gaussian simulated as a particle is the reference; for each driver ratio the drivers
are simulated and every Gaussian interpolated from them. Errors are per Gaussian and frame,
as a fraction of the object's longest side.

    python bench/drivers.py --part speed --device cuda --points 1000000 --clusters 50000
    python bench/drivers.py --part accuracy --device cpu --gaussians 20000 --json acc.json
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pd_tool.drivers import DriverInterpolator, build_drivers, kmeans, nearest_drivers  # noqa: E402

RATIOS = (1 / 4, 1 / 10, 1 / 25, 1 / 50)


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def hardware(device: str) -> str:
    if device.startswith("cuda"):
        return torch.cuda.get_device_name()
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        name = next(line.split(":", 1)[1].strip() for line in out.splitlines() if line.startswith("Model name"))
    except Exception:
        name = platform.processor() or "cpu"
    return f"{name}, {torch.get_num_threads()} torch threads"


def plant_points(n: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    from pd_tool.io.synthetic import make_plant

    scene = make_plant(n, seed=0, thin=False)
    return scene.positions.to(device), scene.quats.to(device)


def timed(fn, device: str, reps: int = 1):
    fn()  # warm-up / compile outside the clock
    sync(device)
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn()
    sync(device)
    return (time.perf_counter() - t0) / reps, out


# --------------------------------------------------------------------------- speed


def bench_speed(args) -> dict:
    dev = args.device
    pts, quats = plant_points(args.points, dev)
    res: dict = {"points": args.points, "clusters": args.clusters}
    # K-Means once cold-ish: a tiny run first so that CUDA kernels are loaded.
    kmeans(pts[:10_000], 100)
    sync(dev)
    t0 = time.perf_counter()
    centres, labels = kmeans(pts, args.clusters, seed=0)
    sync(dev)
    res["kmeans_s"] = time.perf_counter() - t0
    res["kmeans_inertia_m2"] = float(((pts - centres[labels]) ** 2).sum(1).double().mean())
    t0 = time.perf_counter()
    nb = nearest_drivers(pts, centres, 8)
    sync(dev)
    res["nearest_drivers_s"] = time.perf_counter() - t0
    gen = torch.Generator().manual_seed(0)
    # A smooth bend of the drivers, as in a frame of simulation.
    now = centres.clone()
    now[:, 0] += 0.05 * torch.sin(4 * centres[:, 2])
    now += 1e-3 * torch.randn(now.shape, generator=gen).to(dev)
    for mode in ("rigid", "affine"):
        interp = DriverInterpolator(pts, quats, centres, nb, mode=mode)
        with torch.no_grad():
            t, _ = timed(lambda: interp(now), dev, args.reps)
        res[f"interp_{mode}_ms"] = 1e3 * t
    interp = DriverInterpolator(pts, quats, centres, nb)
    x = now.clone().requires_grad_(True)

    def fwd_bwd():
        p, q = interp(x)
        (p.sum() + q.sum()).backward()
        return None

    t, _ = timed(fwd_bwd, dev, max(1, args.reps // 4))
    res["interp_rigid_fwd_bwd_ms"] = 1e3 * t
    if dev.startswith("cuda"):
        res["peak_cuda_mem_gb"] = torch.cuda.max_memory_allocated() / 2**30
    return res


# --------------------------------------------------------------------------- accuracy


def simulate(prep, x0, volume, mass, E, static, mask, accel_sim, frames: int, fps: float, device: str, cfl: float):
    """Positions of the particles at frames 1..frames: [frames, M, 3] float64 (metres)."""
    from pd_tool.sim import MPMSolver, SimConfig

    cfg = SimConfig(grid_res=max(prep.grid_dims), domain=prep.domain, nu=0.3, gravity=(0.0, 0.0, 0.0),
                    cfl_safety=cfl)
    solver = MPMSolver(x0, volume, mass, E, static, cfg, device=device)
    solver.add_force(mask, accel_sim, 0.0, POKE_DURATION_S)
    out = []
    substeps = 0
    for _ in range(frames):
        substeps = solver.step_frame(1.0 / fps)
        out.append(np.asarray(solver.positions(), np.float64))
    return np.stack(out), substeps


POKE_DURATION_S = 0.1  # seconds (the poke preset)
POKE_RADIUS = 0.15  # of the object's longest side, around the top free particle


def bench_accuracy(args) -> dict:
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant

    dev = args.device
    scene = make_plant(args.gaussians, seed=0)
    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=args.grid_res))
    x = prep.positions_sim
    size = prep.object_size_m
    region = scene.labels[prep.foreground]
    table = np.array([REGION_TRUTH_E[name] for name in REGIONS], np.float64)
    E_g = table[region]
    free = ~prep.static
    top = x[free][np.argmax(x[free][:, 2])]
    accel = np.array([args.poke, 0.0, 0.0])  # m/s^2 along +x (simulation axes)

    def poke_mask(p: np.ndarray, static: np.ndarray) -> np.ndarray:
        return (np.linalg.norm(p - top, axis=1) <= POKE_RADIUS * size) & ~static

    simulate(prep, x[:100], prep.volumes[:100], prep.masses[:100], E_g[:100], prep.static[:100],
             np.zeros(100, bool), accel, 1, args.fps, dev, args.cfl)  # load the kernels off the clock
    t0 = time.perf_counter()
    ref, substeps_ref = simulate(prep, x, prep.volumes, prep.masses, E_g, prep.static, poke_mask(x, prep.static),
                                 accel, args.frames, args.fps, dev, args.cfl)
    t_ref = time.perf_counter() - t0
    disp = np.linalg.norm(ref - x[None], axis=2)
    rows = [{
        "ratio": 1.0, "drivers": len(x), "moving_drivers": int((~prep.static).sum()), "rms_frac": 0.0, "max_frac": 0.0, "rms_of_motion": 0.0,
        "build_s": 0.0, "sim_s": t_ref, "interp_s": 0.0, "substeps": substeps_ref,
    }]
    quats = torch.as_tensor(scene.quats[prep.foreground].cpu().numpy(), dtype=torch.float32, device=dev)
    pts = torch.as_tensor(x, dtype=torch.float32, device=dev)
    for ratio in args.ratios:
        t0 = time.perf_counter()
        ds = build_drivers(pts, torch.as_tensor(prep.volumes, dtype=torch.float32, device=dev),
                           torch.as_tensor(prep.masses, dtype=torch.float32, device=dev),
                           torch.as_tensor(prep.static, device=dev), prep.dx,
                           ratio=None if ratio == "rule" else ratio, seed=0, static_drivers=args.static_drivers)
        sync(dev)
        t_build = time.perf_counter() - t0
        rule = ratio == "rule"
        asked = ratio
        member = ds.labels.cpu().numpy()
        votes = np.zeros((len(ds), len(table)))
        np.add.at(votes, (member, region), 1.0)
        E_d = table[votes.argmax(1)]
        d_rest = ds.positions.double().cpu().numpy()
        d_static = ds.static.cpu().numpy().astype(bool)
        t0 = time.perf_counter()
        traj, substeps = simulate(prep, d_rest, ds.volume.cpu().numpy(), ds.mass.cpu().numpy(), E_d, d_static,
                                  poke_mask(d_rest, d_static), accel, args.frames, args.fps, dev, args.cfl)
        t_sim = time.perf_counter() - t0
        interp = DriverInterpolator(pts, quats, ds.positions, ds.neighbors, mode=args.mode)
        t0 = time.perf_counter()
        err = []
        with torch.no_grad():
            for f in range(args.frames):
                p = interp(torch.as_tensor(traj[f], dtype=torch.float32, device=dev))[0]
                err.append(np.linalg.norm(p.double().cpu().numpy() - ref[f], axis=1))
        sync(dev)
        t_interp = time.perf_counter() - t0
        err = np.stack(err)
        rms = float(np.sqrt((err ** 2).mean()))
        # Interpolation alone: drivers that follow the reference exactly (the mean of their
        # members in the all-Gaussian simulation), so no simulation error is mixed in.
        labels = ds.labels.cpu().numpy()
        counts = np.bincount(labels, minlength=len(ds))[:, None]
        err_i = []
        with torch.no_grad():
            for f in range(args.frames):
                d_f = np.zeros((len(ds), 3))
                np.add.at(d_f, labels, ref[f])
                p = interp(torch.as_tensor(d_f / counts, dtype=torch.float32, device=dev))[0]
                err_i.append(np.linalg.norm(p.double().cpu().numpy() - ref[f], axis=1))
        rms_interp = float(np.sqrt((np.stack(err_i) ** 2).mean()))
        rows.append({
            "ratio": asked, "rule": rule, "drivers": len(ds), "moving_drivers": int((~d_static).sum()),
            "drivers_per_gaussian": len(ds) / len(x), "rms_frac": rms / size,
            "rms_interp_only_frac": rms_interp / size, "max_frac": float(err.max()) / size,
            "rms_of_motion": rms / float(np.sqrt((disp ** 2).mean())),
            "build_s": t_build, "sim_s": t_sim, "interp_s": t_interp, "substeps": substeps,
        })
        print(f"ratio {asked if rule else f'1/{1 / asked:.0f}'}: {len(ds)} drivers, RMS {100 * rows[-1]['rms_frac']:.3f}% "
              f"max {100 * rows[-1]['max_frac']:.2f}% of size, sim {t_sim:.1f} s", flush=True)
    print(f"peak displacement {100 * disp.max() / size:.1f}% of the object's size {size:.3f} m", flush=True)
    return {
        "gaussians": len(x), "object_size_m": size, "grid": list(prep.grid_dims), "dx_m": prep.dx,
        "frames": args.frames, "fps": args.fps, "poke_m_s2": args.poke, "mode": args.mode,
        "static_drivers": args.static_drivers,
        "peak_displacement_frac": float(disp.max()) / size,
        "rms_displacement_frac": float(np.sqrt((disp ** 2).mean())) / size,
        "rows": rows,
    }


def markdown(acc: dict) -> str:
    lines = [
        "| driver ratio (of the free Gaussians) | drivers (moving + static) | RMS error / size | max error / size | RMS error / RMS motion "
        "| interpolation alone: RMS / size | simulate (s) | K-Means + 8-NN (s) | interpolate all frames (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in acc["rows"]:
        if r["ratio"] == 1.0:
            name = "all Gaussians (reference)"
        elif r.get("rule"):
            name = "paper rule: 8 per occupied cell"
        else:
            name = f"1/{1 / r['ratio']:.0f}"
        moving = r.get("moving_drivers", r["drivers"])
        lines.append(
            f"| {name} | {moving:,} + {r['drivers'] - moving:,} | {100 * r['rms_frac']:.3f}% | {100 * r['max_frac']:.2f}% | "
            f"{100 * r['rms_of_motion']:.1f}% | {100 * r.get('rms_interp_only_frac', 0.0):.3f}% | "
            f"{r['sim_s']:.1f} | {r['build_s']:.2f} | {r['interp_s']:.2f} |"
        )
    return "\n".join(lines)


def parse_ratios(text: str) -> list:
    out = []
    for v in text.split(","):
        if v.strip() == "rule":
            out.append("rule")
        else:
            num, _, den = v.partition("/")
            out.append(float(num) / float(den or 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--part", choices=["speed", "accuracy", "all"], default="all")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--quick", action="store_true", help="CPU scale: speed on 20,000 Gaussians and 1,000 drivers, "
                    "accuracy on 3000 Gaussians, 5 frames, ratios 1/4 and rule")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    ap.add_argument("--points", type=int, default=1_000_000, help="speed: Gaussians")
    ap.add_argument("--clusters", type=int, default=50_000, help="speed: drivers")
    ap.add_argument("--reps", type=int, default=20, help="speed: interpolation repetitions")
    ap.add_argument("--gaussians", type=int, default=20_000, help="accuracy: Gaussians in the plant")
    ap.add_argument("--grid-res", type=int, default=32, help="accuracy: cells along the longest side")
    ap.add_argument("--frames", type=int, default=20, help="accuracy: frames simulated")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--poke", type=float, default=30.0, help="accuracy: poke acceleration, m/s^2")
    ap.add_argument("--cfl", type=float, default=0.5, help="accuracy: CFL safety")
    ap.add_argument("--mode", default="rigid", choices=["rigid", "affine"])
    ap.add_argument("--static-drivers", default="nodes", choices=["nodes", "majority"],
                    help="accuracy: how static Gaussians become drivers (build_drivers)")
    ap.add_argument("--ratios", type=parse_ratios, default=list(RATIOS) + ["rule"],
                    help="accuracy: comma list, e.g. 1/4,1/10,rule (rule: 8 drivers per occupied cell)")
    args = ap.parse_args()
    if args.quick:
        args.points, args.clusters, args.reps = 20_000, 1_000, 3
        args.gaussians, args.grid_res, args.frames = 3000, 16, 5
        args.ratios = args.ratios[:1] + ["rule"]
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=Path(__file__).resolve().parents[1]).stdout.strip()
    except Exception:
        commit = "?"
    out = {"device": args.device, "hardware": hardware(args.device), "torch": torch.__version__, "commit": commit,
           "command": " ".join(sys.argv)}
    if args.part in ("speed", "all"):
        out["speed"] = bench_speed(args)
        print(json.dumps(out["speed"], indent=1), flush=True)
    if args.part in ("accuracy", "all"):
        out["accuracy"] = bench_accuracy(args)
        print(markdown(out["accuracy"]))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
