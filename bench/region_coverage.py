"""How much of the recovery benchmark's first view each region of the synthetic plant
covers, at several Gaussian counts.

    python bench/region_coverage.py --gaussians 10000 30000 100000 --json coverage.json

Each region is rendered in colour 1 and every other Gaussian in colour 0 on a black
background, so a pixel's value is the share of it that the region contributes after
occlusion; the sum over the frame is the region's coverage in pixels. The plant's
Gaussians scale with its point spacing, so the same thin leaves are drawn wider by fewer,
larger Gaussians: this measures by how much (docs/benchmarks.md, "What separates 10k from
100k").
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def region_coverage(n: int, width: int, height: int, device: str) -> dict[str, float]:
    """Pixels (fractional, occlusion included) each region of an n-Gaussian plant covers in
    the benchmark's view 0 at width x height."""
    import numpy as np
    import torch

    from pd_tool.render.api import render
    from pd_tool.core.scene import rgb_to_sh
    from pd_tool.io.synthetic import REGIONS, make_plant
    from pd_tool.render.views import scene_camera

    scene = make_plant(n, seed=0).to(device)
    cam = scene_camera(scene, width=width, height=height)
    labels = np.asarray(scene.labels)
    out = {}
    for i, name in enumerate(REGIONS):
        colour = torch.from_numpy((labels == i).astype(np.float32)).to(scene.positions.device)
        sh = rgb_to_sh(colour[:, None, None].expand(-1, 1, 3)).contiguous()
        img = render(scene.positions, scene.quats, scene.scales, scene.opacities, sh, cam).rgb
        out[name] = float(img[..., 0].sum())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, nargs="+", default=[10_000, 30_000, 100_000])
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--height", type=int, default=576)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from pd_tool.core.device import init_warp_quietly

    init_warp_quietly()
    rows = []
    for n in args.gaussians:
        px = region_coverage(n, args.width, args.height, args.device)
        total = sum(px.values())
        rows.append({"gaussians": n, "pixels": px, "share": {k: v / total for k, v in px.items()}})
        print(f"{n:>8} Gaussians: " + ", ".join(f"{k} {v:.0f} px ({100 * v / total:.1f}%)" for k, v in px.items()))
    if args.json:
        args.json.write_text(json.dumps({"width": args.width, "height": args.height, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
