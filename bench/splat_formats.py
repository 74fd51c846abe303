"""Bytes per frame and write time of each bake output format on real captures.

One bake per scene writes every format in the same pass (`--format both,ply-seq,spz-seq,
gltf`): the USD file (instancer and splat prims), a .ply sequence, an .spz sequence and a
.glb flipbook. Each scene's bottom 15% is pinned (static splats are written once where the
format allows) and a gust moves the rest. Reported per scene and format: bytes per frame
(the file or folder over the frames) and the seconds spent writing it, per frame.

    python bench/splat_formats.py --quick                       # CPU, the udon capture, 4 frames
    python bench/splat_formats.py --json formats.json           # udon, donut, tree, the plant; 1 s at 30 fps
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"
SCENES = {"udon": "udon.ply", "donut": "donut_fused.ply", "tree": "tree_100k.splat", "plant": None}
FORMATS = ("usd", "ply-seq", "spz-seq", "gltf")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="udon,donut,tree,plant", help="comma-separated: " + ", ".join(SCENES))
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--quality", default="draft", help="the bake's quality (the formats do not depend on it)")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the real captures")
    ap.add_argument("--quick", action="store_true", help="CPU scale: udon only, 4 frames")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.seconds = "udon", 3 / 30

    from pd_tool.bake import BakeSettings, ForceSpec, bake
    from pd_tool.core.device import init_warp_quietly
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import make_plant
    from pd_tool.materials.presets import Material
    from pd_tool.prepare import PrepareOptions

    init_warp_quietly()
    rows = []
    print(f"{'scene':6} {'Gaussians':>9} {'frames':>6} " + " ".join(f"{f + ' MB/frame':>17} {'s/frame':>8}"
                                                                   for f in FORMATS))
    for name in args.scenes.split(","):
        scene = make_plant(30000, seed=0) if SCENES[name] is None else load_splats(args.data / SCENES[name])
        scene = scene.to(args.device)
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            res = bake(scene, Path(tmp) / "out.usd", force=ForceSpec.from_interaction("gust", (1.0, 0.0, 0.0),
                                                                                      units="size"),
                       material=Material.from_preset("jelly"), prepare_options=PrepareOptions(up_axis="auto",
                                                                                            static_below="15%"),
                       settings=BakeSettings(seconds=args.seconds, quality=args.quality, device=args.device,
                                             fmt="both", splat_formats=("ply-seq", "spz-seq", "gltf"),
                                             stop_at_rest=False))
            wall = time.perf_counter() - t0
        row = {"scene": name, "gaussians": scene.count, "frames": res.frames, "wall_s": wall,
               "bytes_per_frame": {f: res.output_bytes[f] / res.frames for f in FORMATS},
               "write_s_per_frame": {f: res.output_seconds[f] / res.frames for f in FORMATS}}
        rows.append(row)
        print(f"{name:6} {scene.count:9,d} {res.frames:6d} " + " ".join(
            f"{row['bytes_per_frame'][f] / 2**20:17.2f} {row['write_s_per_frame'][f]:8.3f}" for f in FORMATS),
            flush=True)
    if args.json:
        args.json.write_text(json.dumps({"device": args.device, "quality": args.quality, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
