"""Recovery of the plant's per-region E for several fit settings (a tuning sweep).

    python bench/fit_tune.py --device cuda --configs '[{"lr_residual": 0.05}, {"driver_residual": false, "stage1_level": false}]'
Each config is a dict of FitSettings overrides; prints and writes recovered median E per
region, the loss curve and the time.
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
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--quality", default="draft")
    ap.add_argument("--configs", default="[{}]")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    import numpy as np
    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitSettings, run_fit
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_for_fit
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant
    from pd_tool.render.views import scene_camera

    init_warp_quietly()
    if args.device == "cpu":
        torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = save_splats(make_plant(args.gaussians, seed=0), tmp / "plant.ply")
        scene = load_splats(path, device=args.device)
        cam = scene_camera(scene, width=args.size, height=args.size)
        video, _, _ = plant_reference_for_fit(tmp / "video", scene, cam, args.quality, n_frames=args.frames,
                                              device=args.device)
        refs = [load_reference_video(video, working_size=args.size, device=args.device)]
        labels = scene.labels
        for cfg in json.loads(args.configs):
            s = FitSettings(quality=args.quality, device=args.device, working_long_side=args.size, **cfg)
            t0 = time.perf_counter()
            r = run_fit(scene, path, refs, tmp / "m.pdmat", prepare_options=PrepareOptions(static_below=POT_TOP),
                        settings=s)
            lab = labels[r.prep.foreground]
            rec = {n: float(np.median(r.gaussian_E[lab == i])) for i, n in enumerate(REGIONS) if n != "pot"}
            err = {n: abs(np.log(rec[n] / REGION_TRUTH_E[n])) for n in rec}
            row = {"config": cfg, "recovered": rec, "abs_log_err": err, "stem_over_leaf": rec["stem"] / rec["leaf"],
                   "loss_first": r.losses["velocity"][0] if r.losses["velocity"] else None,
                   "loss_last": (r.losses["material"] or r.losses["velocity"])[-1],
                   "seconds": time.perf_counter() - t0}
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
