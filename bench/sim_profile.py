"""Where a fast-path MPM substep spends its GPU time: per-kernel CUDA times (warp's
activity timing), the scatter P2G against the chunk launch and the shipped warp sums, without CUDA graphs (timing needs
plain launches; a graph replays the same kernels). --backward profiles the differentiable
path's backward of a frame instead (hand-written adjoints), with its wall time per substep,
so that host launch overhead shows as the gap between the two. --scene profiles a bake's own
solver instead of the block: the procedural plant (`plant`, `thin` for 3 mm leaves, raised to
the finer grid as a bake raises it) or a capture (`udon`, `donut`, `tree` from --data), poked
as bench/bake_speed.py pokes it, at --quality.

    python bench/sim_profile.py --device cuda --sizes 100000:64 --json profile.json
    python bench/sim_profile.py --device cuda --sizes 100000:64 --backward
    python bench/sim_profile.py --device cuda --scene thin --gaussians 300000
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
from collections import defaultdict
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from pd_tool.io.synthetic import make_block  # noqa: E402  (the scene of bench/sim_speed.py)
from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402
from kernel_ptx import apply_kernel_options  # noqa: E402


def hardware(device: str) -> str:
    """The GPU's name (a profile is a GPU's), else the CPU's as Python knows it."""
    return wp.get_device(device).name if device.startswith("cuda") else platform.processor() or platform.machine()


def profile(n: int, res: int, substeps: int, frames: int, device: str, gather: bool, warp_sums: bool = True) -> dict:
    x, vol, mass, E, static = make_block(n, res)
    cfg = SimConfig(grid_res=res, substeps=substeps)
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, cuda_graph=False, gather_p2g=gather,
                    warp_sums=warp_sums)
    sim.step_frame(1e-3)
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)
    for _ in range(frames):
        sim.step_frame(1e-3)
    return per_kernel(wp.timing_end(), substeps * frames)


def per_kernel(results, total_substeps: int) -> dict:
    """warp timing results summed per kernel name: us per substep and call count, slowest first."""
    per = defaultdict(float)
    calls = defaultdict(int)
    for r in results:
        per[r.name] += r.elapsed
        calls[r.name] += 1
    return {name: {"us_per_substep": 1e3 * t / total_substeps, "calls": calls[name]}
            for name, t in sorted(per.items(), key=lambda kv: -kv[1])}


def bake_inputs(name: str, gaussians: int, device: str, data: Path):
    """(scene, PrepareOptions) as the bake benchmarks use them: the plant with its pot
    static, or a capture with its lowest tenth static (bench/convergence.py's cases)."""
    from pd_tool.io.synthetic import POT_TOP, make_plant
    from pd_tool.prepare.preparation import PrepareOptions

    if name in ("plant", "thin"):
        return make_plant(gaussians, seed=0, device=device, thin=name == "thin"), PrepareOptions(static_below=POT_TOP)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from convergence import CASES, load_scene, pinned_below

    scene = load_scene(name, gaussians, data=data).to(device)
    return scene, PrepareOptions(up_axis=CASES[name].up, static_below=pinned_below(scene, CASES[name]))


def profile_bake(name: str, gaussians: int, quality: str, frames: int, device: str, data: Path) -> dict:
    """Per-kernel GPU time (us per substep) of a bake's solver over `frames` frames from the
    poke's start, without CUDA graphs; with the solver's size and the share of the grid's
    activity blocks that the last substep visited."""
    import tempfile

    import numpy as np

    from pd_tool.bake.baker import Baker, BakeSettings, ForceSpec
    from pd_tool.materials.presets import Material

    scene, opts = bake_inputs(name, gaussians, device, data)
    with tempfile.TemporaryDirectory() as tmp, Baker(
            scene, Path(tmp) / "out.usd", force=ForceSpec.from_interaction("poke", (20.0, 0.0, 0.0)),
            material=Material.from_preset("flower"), prepare_options=opts,
            settings=BakeSettings(seconds=(frames + 1) / 30.0, quality=quality, device=device,
                                  stop_at_rest=False)) as baker:
        sim = baker.solver
        sim._use_graphs = False
        substeps = sim.step_frame(baker.frame_dt)
        wp.synchronize_device(device)
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)
        counts = [sim.step_frame(baker.frame_dt) for _ in range(frames)]
        kernels = per_kernel(wp.timing_end(), sum(counts))
        # the binned P2G's tags (CUDA): the last substep's is the last frame's substep count
        active = float(np.mean(sim.grid.blocks.numpy() == counts[-1])) if sim._gather else None
        return {"particles": sim.n, "grid": list(baker.prep.grid_dims), "substeps_per_frame": substeps,
                "active_blocks": active, "kernels": kernels}


def profile_backward(n: int, res: int, substeps: int, frames: int, device: str, segment: int | None) -> dict:
    """Per-kernel GPU time and wall time (us per substep) of backward_frame for a frame not
    stored by its forward (the recompute, then the adjoints), without CUDA graphs (the
    activity timing needs plain launches). A stored frame's backward is the adjoints' rows
    plus the copies of its stored states and tagged grid blocks."""
    import time

    import numpy as np

    from pd_tool.sim import DiffSim
    from pd_tool.sim.autograd import backward_frame

    x, vol, mass, E, static = make_block(n, res)
    dsim = DiffSim(vol, mass, static, SimConfig(grid_res=res, segment=segment), device=device)
    dsim.cuda_graph = False
    arr = lambda a, t: wp.array(np.asarray(a, np.float32), dtype=t, device=device)  # noqa: E731
    args = [arr(x, wp.vec3), wp.zeros(n, dtype=wp.vec3, device=device), wp.zeros(n, dtype=wp.mat33, device=device),
            arr(np.tile(np.eye(3), (n, 1, 1)), wp.mat33), arr(E, float), dsim.forces([]), 0.0, 1e-3, substeps,
            arr(np.ones((n, 3)), wp.vec3), wp.zeros(n, dtype=wp.vec3, device=device),
            wp.zeros(n, dtype=wp.mat33, device=device), wp.zeros(n, dtype=wp.mat33, device=device)]
    backward_frame(dsim, *args)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    for _ in range(frames):
        backward_frame(dsim, *args)
    wp.synchronize_device(device)
    wall = (time.perf_counter() - t0) / (frames * substeps) * 1e6
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET | wp.TIMING_MEMCPY)
    for _ in range(frames):
        backward_frame(dsim, *args)
    return {"wall_us_per_substep": wall, "kernels": per_kernel(wp.timing_end(), frames * substeps)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", default="100000:64")
    ap.add_argument("--substeps", type=int, default=32)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--blocks", default="", help="PARTICLE:CELL block sizes to sweep for the chunk "
                    "launch's P2G, comma separated, e.g. 256:256,128:128 (default: the module's)")
    ap.add_argument("--backward", action="store_true", help="profile the differentiable backward instead")
    ap.add_argument("--segment", type=int, default=None, help="backward: substeps per recomputed segment "
                    "(default SimConfig's)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 20,000 particles on a 32-cell grid, 4 substeps, 1 frame")
    ap.add_argument("--scene", default=None, help="profile a bake's solver on this scene instead: plant, thin, "
                    "udon, donut or tree")
    ap.add_argument("--gaussians", type=int, default=300_000, help="--scene: Gaussians (a capture is subsampled)")
    ap.add_argument("--quality", default="default", help="--scene: the bake's quality")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data",
                    help="--scene: the folder holding the captures")
    ap.add_argument("--chunk", type=int, default=None, help="particles per chunk of the chunked P2G "
                    "(gather.CHUNK; compile-time, one value per process)")
    ap.add_argument("--kernel-options", default="", metavar="SPEC",
                    help="warp compile options per kernel before the first launch, e.g. "
                         "'gather.g2p2g_rows:cuda_max_registers=64;gather.*:grid_stride=0' (bench/kernel_ptx.py)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    try:
        applied = apply_kernel_options(args.kernel_options)
    except ValueError as e:
        ap.error(str(e))
    from pd_tool.sim import gather as G

    if args.chunk:  # before the first launch compiles the module
        G.CHUNK, G.CHUNK_W = args.chunk, wp.constant(args.chunk)
    if args.quick:
        args.sizes, args.substeps, args.frames = "20000:32", 4, 1
    wp.config.quiet = True
    wp.init()
    out = {"hardware": hardware(args.device), "kernel_options": applied, "rows": []}
    if args.scene:
        row = profile_bake(args.scene, args.gaussians, args.quality, args.frames, args.device, args.data)
        out["rows"].append({"scene": args.scene, "gaussians": args.gaussians, "quality": args.quality, **row})
        gpu = sum(k["us_per_substep"] for k in row["kernels"].values())
        active = "" if row["active_blocks"] is None else f", {100 * row['active_blocks']:.1f}% of the activity blocks visited"
        print(f"{args.scene} ({args.gaussians} Gaussians, {args.quality}): {row['particles']} particles, grid "
              f"{row['grid']}, {row['substeps_per_frame']} substeps a frame{active}: {gpu:.1f} us/substep"
              + (" (kernel times need CUDA)" if not args.device.startswith("cuda") else ""))
        for name, k in row["kernels"].items():
            print(f"    {k['us_per_substep']:8.2f} us  {name} ({k['calls']} calls)")
        if args.json:
            args.json.write_text(json.dumps(out, indent=1))
        return 0
    if args.backward:
        for item in args.sizes.split(","):
            n, res = (int(v) for v in item.split(":"))
            prof = profile_backward(n, res, args.substeps, args.frames, args.device, args.segment)
            out["rows"].append({"particles": n, "grid": res, "segment": args.segment, **prof})
            gpu = sum(k["us_per_substep"] for k in prof["kernels"].values())
            print(f"N={n} grid={res}^3 backward: wall {prof['wall_us_per_substep']:.1f} us/substep, "
                  f"GPU {gpu:.1f} us/substep")
            for name, k in prof["kernels"].items():
                print(f"    {k['us_per_substep']:8.2f} us  {name} ({k['calls']} calls)")
        if args.json:
            args.json.write_text(json.dumps(out, indent=1))
        return 0
    blocks = [tuple(int(v) for v in b.split(":")) for b in args.blocks.split(",") if b]
    for item in args.sizes.split(","):
        n, res = (int(v) for v in item.split(":"))
        # the scatter, the chunk launch, then the shipped warp sums (whose block is fixed)
        runs = ([(False, False, None)] + [(True, False, b) for b in (blocks or [None])]
                + [(True, True, None)])
        for gather, warp_sums, block in runs:
            if block is not None:
                G.PARTICLE_BLOCK, G.CELL_BLOCK = block
            prof = profile(n, res, args.substeps, args.frames, args.device, gather, warp_sums)
            out["rows"].append({"particles": n, "grid": res, "gather": gather, "warp_sums": warp_sums, "blocks": block,
                                "kernels": prof})
            total = sum(k["us_per_substep"] for k in prof.values())
            label = "warp sums" if warp_sums else ("chunks" if gather else "scatter")
            print(f"N={n} grid={res}^3 {label}{'' if block is None else f' blocks {block}'}: {total:.1f} us/substep")
            for name, k in prof.items():
                print(f"    {k['us_per_substep']:8.2f} us  {name} ({k['calls']} calls)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
