"""Stage-1 diagnostic: how far the fitted initial velocity lands from the true push, with E
frozen at the uniform start (what the fit does) and at the true E (an oracle), after N
stage-1 iterations on the first K frames.

    python bench/stage1_v0.py --gaussians 10000 --size 384 --json v0.json
    python bench/stage1_v0.py --device cuda --gaussians 100000 --frames1 3,5

Tells whether v0's error comes from the frozen E (the oracle row is much better) or from
stage 1 itself (both rows are off). Reports per run the relative error over the moving
drivers, its split by axis, and the gain: the fitted v0 projected on the true push,
divided by the push's norm (1: right size; below 1: too slow).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=10_000)
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--quality", default="default")
    ap.add_argument("--iters", default="60", help="stage-1 iterations, comma-separated list")
    ap.add_argument("--frames1", default="3", help="stage-1 frames, comma-separated list")
    ap.add_argument("--E", default="start,truth", help="E during stage 1: start (uniform init_E), truth")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import numpy as np
    import torch

    from bench.fit_recovery import plant_references, true_pushes
    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitProblem, FitSettings, _fit_round
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP, driver_truth_E, make_plant

    init_warp_quietly()
    if args.device == "cpu":
        torch.set_num_threads(1)
    overrides = {}
    for item in args.set:
        key, _, text = item.partition("=")
        overrides[key] = json.loads(text)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = save_splats(make_plant(args.gaussians, seed=0), tmp / "plant.ply")
        scene = load_splats(path, device=args.device)
        refs = plant_references(tmp, scene, views=args.views, size=args.size, quality=args.quality,
                                frames=14, fps=30.0, substeps=None, device=args.device)
        for e_kind in args.E.split(","):
            for frames1 in (int(f) for f in args.frames1.split(",")):
                for iters in (int(i) for i in args.iters.split(",")):
                    # stage 1 alone: the fit's own round with no stage-2 iterations
                    s = FitSettings(quality=args.quality, device=args.device, working_long_side=args.size,
                                    stage1_frames=frames1, velocity_iters=iters, material_iters=0,
                                    **overrides).resolved()
                    pb = FitProblem(scene, refs, PrepareOptions(static_below=POT_TOP), s)
                    if e_kind == "truth":
                        truth = torch.tensor(driver_truth_E(scene, pb.prep, pb.drivers), dtype=torch.float32,
                                             device=pb.device)
                        pb.driver_E = lambda truth=truth: truth
                    losses, seconds = {"velocity": [], "material": []}, {}
                    _fit_round(pb, s, 0, None, tmp / "stage1.ckpt", losses, seconds, None)
                    free = ~pb.static.cpu().numpy()
                    with torch.no_grad():  # after stage 1: moves only with stage1_level
                        e_after = float(pb.driver_E()[pb.static.logical_not()].median())
                    row = {"E": e_kind, "frames1": frames1, "iters": iters, "seconds": seconds["velocity"],
                           "loss_first": losses["velocity"][0], "loss_last": losses["velocity"][-1],
                           "E_median_after_Pa": e_after, "views": []}
                    for i, vt in enumerate(true_pushes(pb, args.views)):
                        with torch.no_grad():
                            vf = pb.driver_v0(i).double().cpu().numpy()[free]
                        vt = vt.double().cpu().numpy()[free]
                        n = np.linalg.norm(vt)
                        row["views"].append({
                            "rel_error": float(np.linalg.norm(vf - vt) / n),
                            "axis_error": (np.linalg.norm(vf - vt, axis=0) / n).tolist(),
                            "gain": float((vf * vt).sum() / n ** 2)})
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    out = {"device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
           "gaussians": args.gaussians, "size_px": args.size, "views": args.views, "quality": args.quality,
           "overrides": overrides, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
