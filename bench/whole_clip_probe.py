"""Probe the whole-clip loss around a fit: how sharply it depends on a global E factor,
on v0's speed, and on the substep count, and how many substeps the CFL condition gives the
fitted E against the true one.

    python bench/whole_clip_probe.py --gaussians 3000 --size 192 --quality draft --json probe.json

Runs stages 1 and 2 (one video), then evaluates the loss (mean over every frame) at the
fitted (E, v0) and at the truth, each scaled by exp(d) in E and by a gain in v0, and the
truth with the substep count forced up to the fitted E's count. Prints the fitted E's
percentiles per region (the stiffest driver sets the CFL count).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--size", type=int, default=192)
    ap.add_argument("--quality", default="draft")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import numpy as np
    import torch

    from bench.fit_recovery import plant_references, true_pushes
    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitProblem, FitSettings, _fit_round, sequence_loss
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP, REGIONS, driver_regions, driver_truth_E, make_plant

    init_warp_quietly()
    if args.device == "cpu":
        torch.set_num_threads(1)
    out: dict = {"device": args.device, "gaussians": args.gaussians, "size_px": args.size, "quality": args.quality}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = save_splats(make_plant(args.gaussians, seed=0), tmp / "plant.ply")
        scene = load_splats(path, device=args.device)
        refs = plant_references(tmp, scene, views=1, size=args.size, quality=args.quality, frames=14, fps=30.0,
                                substeps=None, device=args.device)
        s = FitSettings(quality=args.quality, device=args.device, working_long_side=args.size).resolved()
        pb = FitProblem(scene, refs, PrepareOptions(static_below=POT_TOP), s)
        _fit_round(pb, s, 0, None, tmp / "fit.ckpt", {"velocity": [], "material": []}, {}, None)
        with torch.no_grad():
            f32 = dict(dtype=torch.float32, device=pb.device)
            fitted = (pb.driver_E(), pb.driver_v0(0))
            truth = (torch.tensor(driver_truth_E(scene, pb.prep, pb.drivers), **f32), true_pushes(pb, 1)[0])
            region = torch.as_tensor(driver_regions(scene, pb.prep, pb.drivers), device=pb.device)
            out["fitted_E_percentiles_pa"] = {}
            for r, name in enumerate(REGIONS):
                sel = (region == r) & ~pb.static
                if sel.any():
                    e = fitted[0][sel].double().cpu().numpy()
                    out["fitted_E_percentiles_pa"][name] = dict(zip(("p1", "p50", "p99", "max"),
                                                                    np.percentile(e, [1, 50, 99, 100]).tolist()))
            for name, (E, v) in (("fitted", fitted), ("truth", truth)):
                out[name] = {"substeps": pb.substeps(E, v), "loss_vs_log_E_factor": {}, "loss_vs_v0_gain": {}}
                for d in (-0.2, -0.1, -0.05, -0.02, 0.0, 0.02, 0.05, 0.1, 0.2):
                    out[name]["loss_vs_log_E_factor"][d] = float(sequence_loss(pb, E * math.exp(d), [v], None))
                for g in (0.9, 0.95, 1.0, 1.05, 1.1):
                    out[name]["loss_vs_v0_gain"][g] = float(sequence_loss(pb, E, [v * g], None))
            out["truth"]["loss_vs_substeps"] = {}
            base = out["truth"]["substeps"]
            for n in sorted({base, (base + out["fitted"]["substeps"]) // 2, out["fitted"]["substeps"], 2 * base}):
                pb.sim.config.min_substeps = n  # a floor: forces the count up
                out["truth"]["loss_vs_substeps"][n] = float(sequence_loss(pb, truth[0], [truth[1]], None))
            pb.sim.config.min_substeps = None
    text = json.dumps(out, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text)


if __name__ == "__main__":
    main()
