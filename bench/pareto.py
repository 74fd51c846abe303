"""Run time against error for the bake (and optionally the fit), with the Pareto front.

    python bench/pareto.py --device cpu --clock cpu --json pareto.json --png docs/pareto.png
    python bench/pareto.py --device cuda --grids 16,24,32,48,64,96 --reference-grid 128 --json pareto_gpu.json

Bake: one scene (the synthetic plant, `--gaussians`), one force (a poke of the flower
preset), `--seconds` of animation, baked by `pd_tool.bake.baker.bake` itself (USD written and
read back, so the numbers are the shipped code path) over a sweep of
    grid resolution x CFL safety (at the default driver ratio), and
    grid resolution x driver ratio (at the default CFL safety),
plus the three quality presets exactly. Error: RMS over every Gaussian and every frame of
|x - x_ref|, divided by the object's longest side, where x_ref is a run at
`--reference-grid` with `--reference-cfl` and `--reference-ratio`. Time: the bake's
setup + simulate + interpolate seconds (USD writing excluded: it is the same for every
setting), the minimum over `--reps` runs. Precision: float32 everywhere (pdtool has no
mixed-precision path), recorded as such.
`--check-grid` adds a finer run scored against the reference the same way: the reference's
own error.

Fit (`--fit`): the synthetic plant's reference video (hidden E per region) fitted at
several iteration counts; error = mean over regions of |log10(E_fit / E_true)|.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from usd_export import instance_positions

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

PRESETS = ("draft", "default", "final")


@dataclass
class BakeCase:
    """One bake setting: grid cells along the longest side, CFL safety, driving particles
    per Gaussian. tag names where it comes from (sweep, preset name, reference)."""

    grid: int
    cfl: float
    ratio: float
    tag: str = "sweep"
    time_s: float = float("nan")
    error: float = float("nan")  # RMS position error / object size
    max_error: float = float("nan")  # largest per-Gaussian, per-frame error / object size
    error_of_motion: float = float("nan")  # RMS position error / the reference's peak displacement
    substeps: int = 0
    drivers: int = 0
    timings: dict = field(default_factory=dict)

    @property
    def key(self) -> tuple[int, float, float]:
        return (self.grid, round(self.cfl, 4), round(self.ratio, 4))


def quality_file(folder: Path, grid: int, cfl: float, ratio: float) -> Path:
    """A quality preset TOML with these bake settings (fit iterations unused by bake)."""
    p = folder / f"q_{grid}_{cfl}_{ratio}.toml"
    p.write_text(f"grid_res = {grid}\ncfl_safety = {cfl}\ndriver_ratio = {ratio}\n"
                 f"fit_velocity_iters = 1\nfit_material_iters = 1\n")
    return p


def read_usd_positions(path: Path, frames: int) -> np.ndarray:
    """Instancer positions [frames, N, 3] float64 (scene units) from a baked USD file."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    # every instance by id: pinned ones sit on their own prim, written once
    return np.stack([instance_positions(stage, float(f))[1].astype(np.float64) for f in range(frames)])


def bake_plant(scene, case: BakeCase, *, seconds: float, fps: float, device: str, folder: Path,
               stop_at_rest: bool = False, material: str = "flower", accel: float = 20.0):
    """Bake `scene` (the synthetic plant) with a poke under `case`'s settings.

    Returns (positions [frames, N, 3] scene units, BakeResult)."""
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material
    from pd_tool.io.synthetic import POT_TOP

    out = folder / "bake.usd"
    res = bake(scene, out, force=ForceSpec.from_interaction("poke", (accel, 0.0, 0.0)),
               material=Material.from_preset(material), prepare_options=PrepareOptions(static_below=POT_TOP),
               settings=BakeSettings(seconds=seconds, fps=fps, quality=quality_file(folder, case.grid, case.cfl, case.ratio),
                                     fmt="instancer", device=device, stop_at_rest=stop_at_rest))
    return read_usd_positions(out, res.frames), res


def run_case(scene, case: BakeCase, args, folder: Path) -> tuple[BakeCase, np.ndarray]:
    """Bake `case` args.reps times; keep the fastest timing. Returns (case, positions)."""
    best = float("inf")
    for _ in range(args.reps):
        c0 = time.process_time()
        pos, res = bake_plant(scene, case, seconds=args.seconds, fps=args.fps, device=args.device, folder=folder,
                              accel=args.accel)
        cpu = time.process_time() - c0
        wall = res.timings["setup"] + res.timings["simulate"] + res.timings["interpolate"]
        t = cpu if args.clock == "cpu" else wall
        if t < best:
            best, case.timings = t, dict(res.timings, cpu_s=cpu)
    case.time_s = best
    case.substeps, case.drivers = res.substeps_per_frame, res.drivers
    return case, pos


def score(case: BakeCase, pos: np.ndarray, ref: np.ndarray, size: float) -> None:
    """Fill case's errors from its positions and the reference's, [F, N, 3] scene units."""
    d = np.linalg.norm(pos - ref, axis=2)
    case.error = float(np.sqrt(np.mean(d ** 2)) / size)
    case.max_error = float(d.max() / size)
    case.error_of_motion = float(np.sqrt(np.mean(d ** 2)) / max(_peak_motion(ref), 1e-12))


def reference_setting_run(scene, grid: int, tag: str, args, folder: Path) -> tuple[BakeCase, np.ndarray]:
    """One run on `grid` cells at the reference's CFL safety and driver ratio (the reference
    itself, or its finer check). Returns (case, positions)."""
    return run_case(scene, BakeCase(grid, args.reference_cfl, args.reference_ratio, tag=tag),
                    argparse.Namespace(**{**vars(args), "reps": 1}), folder)


def reference_positions(scene, args, folder: Path) -> tuple[dict, np.ndarray]:
    """The reference run, from --reference-cache when it holds one with the same settings
    (another process may be computing it: wait for it), else computed (and cached)."""
    key = {"gaussians": args.gaussians, "thin": args.thin, "seconds": args.seconds, "fps": args.fps,
           "accel": args.accel, "grid": args.reference_grid,
           "cfl": args.reference_cfl, "ratio": args.reference_ratio}
    cache = args.reference_cache
    if cache is not None:
        lock = cache.with_suffix(".lock")
        while not cache.exists() and lock.exists() and not args.reference_only:
            time.sleep(5)
        if cache.exists():
            with np.load(cache, allow_pickle=False) as z:
                info = json.loads(str(z["info"]))
                if {k: info[k] for k in key} == key:
                    return info, z["positions"]
        lock.touch()
    t0 = time.perf_counter()
    c, pos = reference_setting_run(scene, args.reference_grid, "reference", args, folder)
    info = {**key, "time_s": c.time_s, "substeps": c.substeps, "drivers": c.drivers, "wall_s": time.perf_counter() - t0}
    if cache is not None:
        np.savez(cache, positions=pos, info=json.dumps(info))
        cache.with_suffix(".lock").unlink(missing_ok=True)
    return info, pos


def _peak_motion(pos: np.ndarray) -> float:
    """Largest displacement of any Gaussian from frame 0, scene units."""
    return float(np.linalg.norm(pos - pos[:1], axis=2).max())


def pareto_front(times: list[float], errors: list[float]) -> list[int]:
    """Indices of the non-dominated points (no other point is at least as fast and at least
    as accurate, and strictly better in one), sorted by time."""
    idx = []
    for i, (t, e) in enumerate(zip(times, errors)):
        dominated = any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in zip(times, errors))
        if not dominated:
            idx.append(i)
    return sorted(idx, key=lambda i: times[i])


def dominators(i: int, times: list[float], errors: list[float]) -> list[int]:
    """Points that dominate point i."""
    t, e = times[i], errors[i]
    return [j for j, (t2, e2) in enumerate(zip(times, errors))
            if j != i and t2 <= t and e2 <= e and (t2 < t or e2 < e)]


def fit_sweep(args) -> list[dict]:
    """Fit the plant's reference video at several iteration counts; recovery error per run."""
    import torch

    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_for_fit
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant
    from pd_tool.render.views import scene_camera

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene_path = save_splats(make_plant(args.fit_gaussians, seed=0, thin=args.thin), tmp / "plant.ply")
        scene = load_splats(scene_path, device=args.device)
        cam = scene_camera(scene, width=args.fit_size, height=args.fit_size)
        video, _, _ = plant_reference_for_fit(tmp / "video", scene, cam, args.fit_quality, n_frames=args.fit_frames,
                                              device=args.device)
        refs = [load_reference_video(video, working_size=args.fit_size, device=args.device)]
        for spec in args.fit_iters.split(","):
            vi, mi = (int(v) for v in spec.split("/"))
            s = FitSettings(quality=args.fit_quality, device=args.device, velocity_iters=vi, material_iters=mi,
                            working_long_side=args.fit_size)
            if args.device == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            res = run_fit(scene, scene_path, refs, tmp / f"plant_{vi}_{mi}.pdmat",
                          prepare_options=PrepareOptions(static_below=POT_TOP), settings=s)
            wall = time.perf_counter() - t0
            labels = scene.labels[res.prep.foreground]
            rec = {name: float(np.median(res.gaussian_E[labels == i])) for i, name in enumerate(REGIONS) if name != "pot"}
            err = float(np.mean([abs(np.log10(rec[k] / REGION_TRUTH_E[k])) for k in rec]))
            rows.append({"velocity_iters": vi, "material_iters": mi, "time_s": wall, "log10_error": err,
                         "recovered_E": rec, "truth_E": {k: REGION_TRUTH_E[k] for k in rec}})
            print(f"fit {vi:4d}/{mi:<4d} {wall:8.1f} s  mean |log10 E/E_true| = {err:.3f}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--thick", action="store_true",
                    help="the plant with 2 cm leaves and petals (make_plant(thin=False)), a control; default: 3 mm")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--accel", type=float, default=2.0, help="poke strength, scene units/s^2 along x")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--grids", default="16,24,32,48,64")
    ap.add_argument("--cfls", default="0.3,0.5,0.7")
    ap.add_argument("--ratios", default="0.05,0.25,0.5")
    ap.add_argument("--default-cfl", type=float, default=0.5)
    ap.add_argument("--default-ratio", type=float, default=0.1)
    ap.add_argument("--reference-grid", type=int, default=128)
    ap.add_argument("--reference-cfl", type=float, default=0.3)
    ap.add_argument("--reference-ratio", type=float, default=1.0)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--clock", default="wall", choices=["wall", "cpu"],
                    help="time = the bake's wall seconds (setup+simulate+interpolate), or this process's CPU "
                         "seconds for the whole bake call (robust on a shared CPU with --threads 1)")
    ap.add_argument("--check-grid", type=int, default=0,
                    help="also a finer run (this many cells, the reference's CFL and ratio), scored against "
                         "the reference like the sweep: whether the reference has converged")
    ap.add_argument("--reference-cache", type=Path, help="npz holding the reference run (read, or written)")
    ap.add_argument("--reference-only", action="store_true", help="compute the reference into --reference-cache")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--fit", action="store_true", help="also the fit sweep")
    ap.add_argument("--fit-only", action="store_true", help="only the fit sweep")
    ap.add_argument("--fit-iters", default="5/5,10/8,20/15,40/30", help="velocity/material iterations, comma list")
    ap.add_argument("--fit-quality", default="draft")
    ap.add_argument("--fit-gaussians", type=int, default=1500)
    ap.add_argument("--fit-size", type=int, default=128)
    ap.add_argument("--fit-frames", type=int, default=8)
    ap.add_argument("--quick", action="store_true", help="CPU scale: 1500 Gaussians, 0.3 s, two grids, one CFL and ratio, reference 48 cells")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--png", type=Path)
    args = ap.parse_args()
    args.thin = not args.thick
    if args.quick:
        args.gaussians, args.seconds = 1500, 0.3
        args.grids, args.cfls, args.ratios, args.reference_grid = "16,24", "0.5", "0.25", 48

    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.materials.presets import load_preset
    from pd_tool.io.synthetic import make_plant

    torch.set_num_threads(args.threads)
    init_warp_quietly()
    if args.fit_only:
        out = {"device": args.device, "cpu": _cpu_name(), "gpu": torch.cuda.get_device_name() if args.device == "cuda"
               else None, "fit_quality": args.fit_quality, "fit_gaussians": args.fit_gaussians,
               "fit_size": args.fit_size, "fit_frames": args.fit_frames, "fit": fit_sweep(args)}
        if args.json:
            args.json.write_text(json.dumps(out, indent=2))
        return
    scene = make_plant(args.gaussians, seed=0, device=args.device, thin=args.thin)
    size = float(np.ptp(scene.positions.cpu().numpy(), axis=0).max())
    grids = [int(g) for g in args.grids.split(",")]
    cases: dict[tuple, BakeCase] = {}
    for g in grids:
        for c in (float(v) for v in args.cfls.split(",")):
            cases.setdefault((g, c, args.default_ratio), BakeCase(g, c, args.default_ratio))
        for r in (float(v) for v in args.ratios.split(",")):
            cases.setdefault((g, args.default_cfl, r), BakeCase(g, args.default_cfl, r))
    for name in PRESETS:
        q = load_preset("quality", name)
        c = BakeCase(int(q["grid_res"]), float(q["cfl_safety"]), float(q["driver_ratio"]), tag=name)
        if c.key in {k for k in cases}:
            cases[c.key].tag = name
        else:
            cases[c.key] = c

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        # warm-up: compile/load kernels outside the timings
        bake_plant(make_plant(500, seed=1, device=args.device, thin=False), BakeCase(16, 0.5, 0.1), seconds=0.1, fps=args.fps,
                   device=args.device, folder=tmp)
        if args.reference_only:
            info, _ = reference_positions(scene, args, tmp)
            print(json.dumps(info))
            return
        rows, positions = [], []
        for key in sorted(cases):
            case, pos = run_case(scene, cases[key], args, tmp)
            rows.append(case)
            positions.append(pos)
            print(f"grid {case.grid:4d} cfl {case.cfl:4.2f} ratio {case.ratio:5.3f} {case.tag:9s} "
                  f"{case.time_s:7.2f} s  substeps {case.substeps}  drivers {case.drivers}", flush=True)
        ref_info, ref = reference_positions(scene, args, tmp)
        print(f"reference {json.dumps(ref_info)}", flush=True)
        check = None
        if args.check_grid:
            check, check_pos = reference_setting_run(scene, args.check_grid, "check", args, tmp)
            score(check, check_pos, ref, size)
            print(f"check grid {check.grid} against the reference: rms {check.error:.3e}  "
                  f"of motion {check.error_of_motion:.3f}", flush=True)
    for case, pos in zip(rows, positions):
        score(case, pos, ref, size)
        print(f"grid {case.grid:4d} cfl {case.cfl:4.2f} ratio {case.ratio:5.3f} {case.tag:9s} {case.time_s:7.2f} s  "
              f"rms {case.error:.3e}  max {case.max_error:.3e}  of motion {case.error_of_motion:.3f}")

    times = [r.time_s for r in rows]
    errors = [r.error for r in rows]
    front = pareto_front(times, errors)
    presets = {}
    for i, r in enumerate(rows):
        if r.tag in PRESETS:
            dom = dominators(i, times, errors)
            presets[r.tag] = {"on_front": i in front, "dominated_by": [vars(rows[j]) | {"timings": None} for j in dom]}
    out = {
        "device": args.device,
        "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
        "cpu": _cpu_name(), "torch_threads": args.threads, "precision": "float32 (no mixed-precision path)",
        "gaussians": args.gaussians, "thin": args.thin, "seconds": args.seconds, "fps": args.fps,
        "object_size": size, "force": f"poke preset x ({args.accel}, 0, 0), material flower",
        "reference": ref_info, "check": vars(check) if check else None, "clock": args.clock,
        "reference_peak_motion_of_size": _peak_motion(ref) / size,
        "cases": [vars(r) for r in rows], "front": front, "presets": presets,
    }
    if args.fit:
        out["fit"] = fit_sweep(args)
    print(json.dumps({"front": [(rows[i].grid, rows[i].cfl, rows[i].ratio) for i in front], "presets": {
        k: v["on_front"] for k, v in presets.items()}}, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    if args.png:
        write_plot(args.png, rows, front, out)


def write_plot(path: Path, rows: list[BakeCase], front: list[int], out: dict) -> None:
    from pd_tool.render.plots import scatter_plot

    # a log axis cannot show an error of 0 (a case identical to the reference)
    keep = [i for i, r in enumerate(rows) if r.error > 0]
    new = {i: k for k, i in enumerate(keep)}
    pts = [(rows[i].time_s, rows[i].error, f"{rows[i].grid}/{rows[i].cfl}/{rows[i].ratio}") for i in keep]
    highlight = {new[i]: rows[i].tag for i in keep if rows[i].tag in PRESETS}
    front = [new[i] for i in front if i in new]
    where = out["gpu"] or out["cpu"]
    scatter_plot(path, pts, front=front, highlight=highlight,
                 title=f"bake: time vs error, plant {out['gaussians']} Gaussians, {out['seconds']} s, {where}",
                 xlabel=("bake CPU s (1 thread)" if out["clock"] == "cpu" else "bake wall s (setup+simulate+interpolate)"), ylabel="RMS error / size")


def _cpu_name() -> str:
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown CPU"


if __name__ == "__main__":
    main()
