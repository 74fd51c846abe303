"""Stage 2 runs again from its start at a fraction of its step when nothing it measured beat
the start (retry_step): Adam's first steps can overshoot on whole-clip gradients and never
come back within the stage."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_outputs import _tiny_fit


class Interrupt(Exception):
    pass


@pytest.fixture(scope="module")
def fitted(fit_dir: Path, tmp_path_factory) -> Path:
    """A material already fitted to the fixture's video: a stage 2 started from it has
    little left to gain, so steps of 20 nats only overshoot."""
    from pd_tool.fit.settings import FitSettings

    out = tmp_path_factory.mktemp("retry") / "fitted.pdmat"
    _tiny_fit(fit_dir, out, FitSettings(quality="draft", velocity_iters=1, material_iters=8, working_long_side=24,
                                        stage1_level=False))
    return out


def _settings(fitted: Path, **kw):
    from pd_tool.fit.settings import FitSettings

    return FitSettings(quality="draft", velocity_iters=1, material_iters=2, working_long_side=24, stage1_level=False,
                       keep_best_every=1, lr_material=20.0, lr_residual=20.0, warmup=0, init_material=str(fitted),
                       **kw)


def test_a_stage_2_that_keeps_its_start_runs_again_at_a_fraction_of_its_step(fit_dir: Path, fitted: Path,
                                                                            tmp_path: Path) -> None:
    """Without the retry the overshooting stage keeps its start; with it the same first
    attempt runs, then a second from the start whose smaller steps move the whole-clip loss
    less, and the fit keeps the best of the second's measures and the start."""
    from pd_tool.materials.file import MaterialFile

    off = _tiny_fit(fit_dir, tmp_path / "off.pdmat", _settings(fitted, retry_step=0.0))[2]
    start, *after = off.losses["whole_clip"]
    assert min(after) > start, f"no overshoot to test: {off.losses['whole_clip']}"
    assert off.losses["kept"] == [0.0] and "whole_clip_first_try" not in off.losses

    on = _tiny_fit(fit_dir, tmp_path / "on.pdmat", _settings(fitted, retry_step=0.01))[2]
    # the first attempt, kept apart, is the fit without the retry
    np.testing.assert_allclose(on.losses["whole_clip_first_try"], off.losses["whole_clip"], rtol=1e-6)
    np.testing.assert_allclose(on.losses["material_first_try"], off.losses["material"], rtol=1e-6)
    # the second starts where the first did and takes a hundredth of its steps
    retry = on.losses["whole_clip"]
    assert len(retry) == 3 and retry[0] == pytest.approx(start, rel=1e-6) and len(on.losses["material"]) == 2
    assert abs(retry[1] - start) < abs(after[0] - start)
    kept = int(on.losses["kept"][0])
    assert on.losses["final"][0] == pytest.approx(retry[kept], rel=1e-4) and on.losses["final"][0] <= start
    if kept > 0:  # the retry found a better state than the start
        assert not np.allclose(on.driver_E, off.driver_E)
    else:
        np.testing.assert_allclose(on.driver_E, off.driver_E, rtol=1e-5)
    meta = MaterialFile.load(tmp_path / "on.pdmat").meta
    assert meta["metrics"]["stage2_retried"] is True and meta["settings"]["retry_step"] == 0.01
    assert MaterialFile.load(tmp_path / "off.pdmat").meta["metrics"]["stage2_retried"] is False
    assert any("stage 2 kept its start" in line and "at 0.01 of its step" in line for line in on.report)


def test_a_fit_killed_in_its_retry_resumes_in_its_first_attempt_and_ends_the_same(fit_dir: Path, fitted: Path,
                                                                                  tmp_path: Path) -> None:
    """The retry takes no checkpoint: killed in it, the fit resumes from the first attempt's
    last checkpoint, retries again and ends as the uninterrupted fit does."""
    from pd_tool.fit.run import run_fit
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.video.folder import load_reference_video

    scene = load_splats(fit_dir / "plant.ply")
    refs = [load_reference_video(fit_dir / "video", working_size=24)]
    settings = _settings(fitted, retry_step=0.01, checkpoint_every=1)

    def fit(out: Path, stop_at=None, resume: bool = False):
        def progress(stage: str, it: int, total: int, loss: float) -> None:
            if (stage, it) == stop_at:
                raise Interrupt
        return run_fit(scene, fit_dir / "plant.ply", refs, out, settings=settings, progress=progress, resume=resume,
                       prepare_options=PrepareOptions(static_below=POT_TOP, up_axis="+z"))

    whole = fit(tmp_path / "whole.pdmat")
    assert "whole_clip_first_try" in whole.losses
    out = tmp_path / "cut.pdmat"
    with pytest.raises(Interrupt):
        fit(out, stop_at=("material, retried", 1))
    assert out.with_name(out.name + ".ckpt").is_file() and not out.exists()
    res = fit(out, resume=True)
    for k in ("whole_clip_first_try", "whole_clip", "kept"):
        np.testing.assert_allclose(res.losses[k], whole.losses[k], rtol=1e-6)
    np.testing.assert_allclose(res.driver_E, whole.driver_E, rtol=1e-6)


def test_retry_settings() -> None:
    from pd_tool.fit.settings import FitSettings
    from pd_tool.fit.stages import Kept, retries

    s = FitSettings(lr_material=0.05, lr_residual=0.15, refine_velocity_factor=0.5).with_step_scale(0.2)
    assert (s.lr_material, s.lr_residual, s.refine_velocity_factor) == pytest.approx((0.01, 0.03, 0.1))
    for bad in (-0.1, 1.0, float("nan")):
        with pytest.raises(ValueError, match="retry_step"):
            FitSettings(retry_step=bad).resolved()
    at = lambda it: Kept({}, {}, None, 0.01, it)  # noqa: E731
    s = FitSettings(material_iters=10, retry_step=0.3)
    assert retries(s, at(0)) and not retries(s, at(10)) and not retries(s, None)
    assert not retries(FitSettings(material_iters=10, retry_step=0.0), at(0))
    assert not retries(FitSettings(material_iters=10, retry_step=0.3, rounds=2), at(0))
