"""Stage 2 with refine_velocity: the initial velocity keeps moving under the default
one-frame gradient horizon (a graph cut before the first frame once froze it silently)."""
from __future__ import annotations

import numpy as np
import torch


def test_refine_velocity_moves_v0_with_horizon_one(tmp_path) -> None:
    from _plant import tiny_plant_video
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(tmp_path, 600, seed=2, size=24)
    refs = [load_reference_video(tmp_path / "video", working_size=24)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        v0 = {}
        for refine in (False, True):
            s = FitSettings(quality="draft", velocity_iters=2, material_iters=3, working_long_side=24,
                            refine_velocity=refine, material_horizon=1)
            res = run_fit(scene, tmp_path / "plant.ply", refs, tmp_path / f"fit{int(refine)}.pdmat",
                          prepare_options=PrepareOptions(static_below=POT_TOP), settings=s)
            v0[refine] = res.driver_v0
    finally:
        torch.set_num_threads(threads)
    assert np.all(np.isfinite(v0[True]))
    # same stage 1 (same seed), so any difference comes from stage 2 refining v0
    change = np.abs(v0[True] - v0[False]).max()
    assert change > 1e-4 * max(np.abs(v0[False]).max(), 1e-6), change
