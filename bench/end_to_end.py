"""The user's pipeline through the real CLI, timed: `pdtool fit scene.ply video/` then
`pdtool bake --force 0,0,1 out.usd` in the same folder, on the synthetic plant with a
reference video rendered from its hidden E field (as `pdtool demo` does, at any size).

    python bench/end_to_end.py --device cuda --gaussians 100000 --size 1024 --json e2e.json
    python bench/end_to_end.py --gaussians 2000 --size 128 --quality draft   # CPU check
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def run_cli(args: list[str], cwd: Path) -> float:
    """Run `pdtool ARGS` (this interpreter's package) in cwd; seconds, or exit on failure."""
    t0 = time.perf_counter()
    cmd = [sys.executable, "-c", "from cli import main; main()", *args]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"pdtool {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=2000)
    ap.add_argument("--size", type=int, default=128, help="reference frames' long side, px (16:9 from 512 up)")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--quality", default="default", choices=["draft", "default"])
    ap.add_argument("--out", help="working folder (default: a temporary one)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 500 Gaussians, 48 px, 4 frames, draft")
    ap.add_argument("--json")
    a = ap.parse_args()
    if a.quick:
        a.gaussians, a.size, a.frames, a.quality = 500, 48, 4, "draft"

    from pxr import Usd

    from pd_tool.io import load_splats, save_splats
    from pd_tool.fit.reference import plant_reference_for_fit, reference_height
    from pd_tool.io.synthetic import POT_TOP, make_plant
    from pd_tool.render.views import scene_camera

    out = Path(a.out or tempfile.mkdtemp(prefix="pdtool-e2e-"))
    out.mkdir(parents=True, exist_ok=True)
    scene_path = save_splats(make_plant(a.gaussians, seed=0), out / "plant.ply")
    scene = load_splats(scene_path, device=a.device)
    h = reference_height(a.size)
    t0 = time.perf_counter()
    plant_reference_for_fit(out / "video", scene, scene_camera(scene, width=a.size, height=h), a.quality,
                            n_frames=a.frames, device=a.device)
    video_s = time.perf_counter() - t0
    fit_s = run_cli(["fit", "plant.ply", "video/", "--static-below", str(POT_TOP), "--quality", a.quality,
                     "--device", a.device], out)
    bake_s = run_cli(["bake", "--force", "0,0,1", "out.usd", "--device", a.device], out)
    stage = Usd.Stage.Open(str(out / "out.usd"))
    if stage is None:
        sys.exit("out.usd did not open")
    frames = int(stage.GetEndTimeCode() - stage.GetStartTimeCode()) + 1
    res = {"device": a.device, "gaussians": a.gaussians, "size_px": [a.size, h], "frames": a.frames,
           "quality": a.quality, "reference_video_s": video_s, "fit_cli_s": fit_s, "bake_cli_s": bake_s,
           "usd_frames": frames, "usd_bytes": (out / "out.usd").stat().st_size, "folder": str(out)}
    if a.device == "cuda":
        import torch
        res["gpu"] = torch.cuda.get_device_name(0)
    print(json.dumps(res, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
