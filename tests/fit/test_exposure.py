"""The fit matches each video's exposure and white balance at rest, so that a darker or
tinted camera does not count as motion error."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

from tests._plant import tiny_plant_video


def _problem(folder: Path, gain: tuple[float, float, float], match: bool):
    from pd_tool.fit.problem import FitProblem
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(folder, 1500, seed=0, size=64, n_frames=3)
    ref = load_reference_video(folder / "video", working_size=64)
    ref.frames = (ref.frames * torch.tensor(gain)).clamp(0, 1)
    settings = FitSettings(quality="draft", working_long_side=64, match_exposure=match).resolved()
    return FitProblem(scene, [ref], PrepareOptions(static_below=POT_TOP), settings)


def test_a_darker_tinted_video_is_matched_at_rest(tmp_path: Path) -> None:
    gain = (0.9, 0.85, 0.95)
    pb = _problem(tmp_path, gain, match=True)
    assert pb.gains[0].tolist() == pytest.approx(gain, abs=0.01)
    rest = pb.render(0, pb.x_rest)
    matched = float(pb.frame_loss(0, 0, rest))
    pb.gains[0] = torch.ones(3)
    unmatched = float(pb.frame_loss(0, 0, rest))
    assert matched < 0.5 * unmatched, (matched, unmatched)


def test_match_exposure_off_keeps_the_render_as_it_is(tmp_path: Path) -> None:
    pb = _problem(tmp_path, (0.9, 0.9, 0.9), match=False)
    assert pb.gains[0].tolist() == [1.0, 1.0, 1.0]


def test_a_fit_of_a_darker_video_says_it_matched_the_exposure(tmp_path: Path) -> None:
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(tmp_path, 1500, seed=0, size=64, n_frames=3)
    ref = load_reference_video(tmp_path / "video", working_size=64)
    ref.frames = (ref.frames * 0.8).clamp(0, 1)
    settings = FitSettings(quality="draft", working_long_side=64, velocity_iters=1, material_iters=1,
                           calibrate_iters=0)
    res = run_fit(scene, tmp_path / "plant.ply", [ref], tmp_path / "plant.pdmat",
                  prepare_options=PrepareOptions(static_below=POT_TOP), settings=settings)
    line = next(x for x in res.report if "exposure matched" in x)
    assert "gain 0.80 / 0.80 / 0.80" in line and "--no-match-exposure" in line


def test_fit_help_names_the_exposure_switch() -> None:
    from click.testing import CliRunner

    from cli import main

    out = CliRunner().invoke(main, ["fit", "--help"]).output
    assert "--no-match-exposure" in out
