"""`pdtool register` and `pdtool fit` on a clip without a camera, through the CLI.

A tiny plant (800 Gaussians) and its 32-px video: the registered camera against the one
the video was rendered with, the files written, and the refusals (exit 2, one line that
names the way out, nothing written).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

FIT = ["--static-below", "0.2", "--quality", "draft", "--velocity-iters", "1", "--material-iters", "2",
       "--working-size", "32", "--device", "cpu", "--no-preview"]


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from _plant import tiny_plant_video

    d = tmp_path_factory.mktemp("plant")
    tiny_plant_video(d, 800, seed=0, size=32)
    return d


def _invoke(args: list[str], cwd: Path, monkeypatch):
    from click.testing import CliRunner
    from tqdm import tqdm

    import cli

    monkeypatch.chdir(cwd)
    monkeypatch.setattr(cli, "_tqdm", lambda *a, **k: tqdm(disable=True), raising=False)
    return CliRunner().invoke(cli.main, [str(a) for a in args])


def _copy(plant: Path, tmp_path: Path, *, camera: bool) -> Path:
    w = tmp_path / "work"
    shutil.copytree(plant, w)
    if not camera:
        (w / "video" / "camera.json").unlink()
    return w


def test_register_finds_the_plant_videos_camera(plant, tmp_path, monkeypatch):
    """The plant's video is pdtool's own render over white: registered from the default
    start, its camera is within the bench's goal (1 degree, 2% of the size, 2% focal)."""
    import sys

    from pd_tool.core.cameras import load_cameras, select_view
    from pd_tool.io import load_splats
    from pd_tool.register.solve import object_bounds

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))
    from register_accuracy import camera_errors

    w = _copy(plant, tmp_path, camera=True)
    res = _invoke(["register", "plant.ply", "video", "-o", "found.json"], w, monkeypatch)
    assert res.exit_code == 0, res.output
    assert "residual" in res.output
    assert (w / "found.register.png").stat().st_size > 0
    found, truth = (select_view(load_cameras(p)) for p in (w / "found.json", w / "video" / "camera.json"))
    assert (found.width, found.height) == (truth.width, truth.height)
    size = 2.0 * object_bounds(load_splats(w / "plant.ply").positions.numpy())[1]
    err = camera_errors(found, truth, size)
    assert err["rotation_deg"] < 1.0 and err["translation"] < 0.02 and err["focal"] < 0.02, err


def test_register_refuses_over_the_residual_bound_and_writes_nothing(plant, tmp_path, monkeypatch):
    w = _copy(plant, tmp_path, camera=True)
    before = sorted(p.name for p in w.rglob("*"))
    res = _invoke(["register", "plant.ply", "video", "-o", "found.json", "--max-residual", "1e-6"], w, monkeypatch)
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert "\n" not in line and "Traceback" not in line
    assert "residual" in line and "--mask" in line
    assert sorted(p.name for p in w.rglob("*")) == before


def test_fit_registers_a_clip_without_a_camera(plant, tmp_path, monkeypatch):
    w = _copy(plant, tmp_path, camera=False)
    res = _invoke(["fit", "plant.ply", "video", "-o", "fit.pdmat", *FIT], w, monkeypatch)
    assert res.exit_code == 0, res.output
    assert "no camera.json, so frame 0 was registered" in res.output
    cam = json.loads((w / "fit.camera.json").read_text())
    assert cam["width"] == 32
    assert (w / "fit.camera.register.png").is_file()
    assert not (w / "video" / "camera.json").exists()  # nothing written into the user's clip folder
    report = json.loads((w / "fit.report.json").read_text())
    reg = report["clips"][0]["registered"]
    assert reg["camera"].endswith("fit.camera.json") and 0.0 <= reg["residual"] <= 0.06
    # the camera found is the one a rerun uses by name
    res2 = _invoke(["fit", "plant.ply", "video", "-o", "fit2.pdmat", "--camera", "fit.camera.json", *FIT], w,
                   monkeypatch)
    assert res2.exit_code == 0, res2.output
    assert "registered" not in res2.output


def test_fit_refuses_a_clip_it_cannot_register(plant, tmp_path, monkeypatch):
    from PIL import Image

    w = _copy(plant, tmp_path, camera=False)
    for f in sorted((w / "video").glob("*.png")):  # a clip of an empty grey backdrop
        size = Image.open(f).size
        Image.fromarray(np.full((size[1], size[0], 3), 128, dtype=np.uint8)).save(f)
    before = sorted(p.relative_to(w).as_posix() for p in w.rglob("*"))
    res = _invoke(["fit", "plant.ply", "video", "-o", "fit.pdmat", *FIT], w, monkeypatch)
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert "\n" not in line and "Traceback" not in line
    assert "could not register" in line and "--camera" in line
    assert sorted(p.relative_to(w).as_posix() for p in w.rglob("*")) == before
