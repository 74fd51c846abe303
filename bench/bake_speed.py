"""Bake time and peak memory for one second of animation of a synthetic plant or a capture.

    python bench/bake_speed.py --device cuda --gaussians 300000 --json bake.json
    python bench/bake_speed.py --device cuda --scene tree --json tree.json   # udon, donut, tree

Times the whole `pd_tool.bake.baker.bake` call (after a warm-up bake that compiles the kernels)
and its parts: setup (preparation, K-Means, nearest drivers), simulation, interpolation,
USD writing. Peak memory: host RSS (ru_maxrss) and, on CUDA, torch's peak allocation and
the device memory the bake took and kept (torch's cache and warp's mempool), beside the
estimate the bake checked before it started (pd_tool.prepare.memory).
"""
from __future__ import annotations

import argparse
import cProfile
import io
import json
import pstats
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=300_000)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--quality", default="default")
    ap.add_argument("--fmt", default="instancer")
    ap.add_argument("--preset", default="flower")
    ap.add_argument("--thin", action="store_true", help="the plant with 3 mm leaves and petals (make_plant(thin=True))")
    ap.add_argument("--scene", default=None, help="a capture instead of the plant: udon, donut or tree (at most "
                    "--gaussians of it; its lowest tenth static, as bench/convergence.py pins it)")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data",
                    help="--scene: the folder holding the captures")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 3000 Gaussians, 0.2 s of animation, draft")
    ap.add_argument("--profile", type=Path, help="also write cProfile's 60 costliest calls (cumulative), then the 40 with the most own time, of the timed "
                    "bake to this text file; set CUDA_LAUNCH_BLOCKING=1 so that GPU work is charged where it is launched")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.seconds, args.quality = 3000, 0.2, "draft"

    import torch

    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.core.device import init_warp_quietly
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material
    from pd_tool.io.synthetic import POT_TOP, make_plant

    init_warp_quietly()
    if args.scene:
        from sim_profile import bake_inputs

        scene, opts = bake_inputs(args.scene, args.gaussians, args.device, args.data)
    else:
        scene, opts = make_plant(args.gaussians, seed=0, device=args.device, thin=args.thin), \
            PrepareOptions(static_below=POT_TOP)
    kw = dict(force=ForceSpec.from_interaction("poke", (20.0, 0.0, 0.0)), material=Material.from_preset(args.preset))
    with tempfile.TemporaryDirectory() as tmp:
        bake(make_plant(2000, seed=1, device=args.device, thin=False), Path(tmp) / "warm.usd",
             prepare_options=PrepareOptions(static_below=POT_TOP),
             settings=BakeSettings(seconds=0.1, fps=args.fps, quality=args.quality, fmt=args.fmt,
                                   device=args.device), **kw)
        if args.device == "cuda":
            torch.cuda.reset_peak_memory_stats()
            free_before = torch.cuda.mem_get_info()[0]
        profiler = cProfile.Profile() if args.profile else None
        if profiler:
            profiler.enable()
        t0 = time.perf_counter()
        res = bake(scene, Path(tmp) / "out.usd", prepare_options=opts,
                   settings=BakeSettings(seconds=args.seconds, fps=args.fps, quality=args.quality, fmt=args.fmt,
                                         device=args.device, stop_at_rest=False), **kw)
        wall = time.perf_counter() - t0
        # what the bake took from the device and kept (torch's cache and warp's mempool hold
        # their high-water marks): the device peak as closely as the process can see it
        device_taken = (free_before - torch.cuda.mem_get_info()[0]) / 2**20 if args.device == "cuda" else None
        if profiler:
            profiler.disable()
            text = io.StringIO()
            stats = pstats.Stats(profiler, stream=text)
            stats.sort_stats("cumulative").print_stats(60)
            stats.sort_stats("tottime").print_stats(40)  # where the host itself spends it
            args.profile.write_text(text.getvalue())
        size = res.bytes_written
    out = {
        "device": args.device,
        "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
        "scene": args.scene or "plant", "gaussians": scene.count, "thin": args.thin, "report": res.report, "drivers": res.drivers, "frames": res.frames,
        "substeps_per_frame": res.substeps_per_frame, "quality": args.quality, "fmt": args.fmt,
        "wall_s": wall, "timings_s": res.timings, "setup_parts_s": res.setup_parts,
        "output_seconds": res.output_seconds,
        "sim_plus_interp_s": res.timings["simulate"] + res.timings["interpolate"],
        "file_bytes": size, "bytes_per_frame": size / res.frames,
        "host_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "cuda_peak_torch_mb": torch.cuda.max_memory_allocated() / 2**20 if args.device == "cuda" else None,
        "cuda_taken_mb": device_taken,
        "estimate_mb": {"host": res.memory_estimate.host / 2**20, "device": res.memory_estimate.device / 2**20},
    }
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
