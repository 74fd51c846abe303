"""The work estimate before a bake or fit, its refusal and override, what explodes
(stiff materials, huge scales), and the stability guard's suggested force."""
from __future__ import annotations

import math
import re
import signal
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    return save_splats(make_plant(600, seed=0), tmp_path_factory.mktemp("plant") / "plant.ply")


def _one_error_line(res) -> str:
    assert res.exit_code == 2, (res.exit_code, res.stdout, res.stderr)
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.stderr
    return lines[0]


# ----------------------------------------------------------------------------- the estimates
def test_bake_estimate_grows_with_every_count() -> None:
    from pd_tool.prepare.work import estimate_bake_work

    base = dict(n_gaussians=10_000, n_particles=1_000, grid_nodes=17**3, frames=61, substeps=10)
    t = estimate_bake_work(**base).seconds
    for key, more in (("n_gaussians", 100_000), ("n_particles", 10_000), ("grid_nodes", 65**3), ("frames", 601),
                      ("substeps", 100)):
        assert estimate_bake_work(**{**base, key: more}).seconds > t, key
    assert estimate_bake_work(**base, preview_pixels=480 * 270).seconds > t
    long = {**base, "frames": 6001}
    assert estimate_bake_work(**long, device="cuda").seconds < estimate_bake_work(**long).seconds  # GPU faster


def test_fit_estimate_grows_with_every_count() -> None:
    from pd_tool.prepare.work import estimate_fit_work

    base = dict(n_gaussians=3_000, n_particles=300, grid_nodes=25**3, frames=[12], image_pixels=144 * 144,
                substeps=30, velocity_iters=30, material_iters=20)
    t = estimate_fit_work(**base).seconds
    for key, more in (("n_gaussians", 30_000), ("n_particles", 3_000), ("grid_nodes", 65**3), ("frames", [12, 12]),
                      ("image_pixels", 512 * 512), ("substeps", 300), ("velocity_iters", 300),
                      ("material_iters", 200), ("rounds", 2), ("calibrate_iters", 10), ("whole_clips", 5)):
        assert estimate_fit_work(**{**base, key: more}).seconds > t, key


def test_stiffer_material_and_faster_push_need_more_substeps() -> None:
    from pd_tool.prepare.work import cfl_substeps_estimate

    n = cfl_substeps_estimate(1 / 30, 0.05, 1e6, 1000.0, 0.3, 0.0, 0.5)
    assert cfl_substeps_estimate(1 / 30, 0.05, 1e12, 1000.0, 0.3, 0.0, 0.5) > 100 * n
    assert cfl_substeps_estimate(1 / 30, 0.05, 1e6, 1000.0, 0.3, 1e3, 0.5) > n
    assert cfl_substeps_estimate(1 / 30, 0.05, 1e12, 1000.0, 0.3, 0.0, 0.5, fixed=7) == 7
    assert cfl_substeps_estimate(1 / 30, 0.05, 1e6, 1000.0, 0.3, 0.0, 0.5, floor=10 * n) == 10 * n


def test_check_work_refuses_over_the_limit_with_the_override_named(monkeypatch) -> None:
    from pd_tool.core.errors import PdToolError
    from pd_tool.prepare.work import DEFAULT_MAX_MINUTES, WorkEstimate, WorkTooLarge, check_work, work_policy

    monkeypatch.delenv("PDTOOL_SKIP_WORK_CHECK", raising=False)
    long = WorkEstimate(seconds=DEFAULT_MAX_MINUTES * 60 * 3, what="bake", device="cpu", summary="600 frames x ...")
    with pytest.raises(WorkTooLarge) as e:
        check_work(long, fixes="shorten --seconds")
    msg = str(e.value)
    assert isinstance(e.value, PdToolError) and "\n" not in msg
    for word in ("3.0 h", "cpu", "60-minute limit", "shorten --seconds", "--max-minutes 270",
                 "PDTOOL_SKIP_WORK_CHECK=1"):
        assert word in msg, (word, msg)
    check_work(WorkEstimate(seconds=DEFAULT_MAX_MINUTES * 60 * 0.9, what="bake", device="cpu"), fixes="x")
    seen = []
    with work_policy(max_minutes=None, on_estimate=seen.append):
        check_work(long, fixes="x")  # no limit
    assert seen == [long]
    with work_policy(max_minutes=1e4):
        check_work(long, fixes="x")
    monkeypatch.setenv("PDTOOL_SKIP_WORK_CHECK", "1")
    check_work(long, fixes="x")


# ----------------------------------------------------------------------------- refusals in real runs
def test_bake_of_a_stiff_material_is_refused_before_the_drivers(plant, tmp_path, monkeypatch) -> None:
    """E = 1e12 Pa (a preset TOML's largest) for ten minutes of animation: tens of thousands of
    CFL substeps per frame. Refused at once, with the estimate and the override."""
    monkeypatch.delenv("PDTOOL_SKIP_WORK_CHECK", raising=False)
    (tmp_path / "steel.toml").write_text("E = 1e12\nnu = 0.3\ndensity = 1000.0\n")
    out = tmp_path / "o.usd"
    res = CliRunner().invoke(main, ["bake", str(out), "--scene", str(plant), "--preset", str(tmp_path / "steel.toml"),
                                    "--force", "0,0,1", "--seconds", "600", "--quality", "draft", "--device", "cpu",
                                    "--max-minutes", "60"])
    line = _one_error_line(res)
    assert "this bake would take about" in line and "--max-minutes" in line and "PDTOOL_SKIP_WORK_CHECK=1" in line
    assert "substeps" in line and not out.exists()


def test_max_minutes_refuses_and_the_environment_overrides(plant, tmp_path, monkeypatch) -> None:
    monkeypatch.delenv("PDTOOL_SKIP_WORK_CHECK", raising=False)
    out = tmp_path / "o.usd"
    args = ["bake", str(out), "--scene", str(plant), "--preset", "flower", "--force", "0,0,1", "--frames", "4",
            "--quality", "draft", "--device", "cpu", "--max-minutes", "0.0001"]
    line = _one_error_line(CliRunner().invoke(main, args))
    assert "over the 0.0001-minute limit" in line and not out.exists()
    ok = CliRunner().invoke(main, args, env={"PDTOOL_SKIP_WORK_CHECK": "1"})
    assert ok.exit_code == 0, (ok.stdout, ok.stderr)
    assert out.is_file() and "work estimate up to" in ok.stdout


def test_fit_is_refused_before_the_drivers(plant, tmp_path, monkeypatch) -> None:
    import numpy as np

    from pd_tool.video.folder import write_video_folder
    from pd_tool.io import load_splats
    from pd_tool.render.views import scene_camera

    monkeypatch.delenv("PDTOOL_SKIP_WORK_CHECK", raising=False)
    cam = scene_camera(load_splats(plant), width=16, height=16)
    write_video_folder(tmp_path / "video", np.full((4, 16, 16, 3), 128, np.uint8), cam, 30.0)
    out = tmp_path / "m.pdmat"
    res = CliRunner().invoke(main, ["fit", str(plant), str(tmp_path / "video"), "-o", str(out), "--quality", "draft",
                                    "--working-size", "16", "--velocity-iters", "10000", "--material-iters", "10000",
                                    "--static-below", "0.2", "--device", "cpu", "--max-minutes", "5"])
    line = _one_error_line(res)
    assert "this fit would take about" in line and "--max-minutes" in line and "--velocity-iters" in line, line
    assert not out.exists() and not (tmp_path / "m.pdmat.ckpt").exists()


# ----------------------------------------------------------------------------- what explodes
def test_knn_finishes_at_any_coordinate_scale() -> None:
    """Squared distances overflow float32 beyond ~1e19 (the cell search then grew NaN cells
    forever); the answer must be the one at unit scale."""
    import torch

    from pd_tool.drivers.knn import knn, knn_brute

    def stop(*_):
        raise TimeoutError("knn did not finish")

    old = signal.signal(signal.SIGALRM, stop)
    signal.alarm(60)
    try:
        g = torch.Generator().manual_seed(0)
        unit = torch.rand(2000, 3, generator=g)
        refs = unit[::10].clone()
        _, want = knn_brute(unit, refs, 8)
        for scale in (1e30, 1e-25, 1.0):
            d2, idx = knn(unit * scale, refs * scale, 8)
            assert torch.equal(idx, want), scale
            assert bool((d2[:, 1:] >= d2[:, :-1]).all())
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    with pytest.raises(ValueError, match="NaN or inf"):
        knn(torch.tensor([[math.nan, 0.0, 0.0]]), refs, 1)


def test_preparation_refuses_an_object_outside_the_simulated_sizes() -> None:
    from pd_tool.core.errors import PreparationError
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import make_plant

    scene = make_plant(300, seed=0)
    for mpu in (1e30, 1e-30):
        with pytest.raises(PreparationError, match="--meters-per-unit"):
            prepare_scene(scene, PrepareOptions(meters_per_unit=mpu, fill="off"))
    prepare_scene(scene, PrepareOptions(meters_per_unit=10.0, fill="off"))


def test_box_without_volume_is_refused_by_the_library_too() -> None:
    from pd_tool.core.errors import PreparationError
    from pd_tool.prepare.preparation import Box

    with pytest.raises(PreparationError, match="no volume"):
        Box.parse("0,0,0,1,1,0", "--static-box")
    assert Box.parse("1,1,1,0,0,0").lo == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("text", [
    "grid_res = 512\ncfl_safety = 0.5\ndriver_ratio = 0.1\nfit_velocity_iters = 1\nfit_material_iters = 1\n",
    "grid_res = 32\ncfl_safety = 0.001\ndriver_ratio = 0.1\nfit_velocity_iters = 1\nfit_material_iters = 1\n",
    "grid_res = 32\ncfl_safety = 0.5\ndriver_ratio = 0.1\nfit_velocity_iters = 100000\nfit_material_iters = 1\n",
])
def test_quality_presets_are_bounded(tmp_path, text) -> None:
    from pd_tool.core.errors import PresetError
    from pd_tool.materials.presets import load_preset

    (tmp_path / "q.toml").write_text(text)
    with pytest.raises(PresetError, match="outside"):
        load_preset("quality", tmp_path / "q.toml")


# ----------------------------------------------------------------------------- the guard's hint
@pytest.mark.parametrize("preset,extra,force", [
    ("jelly", [], "0,0,1e4"),  # the whole free object pushed into the box's wall
    ("jelly", [], "1e4,0,0"),
    ("jelly", ["--static-below", "0.2", "--interaction", "poke"], "1e5,0,0"),  # a tap held by the pot
    ("flower", ["--static-below", "0.2", "--interaction", "gust"], "5e4,0,0"),
])
def test_the_force_the_guard_suggests_simulates(plant, tmp_path, preset, extra, force) -> None:
    """The refusal names a force; the same bake with that force must run to the end."""
    args = ["--scene", str(plant), "--preset", preset, "--seconds", "1", "--quality", "draft", "--device", "cpu",
            *extra]
    res = CliRunner().invoke(main, ["bake", str(tmp_path / "a.usd"), *args, "--force", force])
    assert res.exit_code == 2, (res.stdout, res.stderr)
    m = re.search(r"lower --force below about ([0-9.e+-]+)", res.stderr)
    assert m, res.stderr
    hint = float(m.group(1))
    direction = [float(v) for v in force.split(",")]
    scale = hint / math.sqrt(sum(v * v for v in direction))
    suggested = ",".join(f"{v * scale:.6g}" for v in direction)
    ok = CliRunner().invoke(main, ["bake", str(tmp_path / "b.usd"), *args, "--force", suggested])
    assert ok.exit_code == 0, (suggested, ok.stderr)
    assert (tmp_path / "b.usd").is_file()
