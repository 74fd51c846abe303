"""Throughput constants of pd_tool/prepare/work.py, measured on this machine.

Times, per call, the pieces the work estimate adds up and fits each to a line:

- the bake's forward substep (MPMSolver, fixed substeps):      t0 + a * particles + b * grid nodes
- the fit's forward + backward substep (a DiffSim frame through torch autograd, hand-written
  adjoint): the same form
- a render, forward and forward + backward:                      r0 + g * Gaussians + p * pixels
- the bake's per-frame work per Gaussian (interpolation and the USD write)

and prints the constants in the form pd_tool/prepare/work.py holds them, with each fit's worst
ratio of measured to predicted time. On a shared machine run it twice and keep the slower.

    OMP_NUM_THREADS=1 python bench/work_estimate.py --device cpu --json docs/runs/work_estimate_cpu.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def _lstsq(rows: list[tuple[float, ...]], t: list[float]) -> tuple[np.ndarray, float]:
    """Non-negative least squares by clipping (three columns at most), relative weighting:
    every measurement counts by its relative error. Returns (coefficients, worst ratio)."""
    A = np.asarray(rows, np.float64)
    y = np.asarray(t, np.float64)
    w = 1.0 / y
    coef, *_ = np.linalg.lstsq(A * w[:, None], y * w, rcond=None)
    coef = np.clip(coef, 0.0, None)
    pred = A @ coef
    return coef, float(np.max(np.maximum(y / pred, pred / y)))


def _seconds_per_call(fn, reps: int, device: str) -> float:
    """Wall seconds per call of fn, after one untimed call (warp compiles, captures graphs),
    with the device drained before the clock starts and before it stops."""
    import torch
    import warp as wp

    def drain():
        wp.synchronize_device(device)
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    fn()
    drain()
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    drain()
    return (time.perf_counter() - t0) / reps


def sim_rates(device: str, sizes: list[tuple[int, int]], substeps: int, frames: int) -> dict:
    """Seconds per substep of the bake's forward (MPMSolver, its fast path) and of the fit's
    forward + backward (a DiffSim frame through torch autograd, as the fit runs it) on the
    elastic block of bench/sim_speed.py, fitted to t0 + a * particles + b * grid nodes."""
    import torch

    from pd_tool.io.synthetic import make_block
    from pd_tool.sim import DiffSim, MPMSolver, SimConfig
    from pd_tool.sim.autograd import initial_state

    gravity = (0.0, 0.0, -9.81)
    fwd_rows, fwd_t, fb_t = [], [], []
    for n, res in sizes:
        x, vol, mass, E, static = make_block(n, res)
        solver = MPMSolver(x, vol, mass, E, static, SimConfig(grid_res=res, substeps=substeps, gravity=gravity),
                           device=device)
        fwd_t.append(_seconds_per_call(lambda: solver.step_frame(1e-3), frames, device) / substeps)
        dsim = DiffSim(vol, mass, static, SimConfig(grid_res=res, gravity=gravity), device=device)
        rest = initial_state(torch.tensor(x, device=device))
        E_t = torch.tensor(E, dtype=torch.float32, device=device, requires_grad=True)
        forces = dsim.forces([])
        fb_t.append(_seconds_per_call(lambda: dsim.frame(rest, E_t, 1e-3, substeps, forces)[0].sum().backward(),
                                      max(1, frames // 2), device) / substeps)
        fwd_rows.append((1.0, float(n), float((res + 1) ** 3)))
        print(f"  sim {n:>7} particles, {res}^3: fwd {fwd_t[-1] * 1e6:9.1f} us/substep, "
              f"fwd+bwd {fb_t[-1] * 1e6:9.1f} us/substep", flush=True)
    (a0, a1, a2), worst_f = _lstsq(fwd_rows, fwd_t)
    (b0, b1, b2), worst_b = _lstsq(fwd_rows, fb_t)
    return {"forward": {"substep_s": a0, "particle_s": a1, "node_s": a2, "worst_ratio": worst_f},
            "forward_backward": {"substep_s": b0, "particle_s": b1, "node_s": b2, "worst_ratio": worst_b},
            "samples": {"sizes": sizes, "forward_s": fwd_t, "forward_backward_s": fb_t}}


def render_rates(device: str, cases: list[tuple[int, int]], reps: int) -> dict:
    """Seconds per render, forward and forward + backward, of bench/render_speed.py's splat
    ball seen by its camera (50 degrees vertical), square images, fitted to
    r0 + g * Gaussians + p * pixels."""
    import math

    from pd_tool.core.cameras import Camera, look_at
    from pd_tool.io.synthetic import make_splat_ball
    from pd_tool.render import render

    rows, tf, tb = [], [], []
    for n, side in cases:
        ball = make_splat_ball(n, device=device)
        splats = [ball.positions, ball.quats, ball.scales, ball.opacities, ball.sh]
        leaves = [t.detach().clone().requires_grad_() for t in splats]
        f = 0.5 * side / math.tan(math.radians(25.0))
        cam = Camera(side, side, f, f, side / 2, side / 2, look_at([2.1, -2.1, 0.6], [0, 0, 0], [0, 0, 1]))
        tf.append(_seconds_per_call(lambda: render(*splats, cam, background=(1.0, 1.0, 1.0)), reps, device))
        tb.append(_seconds_per_call(lambda: render(*leaves, cam, background=(1.0, 1.0, 1.0)).rgb.sum().backward(),
                                    reps, device))
        rows.append((1.0, float(n), float(side * side)))
        print(f"  render {n:>7} Gaussians at {side}x{side}: fwd {tf[-1] * 1e3:8.1f} ms, fwd+bwd {tb[-1] * 1e3:8.1f} ms",
              flush=True)
    (f0, f1, f2), worst_f = _lstsq(rows, tf)
    (b0, b1, b2), worst_b = _lstsq(rows, tb)
    return {"forward": {"call_s": f0, "gaussian_s": f1, "pixel_s": f2, "worst_ratio": worst_f},
            "forward_backward": {"call_s": b0, "gaussian_s": b1, "pixel_s": b2, "worst_ratio": worst_b}}


def bake_frame_rate(device: str, counts: list[int], frames: int) -> dict:
    """Seconds per Gaussian and frame outside the simulation: a bake at one substep per
    frame, minus its measured simulation time (no force: one substep stays stable)."""
    import tempfile

    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material
    from pd_tool.io.synthetic import POT_TOP, make_plant

    per = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            scene = make_plant(n, seed=0, thin=False)
            res = bake(scene, Path(tmp) / f"b{n}.usd", force=ForceSpec(accel=(0.0, 0.0, 0.0)),
                       material=Material.from_preset("flower"), prepare_options=PrepareOptions(static_below=POT_TOP),
                       settings=BakeSettings(seconds=(frames - 1) / 30.0, quality="draft", fmt="both", device=device,
                                             substeps=1, stop_at_rest=False))
            t = res.timings["interpolate"] + res.timings["write"]
            per.append(t / (n * (frames - 1)))
            print(f"  bake {n:>7} Gaussians: {per[-1] * 1e9:8.1f} ns per Gaussian-frame "
                  f"(interpolate {res.timings['interpolate']:.2f} s, write {res.timings['write']:.2f} s, "
                  f"setup {res.timings['setup']:.2f} s)", flush=True)
    return {"gaussian_frame_s": max(per), "samples": dict(zip(map(str, counts), per))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--quick", action="store_true", help="fewer sizes (a smoke test of the script)")
    args = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    if args.quick:
        sizes, renders, counts = [(200, 16), (2000, 32)], [(1000, 32), (4000, 64)], [600]
    elif args.device.startswith("cuda"):
        sizes = [(20000, 32), (100000, 64), (300000, 128), (2000, 16), (20000, 64)]
        renders = [(20000, 256), (100000, 512), (300000, 1024)]
        counts = [30000, 300000]
    else:
        sizes = [(200, 16), (2000, 16), (2000, 32), (20000, 32), (5000, 64)]
        renders = [(3000, 64), (3000, 256), (20000, 128), (20000, 256)]
        counts = [3000, 30000]
    substeps = 8 if args.device == "cpu" else 64
    out = {"device": args.device,
           "sim": sim_rates(args.device, sizes, substeps, 3 if args.device == "cpu" else 10),
           "render": render_rates(args.device, renders, 2 if args.device == "cpu" else 10),
           "bake_frame": bake_frame_rate(args.device, counts, 11)}
    print(json.dumps(out, indent=1, default=float))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
