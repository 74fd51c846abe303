"""Multi-view fit: several video folders, one shared E field, one v0 field per video.

Two reference videos of the same plant from two cameras (45 and 135 degrees azimuth), with
pushes of different strength, fitted by `pdtool fit plant.ply a/ b/`. The material file
must hold one material field and two velocity fields, and each velocity field must have
learnt its own video's push: the stronger push gives the faster fitted v0.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from click.testing import CliRunner


def test_two_videos_share_E_and_keep_their_own_v0(tmp_path: Path) -> None:
    from cli import main
    from pd_tool.core.cameras import auto_camera
    from pd_tool.fit.fields import VelocityField
    from pd_tool.io import load_splats, save_splats
    from pd_tool.materials.file import MaterialFile
    from pd_tool.prepare.preparation import PrepareOptions, SimTransform, prepare_scene
    from pd_tool.fit.reference import plant_reference_video
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, make_plant

    save_splats(make_plant(600, seed=4), tmp_path / "plant.ply")
    scene = load_splats(tmp_path / "plant.ply")
    pts = scene.positions.numpy()
    pushes = {"a": (45.0, 0.7), "b": (135.0, 0.25)}  # camera azimuth (deg), push speed (m/s)
    for name, (azimuth, speed) in pushes.items():
        plant_reference_video(tmp_path / name, scene, auto_camera(pts, 32, 32, azimuth_deg=azimuth),
                              prepare_options=PrepareOptions(static_below=POT_TOP, grid_res=24),
                              region_E=REGION_TRUTH_E, driver_ratio=0.1, n_frames=5, push_speed=speed,
                              cfl_safety=0.6)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        res = CliRunner().invoke(main, [
            "fit", str(tmp_path / "plant.ply"), str(tmp_path / "a"), str(tmp_path / "b"), "-o",
            str(tmp_path / "fit.pdmat"), "--static-below", str(POT_TOP), "--quality", "draft",
            "--velocity-iters", "25", "--material-iters", "2", "--rounds", "2", "--horizon", "2", "--polish", "1",
            "--keep-best", "1", "--no-level", "--diffusion", "0.05", "--working-size", "32", "--no-preview",
            "--device", "cpu"], catch_exceptions=False)
    finally:
        torch.set_num_threads(threads)
    assert res.exit_code == 0, res.output

    mf = MaterialFile.load(tmp_path / "fit.pdmat")
    assert [Path(v).name for v in mf.meta["videos"]] == ["a", "b"]
    assert set(mf.fields) == {"material", "velocity0", "velocity1"}  # one shared E field
    # evaluate each video's v0 field at the drivers, as the fit does
    prep = prepare_scene(scene, PrepareOptions.from_dict(mf.meta["prepare"]))
    x_sim = SimTransform.from_dict(mf.meta["transform"]).to_sim(mf.driver_rest)
    x_norm = torch.as_tensor(np.clip(x_sim / np.asarray(prep.domain), 0, 1), dtype=torch.float32)
    speed = {}
    for i, name in enumerate(pushes):
        field = VelocityField.from_config(mf.meta["fields"][f"velocity{i}"])
        field.load_state_dict({k: torch.as_tensor(v) for k, v in mf.fields[f"velocity{i}"].items()})
        with torch.no_grad():
            speed[name] = float(field(x_norm).norm(dim=1).mean())
    assert speed["a"] > 1.3 * speed["b"] > 0.0, speed
    report = json.loads((tmp_path / "fit.report.json").read_text())
    assert report["losses"]["velocity"][-1] < report["losses"]["velocity"][0]
    # --rounds 2: stage 1 and stage 2 each ran twice
    assert mf.meta["settings"]["rounds"] == 2
    assert mf.meta["settings"]["material_horizon"] == 2  # --horizon 2 reached stage 2
    assert mf.meta["settings"]["polish_iters"] == 1  # and --polish 1
    # --keep-best 1: each round measured its start and both iterations, and kept one of them
    assert mf.meta["settings"]["keep_best_every"] == 1
    assert len(report["losses"]["whole_clip"]) == 2 * 3 and len(report["losses"]["kept"]) == 2
    assert mf.meta["metrics"]["kept_iteration"] == report["losses"]["kept"][-1] in (0, 1, 2)
    assert mf.meta["settings"]["stage1_level"] is False  # and --no-level: the paper's stage 1, no level
    assert mf.meta["settings"]["residual_diffusion"] == 0.05  # and --diffusion
    assert "stage1_level" not in report["losses"] and mf.meta["metrics"]["stage1_levels"] is None
    assert len(report["losses"]["velocity"]) == 2 * 25 and len(report["losses"]["material"]) == 2 * 2
