"""How far each material preset moves under each interaction, with --force 1 in object sizes/s^2.

Every (scene, material preset, interaction) is baked as `pdtool bake --force ... --pin auto`
would bake it, with one object size per s^2 of acceleration sideways (the scene's horizontal axis that the up
guess leaves) and reports the peak displacement of any Gaussian as a percentage of the
object's longest side. The goal: plainly visible, plausible motion, a few percent of the
object, for `--force 0,0,1` whatever the capture's scale.

    python bench/force_presets.py --device cuda --data ../shared/data --json presets.json
    python bench/force_presets.py --quick                 # CPU: the plant, two presets
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from pd_tool import app
from pd_tool.bake import BakeSettings, ForceSpec
from pd_tool.io import load_splats, save_splats
from pd_tool.io.synthetic import make_plant
from pd_tool.materials.presets import builtin
from pd_tool.prepare.orient import guess_up

SCENES = {"plant": None, "udon": "udon.ply", "donut": "donut_fused.ply", "tree": "tree_100k.splat"}
INTERACTIONS = ("none", "poke", "gust", "drag")


def sideways(up: str) -> tuple[float, float, float]:
    """A unit push along the first scene axis that is not the up axis."""
    axis = 1 if up[1] == "x" else 0
    v = [0.0, 0.0, 0.0]
    v[axis] = 1.0
    return tuple(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--presets", default=",".join(builtin("materials")))
    ap.add_argument("--interactions", default=",".join(INTERACTIONS))
    ap.add_argument("--quality", default="default")
    ap.add_argument("--seconds", type=float, default=1.5)
    ap.add_argument("--gaussians", type=int, default=20000, help="the plant's size")
    ap.add_argument("--quick", action="store_true", help="CPU scale: a 2,000-Gaussian plant, draft, two presets")
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    if a.quick:
        a.scenes, a.presets, a.interactions, a.quality, a.seconds, a.gaussians = \
            "plant", "flower,jelly", "none,poke", "draft", 0.5, 2000

    work = Path(tempfile.mkdtemp(prefix="pdtool-force-presets-"))
    rows = []
    for name in a.scenes.split(","):
        path = work / "plant.ply" if SCENES[name] is None else a.data / SCENES[name]
        if SCENES[name] is None:
            save_splats(make_plant(a.gaussians, seed=0), path)
        scene = load_splats(path)
        up = guess_up(scene.positions.double().numpy(), scene.scales.double().numpy(),
                      scene.opacities.double().numpy()).axis
        size = float(np.ptp(scene.positions.double().numpy(), axis=0).max())
        for preset in a.presets.split(","):
            for interaction in a.interactions.split(","):
                accel = sideways(up)
                force = (ForceSpec(accel=accel, units="size") if interaction == "none" else
                         ForceSpec.from_interaction(interaction, accel, units="size"))
                job = app.BakeJob(work / f"{name}_{preset}_{interaction}.usd", force,
                                  BakeSettings(seconds=a.seconds, fps=30, quality=a.quality, fmt="instancer",
                                               device=a.device),
                                  scene=path, preset=preset, prepare={"pin": "auto", "up_axis": up})
                t0 = time.perf_counter()
                try:
                    res = app.bake(job, max_minutes=None)
                    peak, error = 100.0 * res.peak_displacement / size, None
                except Exception as e:  # a refusal is a result here (the force guard, memory)
                    peak, error = float("nan"), f"{type(e).__name__}: {e}"
                rows.append({"scene": name, "preset": preset, "interaction": interaction, "up": up,
                             "peak_percent": peak, "seconds": time.perf_counter() - t0, "error": error})
                print(f"{name:<6} {preset:<12} {interaction:<6} peak {peak:6.2f}% of the object"
                      + (f"  {error[:120]}" if error else ""), flush=True)
    if a.json:
        a.json.write_text(json.dumps({"device": a.device, "quality": a.quality, "force": 1.0, "units": "size",
                                      "seconds": a.seconds, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
