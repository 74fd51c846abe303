"""FitSettings.field_first: the first round fits E's field alone, the later rounds add the
per-driver residuals on top of it; a checkpoint taken in either round resumes."""
from __future__ import annotations

from pathlib import Path

import pytest


class Interrupt(Exception):
    pass


def test_round_settings_and_refusals() -> None:
    from pd_tool.fit.settings import FitSettings

    s = FitSettings(quality="draft", rounds=2, field_first=True).resolved()
    first, second = s.round_settings(0), s.round_settings(1)
    assert (first.driver_residual, first.stage1_level) == (False, False)
    assert second is s and (s.driver_residual, s.stage1_level) == (True, True)
    plain = FitSettings(quality="draft", rounds=2).resolved()
    assert plain.round_settings(0) is plain
    for bad in (dict(rounds=1), dict(rounds=2, driver_residual=False), dict(rounds=2, init_material="x.pdmat")):
        with pytest.raises(ValueError, match="field_first"):
            FitSettings(quality="draft", field_first=True, **bad).resolved()


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    from _plant import tiny_plant_inputs

    return tiny_plant_inputs(tmp_path_factory.mktemp("field_first"))


def _fit(plant, out: Path, monkeypatch, stop_at=None, resume: bool = False):
    """A field-first fit of two rounds; returns (result, the largest |residual| after each
    round run, the level fitted by each stage 1)."""
    import pd_tool.fit.run as run
    from pd_tool.fit.settings import FitSettings
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.prepare.preparation import PrepareOptions

    d, scene, refs = plant
    after = []
    original = run.fit_round

    def spy(pb, s, rnd, *args):
        skipped = original(pb, s, rnd, *args)
        after.append((rnd, float(pb.log_e_residual.detach().abs().max())))
        return skipped

    monkeypatch.setattr(run, "fit_round", spy)

    def progress(stage: str, it: int, total: int, loss: float) -> None:
        if (stage, it) == stop_at:
            raise Interrupt

    settings = FitSettings(quality="draft", velocity_iters=2, material_iters=2, working_long_side=24, rounds=2,
                           field_first=True, residual_decay=0.5, checkpoint_every=1, keep_best_every=0)
    res = run.run_fit(scene, d / "plant.ply", refs, out, prepare_options=PrepareOptions(static_below=POT_TOP),
                      settings=settings, progress=progress, resume=resume)
    return res, after


def test_the_first_round_keeps_the_residuals_at_zero_and_the_second_moves_them(plant, tmp_path, monkeypatch):
    res, after = _fit(plant, tmp_path / "a.pdmat", monkeypatch)
    assert [r for r, _ in after] == [0, 1]
    assert after[0][1] == 0.0 and after[1][1] > 0.0
    # the level is fitted by the second round's stage 1 only
    assert len(res.losses["stage1_level"]) == 1
    assert len(res.losses["material"]) == 4 and len(res.losses["velocity"]) == 4


@pytest.mark.parametrize("stop_at", [("material 1/2", 1), ("material 2/2", 1)])
def test_a_field_first_fit_resumes_from_either_round(plant, tmp_path, monkeypatch, stop_at):
    out = tmp_path / "b.pdmat"
    with pytest.raises(Interrupt):
        _fit(plant, out, monkeypatch, stop_at=stop_at)
    assert out.with_name(out.name + ".ckpt").is_file()
    res, after = _fit(plant, out, monkeypatch, resume=True)
    assert out.is_file() and len(res.losses["material"]) == 4
    assert after[-1][0] == 1 and after[-1][1] > 0.0
    if stop_at[0].endswith("1/2"):
        assert after[0] == (0, 0.0)
    # bit for bit the uninterrupted fit (on the CPU): nothing of the first round, such as
    # a gradient left on the residuals it does not step, carries into the second
    whole, _ = _fit(plant, tmp_path / "c.pdmat", monkeypatch)
    assert res.losses["material"] == whole.losses["material"]
    assert res.losses["velocity"] == whole.losses["velocity"]
