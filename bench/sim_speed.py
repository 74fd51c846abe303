"""MPM speed: particle-substeps per second, forward and forward+backward.

Scenes: an elastic block of N particles at random positions (8 per occupied cell on
average) given in random order, in a unit box with a res^3 grid
(pd_tool.io.synthetic.make_block). Variants:

- baseline: the obvious implementation: particles in input (random) order, one atomic add
  per node per particle, one launch per kernel per substep, no graph.
- sort_only / fuse_only / graph_only (--ablation): the baseline with one optimisation.
- fast_scatter: particles stored in grid-cell order once, G2P fused with the next
  substep's P2G (atomic scatter) and the grid clear fused into the grid update (two launches
  per substep), CUDA graph of a frame's substeps on GPU, guard read once per frame.
- fast: MPMSolver as bake uses it: on CUDA, fast_scatter with each cell's shares summed
  within a warp before one reduction a node, in the G2P's launch (pd_tool/sim/gather.py);
  on the CPU the same as fast_scatter.
- fast_chunks (CUDA): fast with the sums in a launch of their own, from a payload in
  global memory (MPMSolver(warp_sums=False)).
- fwd+bwd: the differentiable path's cost per frame as the autograd bridge runs it: the
  forward storing each substep's state and grid (SimConfig.keep_budget_mb), then the
  hand-written adjoint kernels in reverse over them, on warp arrays.
  fwd+bwd_recompute: the same with nothing stored (keep_budget_mb 0): the forward in
  place, and a backward that recomputes the frame's segments before the adjoints.
  fwd+bwd_tape (--backward both): the recompute with warp's taped adjoints.

    python bench/sim_speed.py --device cpu --sizes 20000:32 --json cpu.json
    python bench/sim_speed.py --device cuda --json h100.json      # 20k/32, 100k/64, 300k/128
    python bench/sim_speed.py --device cuda --sizes 100000:64 --no-backward --frame-cost
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
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from pd_tool.io.synthetic import make_block  # noqa: E402
from pd_tool.sim import DiffSim, MPMSolver, SimConfig  # noqa: E402
from pd_tool.sim.autograd import backward_frame, forward_frame  # noqa: E402
from kernel_ptx import apply_kernel_options  # noqa: E402

DEFAULT_SIZES = "20000:32,100000:64,300000:128"


def sync(device) -> None:
    wp.synchronize_device(device)


VARIANTS = {  # MPMSolver options of each forward variant
    "baseline": dict(optimized=False),
    "sort_only": dict(optimized=False, sort_particles=True),
    "fuse_only": dict(optimized=False, fuse_kernels=True),
    "graph_only": dict(optimized=False, cuda_graph=True),
    "fast_scatter": dict(optimized=True, gather_p2g=False),
    "fast": dict(optimized=True),
    "fast_chunks": dict(optimized=True, warp_sums=False),
}


def time_forward(n: int, res: int, substeps: int, frames: int, device: str, variant: str) -> float:
    x, vol, mass, E, static = make_block(n, res)
    cfg = SimConfig(grid_res=res, substeps=substeps, gravity=(0.0, 0.0, -9.81))
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, **VARIANTS[variant])
    frame_dt = 1e-3
    sim.step_frame(frame_dt)  # compile, capture the graph
    sync(device)
    t0 = time.perf_counter()
    for _ in range(frames):
        sim.step_frame(frame_dt)  # includes the guard's one sync per frame
    sync(device)
    return n * substeps * frames / (time.perf_counter() - t0)


def frame_cost(n: int, res: int, substeps: int, frames: int, device: str) -> dict:
    """The bake's forward (`fast`) at `substeps` and at 4x as many substeps a frame: a
    frame's time split into a fixed part (the guard's read, the host's turn between frames,
    the launches once a frame) and a part a substep, from the line through the two."""
    us = {}
    for s in (substeps, 4 * substeps):
        rate = time_forward(n, res, s, max(1, frames * substeps // s), device, "fast")
        us[s] = n * s / rate * 1e6
    per = (us[4 * substeps] - us[substeps]) / (3 * substeps)
    return {"frame_us": {str(k): v for k, v in us.items()}, "substep_us": per,
            "frame_fixed_us": us[substeps] - substeps * per}


def time_forward_backward(n: int, res: int, substeps: int, frames: int, device: str, segment: int | None,
                          backward: str = "adjoint", store: bool = True) -> tuple[float, float, dict]:
    """(forward, forward + backward) particle-substeps/s of the differentiable path, and the
    MB a stored frame takes (`stored_frame_mb`, packed on CUDA) against a dense slot's
    (`dense_frame_mb`); store: the forward keeps the frame's substeps for the backward where
    the budget allows."""
    x, vol, mass, E, static = make_block(n, res)
    cfg = SimConfig(grid_res=res, gravity=(0.0, 0.0, -9.81), segment=segment, backward=backward,
                    keep_budget_mb=None if store else 0)
    dsim = DiffSim(vol, mass, static, cfg, device=device)
    claim = dsim._claim_kept(substeps, x)  # held for the whole run: every frame reuses its slot
    kept = claim.slot if claim is not None else None
    xw = wp.array(x, dtype=wp.vec3, device=device)
    vw = wp.zeros(n, dtype=wp.vec3, device=device)
    Cw = wp.zeros(n, dtype=wp.mat33, device=device)
    Fw = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33, device=device)
    Ew = wp.array(E, dtype=float, device=device)
    forces = dsim.forces([])
    ones = wp.array(np.ones((n, 3), np.float32), dtype=wp.vec3, device=device)
    zv = wp.zeros(n, dtype=wp.vec3, device=device)
    zm = wp.zeros(n, dtype=wp.mat33, device=device)
    frame_dt = 1e-3

    outs = (wp.empty_like(xw), wp.empty_like(vw), wp.empty_like(Cw), wp.empty_like(Fw))

    def one_frame():
        # forward (no tape) + backward, as the autograd bridge runs them
        forward_frame(dsim, xw, vw, Cw, Fw, Ew, forces, 0.0, frame_dt, substeps, *outs, kept=kept).numpy()  # guard sync
        backward_frame(dsim, xw, vw, Cw, Fw, Ew, forces, 0.0, frame_dt, substeps, ones, zv, zm, zm, kept=kept)

    def forward_only():
        forward_frame(dsim, xw, vw, Cw, Fw, Ew, forces, 0.0, frame_dt, substeps, *outs, kept=kept).numpy()

    rates = []
    for fn in (forward_only, one_frame):
        fn()
        fn()  # a graph key's first run launches directly, its second captures (DiffSim._run_graphed)
        sync(device)
        t0 = time.perf_counter()
        for _ in range(frames):
            fn()
        sync(device)
        rates.append(n * substeps * frames / (time.perf_counter() - t0))
    mb = {}
    if kept is not None:
        mb = {"stored_frame_mb": kept.nbytes / 2**20 * substeps / kept.count,
              "dense_frame_mb": substeps * dsim._substep_bytes() / 2**20, "stored_frame_held": bool(kept.holds)}
    return rates[0], rates[1], mb


def check_adjoint(n: int, res: int, substeps: int, device: str, segment: int | None) -> float:
    """Largest relative difference (per gradient, relative to its max) between the
    hand-written and the taped backward of one frame from a moving, deformed state."""
    x, vol, mass, E, static = make_block(n, res)
    rng = np.random.default_rng(1)
    v = rng.normal(0, 0.3, (n, 3)).astype(np.float32)
    v[static] = 0
    F = (np.eye(3) + rng.normal(0, 0.02, (n, 3, 3))).astype(np.float32)
    cot = [rng.normal(0, 1, s).astype(np.float32) for s in ((n, 3), (n, 3), (n, 3, 3), (n, 3, 3))]
    grads = {}
    arr = lambda a, t: wp.array(a, dtype=t, device=device)  # noqa: E731
    for mode in ("adjoint", "tape"):
        cfg = SimConfig(grid_res=res, gravity=(0.0, 0.0, -9.81), segment=segment, backward=mode)
        dsim = DiffSim(vol, mass, static, cfg, device=device)

        def run(xx, vv, FF, cc):
            return backward_frame(dsim, arr(xx, wp.vec3), arr(vv, wp.vec3), wp.zeros(n, dtype=wp.mat33, device=device),
                                  arr(FF, wp.mat33), arr(E.astype(np.float32), float), dsim.forces([]), 0.0, 1e-3,
                                  substeps, arr(cc[0], wp.vec3), arr(cc[1], wp.vec3), arr(cc[2], wp.mat33),
                                  arr(cc[3], wp.mat33))

        # a first frame from other inputs: the compared one replays its captured graphs
        run(x[::-1].copy(), -v, F.transpose(0, 2, 1).copy(), [-c for c in cot])
        grads[mode] = [g.numpy().astype(np.float64) for g in run(x, v, F, cot)]
    return max(float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))
               for a, b in zip(grads["adjoint"], grads["tape"]))


def hardware(device: str) -> str:
    if device.startswith("cuda"):
        return wp.get_device(device).name
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(line.split(":", 1)[1].strip() for line in out.splitlines() if "Model name" in line)
    except Exception:
        return platform.processor()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--sizes", default=DEFAULT_SIZES, help="N:res pairs, comma separated")
    ap.add_argument("--substeps", type=int, default=None, help="substeps per frame (default 64 cuda, 8 cpu)")
    ap.add_argument("--frames", type=int, default=None, help="timed frames (default 10 cuda, 2 cpu)")
    ap.add_argument("--segment", type=int, default=None,
                    help="substeps per recomputed segment in backward (default: SimConfig's, the whole frame "
                         "within its memory budget)")
    ap.add_argument("--backward", choices=["adjoint", "tape", "both"], default="adjoint",
                    help="backward kernels: hand-written adjoints, warp's taped adjoints, or both")
    ap.add_argument("--no-backward", action="store_true", help="forward only")
    ap.add_argument("--ablation", action="store_true",
                    help="also time each optimisation alone (sort_only, fuse_only, graph_only)")
    ap.add_argument("--check", action="store_true",
                    help="also compare the hand-written backward with the taped one (max relative difference)")
    ap.add_argument("--frame-cost", action="store_true",
                    help="also time the fast forward at 4x the substeps a frame and split a frame's time into a "
                         "fixed part and a part a substep")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 20,000 particles on a 32-cell grid, 4 substeps, 1 frame")
    ap.add_argument("--kernel-options", default="", metavar="SPEC",
                    help="warp compile options per kernel before the first launch, e.g. "
                         "'gather.g2p2g_rows:cuda_max_registers=64;gather.*:grid_stride=0' (bench/kernel_ptx.py)")
    ap.add_argument("--json", type=Path, help="write results here")
    args = ap.parse_args(argv)
    try:
        applied = apply_kernel_options(args.kernel_options)
    except ValueError as e:
        ap.error(str(e))
    if args.quick:
        args.sizes, args.substeps, args.frames = "20000:32", 4, 1
    wp.config.quiet = True
    wp.init()
    cuda = args.device.startswith("cuda")
    substeps = args.substeps or (64 if cuda else 8)
    frames = args.frames or (10 if cuda else 2)
    rows = []
    for item in args.sizes.split(","):
        n, res = (int(v) for v in item.split(":"))
        row = {"particles": n, "grid": res, "substeps_per_frame": substeps, "frames": frames}
        variants = (["baseline", "sort_only", "fuse_only"] + (["graph_only"] if cuda else [])
                    + ["fast_scatter"] + (["fast_chunks"] if cuda else []) + ["fast"])
        if not args.ablation:
            variants = ["baseline"] + (["fast_scatter", "fast_chunks"] if cuda else []) + ["fast"]
        for v in variants:
            row[f"{v}_fwd"] = time_forward(n, res, substeps, frames, args.device, v)
        if not args.no_backward:
            modes = ["adjoint", "tape"] if args.backward == "both" else [args.backward]
            for mode in modes:
                key = "fwd_bwd" if mode == modes[0] else "fwd_bwd_tape"
                diff_fwd, row[key], mb = time_forward_backward(n, res, substeps, max(1, frames // 2), args.device,
                                                               args.segment, mode)
                if mode == modes[0]:
                    row.update(mb)
                if mode == modes[0]:
                    row["diff_fwd"] = diff_fwd
                    # the backward alone against the differentiable path's own forward
                    row["bwd_over_diff_fwd"] = diff_fwd / row[key] - 1.0
                if mode == "adjoint":
                    fwd, row["fwd_bwd_recompute"], _ = time_forward_backward(
                        n, res, substeps, max(1, frames // 2), args.device, args.segment, mode, store=False)
                    row["diff_fwd_recompute"] = fwd
                    row["bwd_over_diff_fwd_recompute"] = fwd / row["fwd_bwd_recompute"] - 1.0
            row["backward_kernels"] = modes[0]
            row["segment"] = args.segment
            row["bwd_over_fwd"] = row["fast_fwd"] / row["fwd_bwd"] - 1.0
        if args.frame_cost:
            row["frame_cost"] = fc = frame_cost(n, res, substeps, frames, args.device)
            print(f"  a frame of {substeps} substeps: {fc['frame_fixed_us']:.0f} us fixed + "
                  f"{fc['substep_us']:.1f} us a substep", flush=True)
        if args.check:
            row["adjoint_vs_tape_rel"] = check_adjoint(n, res, min(substeps, 16), args.device, args.segment)
            print(f"  adjoint vs tape: max relative difference {row['adjoint_vs_tape_rel']:.2e}", flush=True)
        rows.append(row)
        extra = "".join(f"  {v} {row[v + '_fwd']:.3e}" for v in variants if v not in ("baseline", "fast"))
        print(f"N={n:7d} grid={res:4d}^3  baseline {row['baseline_fwd']:.3e}{extra}  fast {row['fast_fwd']:.3e}"
              + (f"  diff fwd {row['diff_fwd']:.3e}  fwd+bwd {row['fwd_bwd']:.3e} (backward = "
                 f"{row['bwd_over_fwd']:.2f} x fast forward, {row['bwd_over_diff_fwd']:.2f} x its own forward)"
                 if "fwd_bwd" in row else "")
              + (f"  recomputed: diff fwd {row['diff_fwd_recompute']:.3e}  fwd+bwd {row['fwd_bwd_recompute']:.3e} "
                 f"(backward = {row['bwd_over_diff_fwd_recompute']:.2f} x its own forward)"
                 if "fwd_bwd_recompute" in row else "") + "  particle-substeps/s"
              + (f"; a stored frame {row['stored_frame_mb']:.0f} MB (dense {row['dense_frame_mb']:.0f})"
                 if "stored_frame_mb" in row else ""), flush=True)
    out = {"device": args.device, "hardware": hardware(args.device), "unit": "particle-substeps/s",
           "kernel_options": applied, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
