"""Diagnostic: the fit's loss and stage-2 gradient around the synthetic plant's true E.

The recovery benchmark fits the stem too soft in every run (1.4-2.4e6 Pa against 3e6). This
asks whether the fit's own objective puts its minimum there, with nothing else wrong: the
true initial velocity of every video, every other region at its true E, and one region's E
scaled. It prints, per scale, the mean frame loss over every frame of every video, with the
substep count chosen by CFL for that E (as the fit does) and held at the truth's count; and,
at the truth and at the fit's uniform start, d loss / d ln E per region as stage 2 computes
it (gradient horizon 1, the default) and through every frame (horizon 0). A minimum away from scale 1, or a gradient at
the truth that is not near zero, is a bias in the objective rather than in the optimiser.

    python bench/loss_landscape.py --gaussians 10000 --size 384 --region stem --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def with_substeps(pb, n: int | None):
    """pb with its substep count held at n per frame (None: CFL for each E, as the fit does)."""
    if n is None:
        pb.__dict__.pop("substeps", None)
    else:
        pb.substeps = lambda E, v0: n
    return pb


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=10_000)
    ap.add_argument("--size", type=int, default=384, help="reference frames' long side, px")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--quality", default="default")
    ap.add_argument("--region", default="stem", help="the region whose E is scaled")
    ap.add_argument("--scales", default="0.5,0.7,0.85,1,1.2,1.5")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import torch

    from fit_recovery import plant_references, true_pushes
    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitProblem, FitSettings, sequence_loss
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP, REGIONS, driver_regions, driver_truth_E, make_plant

    init_warp_quietly()
    if args.device == "cpu":
        torch.set_num_threads(1)
    t0 = time.perf_counter()
    settings = FitSettings(quality=args.quality, device=args.device, working_long_side=args.size).resolved()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = save_splats(make_plant(args.gaussians, seed=0), tmp / "plant.ply")
        scene = load_splats(path, device=args.device)
        refs = plant_references(tmp, scene, views=args.views, size=args.size, quality=args.quality,
                                frames=args.frames, fps=30.0, substeps=None, device=args.device)
        pb = FitProblem(scene, refs, PrepareOptions(static_below=POT_TOP), settings)
    region = driver_regions(scene, pb.prep, pb.drivers)
    truth = torch.tensor(driver_truth_E(scene, pb.prep, pb.drivers), dtype=torch.float32, device=pb.device)
    v0s = true_pushes(pb, args.views)
    target = REGIONS.index(args.region)
    in_region = torch.tensor(region == target, device=pb.device)
    truth_sub = [pb.substeps(truth, v) for v in v0s]
    rows = []
    with torch.no_grad():
        for s in [float(v) for v in args.scales.split(",")]:
            E = torch.where(in_region, truth * s, truth)
            row = {"scale": s, "substeps_cfl": pb.substeps(E, v0s[0]),
                   "loss_cfl": float(sequence_loss(with_substeps(pb, None), E, v0s, 1)),
                   "loss_truth_substeps": float(sequence_loss(with_substeps(pb, truth_sub[0]), E, v0s, 1))}
            with_substeps(pb, None)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    grads = {}
    start = torch.full_like(truth, settings.init_E)
    for at, base in (("truth", truth), ("uniform_start", start)):
        for name, horizon in (("horizon_1", 1), ("every_frame", None)):
            log_scale = torch.zeros(len(REGIONS), device=pb.device, requires_grad=True)
            E = base * torch.exp(log_scale[torch.as_tensor(region, device=pb.device)])
            sequence_loss(pb, E, v0s, horizon).backward()
            grads[f"{at}/{name}"] = {n: float(g) for n, g in zip(REGIONS, log_scale.grad) if n != "pot"}
            print(json.dumps({f"{at}/{name}": grads[f"{at}/{name}"]}), file=sys.stderr, flush=True)
    out = {"device": args.device, "gaussians": args.gaussians, "size_px": args.size, "views": args.views,
           "quality": args.quality, "region": args.region, "truth_substeps": truth_sub, "landscape": rows,
           "dloss_dlnE": grads, "wall_s": time.perf_counter() - t0,
           "drivers_per_region": {n: int((region == i).sum()) for i, n in enumerate(REGIONS)}}
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
