"""Where a fast-path MPM substep spends its GPU time: per-kernel CUDA times (warp's
activity timing), scatter P2G against the gather P2G, without CUDA graphs (timing needs
plain launches; a graph replays the same kernels).

    python bench/sim_profile.py --device cuda --sizes 100000:64 --json profile.json
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402
from sim_speed import hardware, make_block  # noqa: E402


def profile(n: int, res: int, substeps: int, frames: int, device: str, gather: bool) -> dict:
    x, vol, mass, E, static = make_block(n, res)
    cfg = SimConfig(grid_res=res, substeps=substeps)
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, cuda_graph=False, gather_p2g=gather)
    sim.step_frame(1e-3)
    wp.synchronize_device(device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMSET)
    for _ in range(frames):
        sim.step_frame(1e-3)
    results = wp.timing_end()
    per = defaultdict(float)
    calls = defaultdict(int)
    for r in results:
        per[r.name] += r.elapsed
        calls[r.name] += 1
    total_substeps = substeps * frames
    return {name: {"us_per_substep": 1e3 * t / total_substeps, "calls": calls[name]}
            for name, t in sorted(per.items(), key=lambda kv: -kv[1])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--sizes", default="100000:64")
    ap.add_argument("--substeps", type=int, default=32)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--blocks", default="", help="PARTICLE:CELL block sizes to sweep for the binned "
                    "P2G, comma separated, e.g. 256:256,128:128 (default: the module's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    out = {"hardware": hardware(args.device), "rows": []}
    from pd_tool.sim import gather as G

    blocks = [tuple(int(v) for v in b.split(":")) for b in args.blocks.split(",") if b]
    for item in args.sizes.split(","):
        n, res = (int(v) for v in item.split(":"))
        runs = [(False, None)] + [(True, b) for b in (blocks or [None])]
        for gather, block in runs:
            if block is not None:
                G.PARTICLE_BLOCK, G.CELL_BLOCK = block
            prof = profile(n, res, args.substeps, args.frames, args.device, gather)
            out["rows"].append({"particles": n, "grid": res, "gather": gather, "blocks": block, "kernels": prof})
            total = sum(k["us_per_substep"] for k in prof.values())
            label = "gather" if gather else "scatter"
            print(f"N={n} grid={res}^3 {label}{'' if block is None else f' blocks {block}'}: {total:.1f} us/substep")
            for name, k in prof.items():
                print(f"    {k['us_per_substep']:8.2f} us  {name} ({k['calls']} calls)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
