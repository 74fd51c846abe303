"""FitSettings.residual_parts: one residual per k-means part of the moving drivers instead
of one per driver."""
from __future__ import annotations

import numpy as np
import pytest


def test_negative_parts_are_refused() -> None:
    from pd_tool.fit.settings import FitSettings

    with pytest.raises(ValueError, match="residual_parts"):
        FitSettings(quality="draft", residual_parts=-1).resolved()


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    from _plant import tiny_plant_inputs

    return tiny_plant_inputs(tmp_path_factory.mktemp("parts"))


def fitted_problem(plant, tmp_path, monkeypatch, **settings):
    """The FitProblem of a short draft fit of the tiny plant with these FitSettings."""
    import pd_tool.fit.run as run
    from pd_tool.fit.settings import FitSettings
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.prepare.preparation import PrepareOptions

    d, scene, refs = plant
    seen = {}
    original = run.fit_round

    def spy(pb, s, rnd, *args):
        skipped = original(pb, s, rnd, *args)
        seen["problem"] = pb
        return skipped

    monkeypatch.setattr(run, "fit_round", spy)
    s = FitSettings(quality="draft", velocity_iters=2, material_iters=3, working_long_side=24, checkpoint_every=100,
                    keep_best_every=0, **settings)
    run.run_fit(scene, d / "plant.ply", refs, tmp_path / "a.pdmat", prepare_options=PrepareOptions(static_below=POT_TOP),
                settings=s)
    return seen["problem"]


def test_a_fit_keeps_one_residual_per_part(plant, tmp_path, monkeypatch) -> None:
    import torch

    pb = fitted_problem(plant, tmp_path, monkeypatch, residual_parts=3)
    parts = pb.residual_parts.cpu().numpy()
    r = pb.log_e_residual.detach().cpu().numpy()
    moving = ~pb.static.cpu().numpy()
    assert (parts[moving] >= 0).all() and (parts[~moving] == -1).all()
    assert sorted(set(parts[moving].tolist())) == [0, 1, 2]
    values = [np.unique(r[parts == k]) for k in range(3)]
    assert all(len(v) == 1 for v in values)  # one value a part, exactly
    assert len({float(v[0]) for v in values}) > 1 and any(v[0] != 0 for v in values)  # they moved, apart

    # the sharing step against a plain per-part mean in float64
    rng = np.random.default_rng(0)
    start = rng.normal(size=len(r)).astype(np.float32)
    pb.log_e_residual.data.copy_(torch.as_tensor(start))
    pb.share_residuals()
    got = pb.log_e_residual.detach().cpu().numpy()
    want = start.astype(np.float64)
    for k in range(3):
        want[parts == k] = start[parts == k].astype(np.float64).mean()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert np.array_equal(got[~moving], start[~moving])


def test_a_fit_pools_its_residual_step_within_parts(plant, tmp_path, monkeypatch) -> None:
    """residual_pool_parts: the fit's residual optimiser pools within the k-means parts of the
    moving drivers, static drivers on their own; the residuals themselves stay one a driver."""
    from pd_tool.fit.schedule import PooledAdam
    from pd_tool.fit.stages import stage_optimizers

    pb = fitted_problem(plant, tmp_path, monkeypatch, residual_pool=0.5, residual_pool_parts=3)
    assert pb.residual_parts is None
    parts = pb.pool_parts.cpu().numpy()
    moving = ~pb.static.cpu().numpy()
    assert (parts[~moving] == -1).all() and sorted(set(parts[moving].tolist())) == [0, 1, 2]
    r = pb.log_e_residual.detach().cpu().numpy()
    assert len(np.unique(r[moving])) > 3  # one residual a driver, not a part
    opt, _ = stage_optimizers(pb, pb.s, "material")["_r"]
    assert isinstance(opt, PooledAdam) and opt.groups is pb.pool_parts
