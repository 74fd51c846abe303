"""Stage 2 keeps the state that explained the whole clip best (keep_best_every): a step that
lowers the one-frame losses can still raise the whole clip's."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_outputs import _tiny_fit


def _fit(fit_dir: Path, out: Path, **kw):
    from pd_tool.fit.settings import FitSettings

    kw.setdefault("retry_step", 0.0)  # keeping alone: no second attempt (tests/fit/test_retry.py)
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=3, working_long_side=24,
                           stage1_level=False, **kw)
    return _tiny_fit(fit_dir, out, settings)[2]


def test_an_overshooting_stage_2_ends_in_its_best_measured_state(fit_dir: Path, tmp_path: Path) -> None:
    """Steps of a nat of E overshoot: the whole-clip loss measured after each iteration rises
    above an earlier one's, the fit returns the E of the lowest, and says so in its report;
    with keep_best_every 0 the same fit ends in its last state."""
    from pd_tool.materials.file import MaterialFile

    kept = _fit(fit_dir, tmp_path / "kept.pdmat", keep_best_every=1, lr_material=1.0, lr_residual=1.0)
    last = _fit(fit_dir, tmp_path / "last.pdmat", keep_best_every=0, lr_material=1.0, lr_residual=1.0)
    measures = kept.losses["whole_clip"]
    assert len(measures) == 4 and measures[0] == kept.losses["start"][0]  # the start, then after each iteration
    best = int(np.argmin(measures))
    assert best < 3 and measures[-1] > measures[best], f"no overshoot to test: {measures}"
    assert kept.losses["kept"] == [float(best)]
    # the fit ends where it measured its best, and reports that measure as its result
    assert kept.losses["final"][0] == pytest.approx(measures[best], rel=1e-4)
    # the last state's loss is the keeping fit's last measure, higher than the kept one
    assert last.losses["final"][0] == pytest.approx(measures[-1], rel=1e-4) and last.losses["final"][0] > measures[best]
    assert "kept" not in last.losses and "whole_clip" not in last.losses
    if best == 0:  # the stage's start: E as stage 1 left it, the uniform start
        np.testing.assert_allclose(kept.driver_E, np.full_like(kept.driver_E, 1e6), rtol=1e-5)
    assert not np.allclose(kept.driver_E, last.driver_E)
    mf = MaterialFile.load(tmp_path / "kept.pdmat")
    assert mf.meta["metrics"]["kept_iteration"] == best
    assert any("stage 2 raised the whole-clip loss" in line and "the fit keeps" in line for line in kept.report)


def test_a_whole_clip_iteration_measures_the_state_before_its_step(fit_dir: Path, tmp_path: Path,
                                                                    monkeypatch) -> None:
    """Where the next stage-2 iteration back-propagates through every frame, its own loss is
    the measure of the state before its step (borrowed_points): the same measures, and the
    same kept state, as simulating each point's state again."""
    from pd_tool.fit.settings import FitSettings

    kw = dict(keep_best_every=1, lr_material=1.0, lr_residual=1.0)
    borrowed = _fit(fit_dir, tmp_path / "borrowed.pdmat", **kw)
    monkeypatch.setattr(FitSettings, "borrowed_points", lambda self: [])
    monkeypatch.setattr(FitSettings, "borrows_start", lambda self: False)
    own = _fit(fit_dir, tmp_path / "own.pdmat", **kw)
    assert len(borrowed.losses["whole_clip"]) == 4  # the start, then after each of 3 iterations
    np.testing.assert_allclose(borrowed.losses["whole_clip"], own.losses["whole_clip"], rtol=1e-4)  # float32
    np.testing.assert_allclose(borrowed.losses["start"], own.losses["start"], rtol=1e-4)
    # the start's and the first two points' measures are the iterations' own losses
    assert borrowed.losses["whole_clip"][:3] == borrowed.losses["material"][:3]
    assert borrowed.losses["start"] == borrowed.losses["material"][:1]
    assert borrowed.losses["kept"] == own.losses["kept"]
    np.testing.assert_allclose(borrowed.driver_E, own.driver_E, rtol=1e-5)


def test_borrowed_points() -> None:
    from pd_tool.fit.settings import FitSettings

    # the start is measured by the first iteration where it back-propagates through every frame
    assert FitSettings(material_iters=40).borrows_start()
    assert not FitSettings(material_iters=40, material_horizon=1, polish_iters=15).borrows_start()
    assert not FitSettings(material_iters=0).borrows_start()

    # every frame: each point but the last is the next iteration's loss
    assert FitSettings(material_iters=40, keep_best_every=10).borrowed_points() == [10, 20, 30]
    # a one-frame horizon borrows only where the whole-clip polish has begun
    s = FitSettings(material_iters=40, keep_best_every=10, material_horizon=1, polish_iters=15)
    assert [s.horizon_at(it) for it in (24, 25, 39)] == [1, None, None] and s.borrowed_points() == [30]
    assert FitSettings(material_iters=40, keep_best_every=10, material_horizon=1).borrowed_points() == []


def test_measure_points_and_the_note() -> None:
    from pd_tool.fit.run import whole_clip_note
    from pd_tool.fit.settings import FitSettings

    assert FitSettings(material_iters=40, keep_best_every=10).measure_points() == [10, 20, 30, 40]
    assert FitSettings(material_iters=15, keep_best_every=10).measure_points() == [10, 15]
    assert FitSettings(material_iters=15, keep_best_every=0).measure_points() == []
    s = FitSettings(material_iters=15, keep_best_every=10)
    note = whole_clip_note({"whole_clip": [0.03, 0.02, 0.04], "kept": [10.0], "start": [0.03], "final": [0.02]}, s)
    assert note is not None and "0.0200 at its best, 0.0400 at its end" in note and "iteration 10" in note
    # a start that came out NaN: the kept measure, not min()'s NaN
    note = whole_clip_note({"whole_clip": [float("nan"), 0.02, 0.04], "kept": [10.0], "final": [0.02]}, s)
    assert note is not None and "0.0200 at its best" in note
    note = whole_clip_note({"whole_clip": [0.03, 0.05, 0.04], "kept": [0.0], "start": [0.03], "final": [0.03]}, s)
    assert note is not None and "the E stage 1 left" in note
    assert whole_clip_note({"whole_clip": [0.03, 0.02, 0.01], "kept": [15.0], "start": [0.03], "final": [0.01]},
                           s) is None
    with pytest.raises(ValueError, match="keep_best_every"):
        FitSettings(keep_best_every=-1).resolved()


@pytest.mark.parametrize("every, rounds, calibrate, horizon", [(1, 1, 0, None), (0, 1, 0, None), (2, 2, 0, None),
                                                              (0, 2, 0, None), (1, 1, 1, None), (1, 1, 0, 1)])
def test_the_work_estimate_counts_the_measures_the_fit_takes(fit_dir: Path, tmp_path: Path, monkeypatch,
                                                             every: int, rounds: int, calibrate: int,
                                                             horizon: int | None) -> None:
    """FitSettings.whole_clip_measures, which the work estimate charges, against the
    whole-clip simulations a fit runs: with and without keeping the best state, one and two
    rounds, a calibration, after which the result is measured again, and one-frame
    gradients, whose iterations measure nothing on the way."""
    import pd_tool.fit.run as run_module
    import pd_tool.fit.stages as stages_module
    from pd_tool.fit.settings import FitSettings

    calls = []
    for module in (run_module, stages_module):
        measure = module.whole_clip_loss
        monkeypatch.setattr(module, "whole_clip_loss", lambda pb, v0s, f=measure: calls.append(1) or f(pb, v0s))
    kw = dict(keep_best_every=every, rounds=rounds, calibrate_iters=calibrate, material_horizon=horizon)
    _fit(fit_dir, tmp_path / "f.pdmat", **kw)
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=3, working_long_side=24,
                           stage1_level=False, retry_step=0.0, **kw).resolved()
    assert len(calls) == settings.whole_clip_measures() > 0
