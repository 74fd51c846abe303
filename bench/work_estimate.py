"""Throughput constants of pd_tool/prepare/work.py, measured on this machine.

Times, per call, the pieces the work estimate adds up and fits each to a line:

- the bake's forward substep (MPMSolver, fixed substeps):      t0 + a * particles + b * grid nodes
- the fit's forward + backward substep (DiffSim, hand-written adjoint): the same form
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
sys.path.insert(0, str(Path(__file__).resolve().parent))


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


def sim_rates(device: str, sizes: list[tuple[int, int]], substeps: int, frames: int) -> dict:
    from sim_speed import make_block, time_forward, time_forward_backward

    fwd_rows, fwd_t, fb_rows, fb_t = [], [], [], []
    for n, res in sizes:
        nodes = float((res + 1) ** 3)
        rate = time_forward(n, res, substeps, frames, device, "fast")
        fwd_rows.append((1.0, float(n), nodes))
        fwd_t.append(n / rate)  # seconds per substep
        _, rate_fb = time_forward_backward(n, res, substeps, max(1, frames // 2), device, None)
        fb_rows.append((1.0, float(n), nodes))
        fb_t.append(n / rate_fb)
        print(f"  sim {n:>7} particles, {res}^3: fwd {fwd_t[-1] * 1e6:9.1f} us/substep, "
              f"fwd+bwd {fb_t[-1] * 1e6:9.1f} us/substep", flush=True)
    (a0, a1, a2), worst_f = _lstsq(fwd_rows, fwd_t)
    (b0, b1, b2), worst_b = _lstsq(fb_rows, fb_t)
    return {"forward": {"substep_s": a0, "particle_s": a1, "node_s": a2, "worst_ratio": worst_f},
            "forward_backward": {"substep_s": b0, "particle_s": b1, "node_s": b2, "worst_ratio": worst_b},
            "samples": {"sizes": sizes, "forward_s": fwd_t, "forward_backward_s": fb_t}}


def render_rates(device: str, cases: list[tuple[int, int]], reps: int) -> dict:
    from render_speed import time_case

    rows, tf, tb = [], [], []
    for n, side in cases:
        f, _ = time_case(side, side, n, device, reps, backward=False)
        b, _ = time_case(side, side, n, device, reps, backward=True)
        rows.append((1.0, float(n), float(side * side)))
        tf.append(f)
        tb.append(b)
        print(f"  render {n:>7} Gaussians at {side}x{side}: fwd {f * 1e3:8.1f} ms, fwd+bwd {b * 1e3:8.1f} ms",
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
            scene = make_plant(n, seed=0)
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
