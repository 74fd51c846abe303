"""Whole-fit time: a synthetic plant of N Gaussians, a 14-frame reference video at W x H,
both stages at a quality preset's iteration counts.

    python bench/fit_speed.py --device cuda --gaussians 100000 --width 1024 --height 576 --json fit.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=576)
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--quality", default="default")
    ap.add_argument("--velocity-iters", type=int, default=None)
    ap.add_argument("--material-iters", type=int, default=None)
    ap.add_argument("--quick", action="store_true", help="CPU scale: 1000 Gaussians, 96x54 px, 4 frames, draft, 3 iterations a stage")
    ap.add_argument("--recompute", action="store_true",
                    help="store no frame for the backward (SimConfig.keep_budget_mb 0): every backward "
                         "recomputes its frame, as a comparison")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.width, args.height, args.frames, args.quality = 1000, 96, 54, 4, "draft"
        args.velocity_iters, args.material_iters = 3, 3

    import numpy as np
    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_for_fit
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant
    from pd_tool.render.views import scene_camera

    init_warp_quietly()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene_path = save_splats(make_plant(args.gaussians, seed=0, thin=False), tmp / "plant.ply")
        from pd_tool.io import load_splats

        scene = load_splats(scene_path, device=args.device)
        cam = scene_camera(scene, width=args.width, height=args.height)
        t0 = time.perf_counter()
        video, truth, _ = plant_reference_for_fit(tmp / "video", scene, cam, args.quality, n_frames=args.frames,
                                                  device=args.device)
        t_video = time.perf_counter() - t0
        refs = [load_reference_video(video, working_size=max(args.width, args.height), device=args.device)]
        s = FitSettings(quality=args.quality, device=args.device, velocity_iters=args.velocity_iters,
                        material_iters=args.material_iters, working_long_side=max(args.width, args.height),
                        stored_frames_mb=0.0 if args.recompute else None)
        if args.device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        res = run_fit(scene, scene_path, refs, tmp / "plant.pdmat", prepare_options=PrepareOptions(static_below=POT_TOP),
                      settings=s)
        if args.device == "cuda":
            torch.cuda.synchronize()
        wall = time.perf_counter() - t0
        labels = scene.labels[res.prep.foreground]
        rec = {name: float(np.median(res.gaussian_E[labels == i])) for i, name in enumerate(REGIONS) if name != "pot"}
    rs = s.resolved()
    out = {
        "device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
        "gaussians": args.gaussians, "drivers": int(len(res.driver_E)), "frames": args.frames,
        "stored_frames": not args.recompute,
        "size": [args.width, args.height], "quality": args.quality,
        "velocity_iters": rs.velocity_iters, "material_iters": rs.material_iters,
        "fit_wall_s": wall, "stage_s": res.seconds, "reference_video_s": t_video,
        "loss_first": (res.losses["velocity"] or res.losses["material"])[0],
        "loss_last": (res.losses["material"] or res.losses["velocity"])[-1],
        "recovered_E": rec, "truth_E": {k: REGION_TRUTH_E[k] for k in rec},
        "losses": res.losses, "skipped_material_steps": res.skipped_steps, "driver_E_range": [float(res.driver_E.min()), float(res.driver_E.max())],
    }
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
