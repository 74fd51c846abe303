"""`pdtool demo`: the whole pipeline on the built-in plant, with a known truth to compare.

scene .ply -> reference videos of a hidden E field pushed sideways (+ camera.json) ->
fit -> bake a poke to USD -> previews and the E picture. Every step calls the same
library functions as `pdtool render`, `pdtool fit` and `pdtool bake`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from pd_tool import app
from pd_tool.bake import BakeSettings, ForceSpec
from pd_tool.core.atomic import check_replaceable_folder, folder_mark, mark_folder
from pd_tool.core.cameras import auto_camera
from pd_tool.fit.settings import FitSettings
from pd_tool.fit.reference import plant_reference_for_fit
from pd_tool.fit.run import whole_clip_text
from pd_tool.io import load_splats, save_splats
from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant
from pd_tool.prepare import PrepareOptions
from pd_tool.render.views import scene_camera

# Demo sizes per quality: Gaussians in the plant, reference frames, frame size (px), fit
# iterations (velocity, material) and reference videos. The default demo must finish within
# 10 minutes on a 2-core CPU. Its second video, pushed the other way and seen from another
# side, is what separates the thin leaves' E from the stem's: with one video the leaves came
# out 8.4x too stiff (docs/fitting.md, tried). 14 frames, as the fit benchmarks use: on 12 the
# stem and the flower came out 0.65x and 1.56x of their truth (docs/benchmarks.md).
DEMO_SIZES = {"draft": (2000, 10, 128, 20, 15, 1), "default": (3000, 14, 144, 60, 40, 2)}
# video k: pushed along x (k even) or y (k odd), seen from the scene camera (k = 0) or from
# 45 + 90 k degrees azimuth
DEMO_PUSHES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


DEMO_MARK = "pdtool demo"  # the `what` of the demo folder's manifest
# What the demo writes at fixed names: in a folder an earlier demo made, these are its own
# even when that demo was stopped before it listed them.
DEMO_NAMES = ("plant.ply", "plant.pdmat", "plant.pdmat.ckpt", "plant.report.json", "plant.loss.png",
              "plant.E.ply", "plant.E.png", "plant.preview.mp4", "poke.usd", "poke.mp4", ".pdtool/last-fit.json")


def _claim_folder(out: Path) -> None:
    """The demo writes fixed names into `out`: refuse a folder holding anything pdtool did
    not write (a user's own plant.ply would be replaced), then mark it as the demo's."""
    known = DEMO_NAMES if out.is_dir() and folder_mark(out) == DEMO_MARK else ()
    check_replaceable_folder(out, "--out", known=known)
    out.mkdir(parents=True, exist_ok=True)
    mark_folder(out, DEMO_MARK)


@dataclass
class DemoResult:
    out_dir: Path
    paths: dict[str, Path]
    fit_seconds: float
    bake_seconds: float
    video_seconds: float
    recovered: dict[str, float]  # median fitted E per region, Pa
    truth: dict[str, float]
    lines: list[str] = field(default_factory=list)


def run_demo(out_dir: str | Path, *, quality: str = "default", device: str = "cpu",
             say: Callable[[str], None] = print, fit_progress=None, bake_progress=None) -> DemoResult:
    """Run the demo into out_dir (created); returns what it wrote and the comparison."""
    if quality not in DEMO_SIZES:
        raise ValueError(f"demo quality must be one of {', '.join(DEMO_SIZES)}")
    n_gauss, n_frames, size, velocity_iters, material_iters, n_videos = DEMO_SIZES[quality]
    out = Path(out_dir)
    _claim_folder(out)
    paths: dict[str, Path] = {}

    # 1. the scene, as a user would have it on disk
    # 3 mm leaves and petals, far thinner than a cell, as a real plant has
    paths["scene"] = save_splats(make_plant(n_gauss, seed=0, thin=True), out / "plant.ply")
    scene = load_splats(paths["scene"], device=device)
    say(f"scene      {paths['scene']} ({scene.count:,} Gaussians)")

    # 2. reference videos of the hidden truth: E per region, pushed sideways at t = 0
    t0 = time.perf_counter()
    videos = []
    for k in range(n_videos):
        cam = scene_camera(scene, width=size, height=size) if k == 0 else auto_camera(
            scene.positions.detach().cpu().numpy(), size, size, azimuth_deg=45.0 + 90.0 * k)
        name = "video" if k == 0 else f"video{k + 1}"
        video, truth, _ = plant_reference_for_fit(out / name, scene, cam, quality, n_frames=n_frames,
                                                  push_direction=DEMO_PUSHES[k % 2], device=device)
        videos.append(video)
        paths[name] = video
        say(f"video      {video}/ ({n_frames} frames of a hidden stiffness field, camera.json)")
    video_s = time.perf_counter() - t0

    # 3. fit, exactly as `pdtool fit plant.ply video/ [video2/] --static-below 0.2`
    t0 = time.perf_counter()
    settings = FitSettings(quality=quality, device=device, working_long_side=size, velocity_iters=velocity_iters,
                           material_iters=material_iters)
    mat_path = out / "plant.pdmat"
    done = app.fit(app.FitJob(paths["scene"], videos, mat_path, settings, PrepareOptions(static_below=POT_TOP),
                              record_dir=out), progress=fit_progress)
    result = done.result
    fit_s = time.perf_counter() - t0
    paths.update(material=mat_path, **{f"fit_{k}": v for k, v in done.side.items()})

    # 4. bake a poke with the fitted material, as `pdtool bake --force ... out.usd`
    t0 = time.perf_counter()
    usd = out / "poke.usd"
    bres = app.bake(app.BakeJob(usd, ForceSpec.from_interaction("poke", (20.0, 0.0, 0.0)),
                                BakeSettings(seconds=2.0, fps=30, fmt="both", device=device),  # as the fit simulated
                                scene=paths["scene"], material=mat_path, preview=out / "poke.mp4"),
                    progress=bake_progress)
    bake_s = time.perf_counter() - t0
    paths["usd"] = usd
    paths["bake_preview"] = out / "poke.mp4"
    mark_folder(out, DEMO_MARK)

    labels = scene.labels[result.prep.foreground]
    recovered = {}
    for i, name in enumerate(REGIONS):
        sel = labels == i
        if name != "pot" and sel.any():  # the pot is static: its E is never seen
            recovered[name] = float(np.median(result.gaussian_E[sel]))
    truth_moving = {k: v for k, v in REGION_TRUTH_E.items() if k in recovered}
    lines = [
        f"fit   {fit_s:6.1f} s  ({len(result.driver_E)} drivers, whole-clip loss {whole_clip_text(result.losses)})",
        "E     " + "  ".join(f"{k} {recovered[k]:.3g} Pa (truth {truth_moving[k]:.3g})" for k in recovered),
        f"bake  {bres.seconds_elapsed:6.1f} s  ({bres.frames} frames, {bres.substeps_per_frame} substeps/frame)",
    ]
    return DemoResult(out, paths, fit_s, bake_s, video_s, recovered, truth_moving, lines)
