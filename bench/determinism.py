"""Run-to-run differences of a bake and a fit with the same inputs and seed.

On CPU both are bit-identical (tests/integration/test_reliability_kill.py checks it through the
command line). On CUDA the MPM scatter (particle-to-grid) and the rasteriser's backward
accumulate with floating-point atomics whose order varies between runs; this script
measures what that does to the baked positions and the fitted E.

    python bench/determinism.py --device cuda --n 20000 --runs 3 --json det.json
    python bench/determinism.py --device cpu --n 2000 --runs 2
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from usd_export import instance_positions


def bake_positions(scene, device: str, frames: int, quality: str, out: Path) -> np.ndarray:
    """Every frame's Gaussian positions [T, N, 3] of a bake (read back from the USD)."""
    from pxr import Usd

    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material
    from pd_tool.io.synthetic import POT_TOP

    bake(scene, out, force=ForceSpec(accel=(0.0, 0.0, 1.0)), material=Material.from_preset("flower"),
         prepare_options=PrepareOptions(static_below=POT_TOP),
         settings=BakeSettings(seconds=(frames - 1) / 30, quality=quality, device=device, stop_at_rest=False))
    stage = Usd.Stage.Open(str(out))
    # every instance by id: pinned ones sit on their own prim, written once
    return np.stack([instance_positions(stage, t)[1] for t in range(frames)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--n", type=int, default=2000, help="Gaussians in the synthetic plant")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--quality", default="draft")
    ap.add_argument("--fit-iters", type=int, default=2, help="iterations per fit stage (0: no fit)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 500 Gaussians, 4 frames, 1 fit iteration per stage")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args()
    if a.quick:
        a.n, a.frames, a.fit_iters = 500, 4, 1
    import torch

    if a.device == "cpu":
        torch.set_num_threads(1)
    from pd_tool.fit.reference import write_plant_with_video  # the memory bench's plant + video
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    res: dict = {"device": a.device, "n": a.n, "frames": a.frames, "runs": a.runs}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        write_plant_with_video(tmp, a.n, frames=6)
        scene = load_splats(tmp / "plant.ply", device=a.device)
        t = time.perf_counter()
        pos = [bake_positions(scene, a.device, a.frames, a.quality, tmp / f"b{i}.usd") for i in range(a.runs)]
        size = float(np.ptp(pos[0][0], axis=0).max())
        d = max(float(np.abs(p - pos[0]).max()) for p in pos[1:])
        res["bake"] = {"max_abs_position_diff": d, "relative_to_object": d / size,
                       "usd_bytes_identical": all((tmp / f"b{i}.usd").read_bytes() == (tmp / "b0.usd").read_bytes()
                                                  for i in range(a.runs)),
                       "seconds": time.perf_counter() - t}
        print("bake", res["bake"], flush=True)
        if a.fit_iters > 0:
            refs = [load_reference_video(tmp / "video", working_size=64, device=a.device)]
            E = []
            for i in range(a.runs):
                r = run_fit(scene, tmp / "plant.ply", refs, tmp / f"f{i}.pdmat",
                            prepare_options=PrepareOptions(static_below=POT_TOP),
                            settings=FitSettings(quality=a.quality, velocity_iters=a.fit_iters,
                                                 material_iters=a.fit_iters, working_long_side=64, device=a.device))
                E.append(r.driver_E)
            rel = max(float(np.abs(e / E[0] - 1).max()) for e in E[1:])
            res["fit"] = {"max_rel_E_diff": rel, "bit_identical": rel == 0.0}
            print("fit", res["fit"], flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
