"""What writing the static Gaussians once saves in a baked USD file.

Bakes a scene through `pdtool bake` (default quality, `--format both`, 2 s), then reads every
frame's instance poses back and writes the same frames again twice with UsdBakeWriter: with
the bake's static mask, and as one time-sampled prim (`static=None`). Both rewrites carry
degree-0 SH, so they compare with each other; the bake's own file carries the scene's SH.

    python bench/usd_static_split.py --json split.json                      # the 3 mm plant, 30k
    python bench/usd_static_split.py --scene ../shared/data/donut_fused.ply --preset jelly \\
        --interaction poke --force 0,0,-3 --static-below 0.01 --json donut.json
    python bench/usd_static_split.py --quick                                # CI scale
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
MIB = 2.0 ** 20
FPS = 30.0  # the bake's and both rewrites'


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every instance of a baked file, ordered by id: static [N] bool, and per frame
    positions [F, N, 3], orientations [F, N, 4] (w, x, y, z) and sigmas [F, N, 3] (the
    instancer's scales over the writer's scale factor), scene units; ids [N]."""
    from pxr import Usd

    from usd_export import instance_arrays
    from usd_export.writer import DEFAULT_SCALE_FACTOR

    stage = Usd.Stage.Open(str(path))
    start = stage.GetStartTimeCode()
    pos, quat, sig = [], [], []
    for f in range(int(stage.GetEndTimeCode() - start) + 1):
        ids, static, a = instance_arrays(stage, start + f, ("positions", "orientations", "scales"))
        pos.append(a["positions"])
        quat.append(a["orientations"][:, [3, 0, 1, 2]])  # GfQuath's memory is (i, j, k, real)
        sig.append(a["scales"] / DEFAULT_SCALE_FACTOR)
    return static, np.stack(pos), np.stack(quat), np.stack(sig), ids


def rewrite(path: Path, pos: np.ndarray, quat: np.ndarray, sig: np.ndarray, static: np.ndarray | None,
            fps: float) -> float:
    """Write the frames with UsdBakeWriter (fmt both); returns the file's MiB."""
    from usd_export import UsdBakeWriter

    with UsdBakeWriter(path, n_points=pos.shape[1], fps=fps, fmt="both", static=static) as w:
        for f in range(len(pos)):
            w.write_frame(f, pos[f], quat[f], sig[f])
    return path.stat().st_size / MIB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, help="a scene file (default: the 3 mm plant, make_plant(--gaussians))")
    ap.add_argument("--gaussians", type=int, default=30000)
    ap.add_argument("--preset", default="flower")
    ap.add_argument("--interaction", default=None)
    ap.add_argument("--force", default="0,0,1")
    ap.add_argument("--static-below", default="0.2", help="the plant's pot top is at 0.2")
    ap.add_argument("--up", default=None)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--quality", default="default")
    ap.add_argument("--quick", action="store_true", help="2,000 Gaussians, 0.3 s, draft")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.seconds, args.quality = 2000, 0.3, "draft"

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        scene = args.scene.resolve() if args.scene else None
        if scene is None:
            from pd_tool.io.synthetic import make_plant
            from pd_tool.io import save_splats

            scene = save_splats(make_plant(args.gaussians, seed=0), tmp / "plant.ply")
        out = tmp / "bake.usd"
        cmd = [sys.executable, str(REPO / "cli.py"), "bake", "--scene", str(scene), "--preset", args.preset,
               "--force", args.force, "--static-below", args.static_below, "--seconds", str(args.seconds),
               "--fps", str(FPS), "--quality", args.quality, "--format", "both", "--device", "cpu"]
        if args.interaction:
            cmd += ["--interaction", args.interaction]
        if args.up:
            cmd += ["--up", args.up]
        cmd.append(str(out))
        p = subprocess.run(cmd, cwd=tmp, capture_output=True, text=True)
        if p.returncode != 0:
            last = (p.stderr.strip().splitlines() or ["no message"])[-1]
            sys.exit(f"usd_static_split: the bake failed: {last}")
        static, pos, quat, sig, _ = read_poses(out)
        split = rewrite(tmp / "split.usd", pos, quat, sig, static, fps=FPS)
        one = rewrite(tmp / "one.usd", pos, quat, sig, None, fps=FPS)
        res = {"scene": str(args.scene or f"make_plant({args.gaussians})"), "gaussians": int(len(static)),
               "frames": int(len(pos)), "static_share": float(static.mean()), "bake_mib": out.stat().st_size / MIB,
               "rewrite_split_mib": split, "rewrite_one_prim_mib": one, "one_over_split": one / split,
               "command": cmd[1:]}
    print(f"{res['scene']}: {res['gaussians']} Gaussians, {res['static_share']:.0%} static, {res['frames']} frames: "
          f"bake {res['bake_mib']:.1f} MiB; rewritten split {split:.1f} MiB, one prim {one:.1f} MiB "
          f"({one / split:.2f}x)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
