"""FitSettings.stored_frames_mb: the memory the fit's simulation may fill with frames stored
for the backward. 0 stores none and gives the same gradients; a bad value is refused."""
from __future__ import annotations

import math

import pytest
import torch


def test_no_stored_frames_gives_the_same_gradients(tmp_path) -> None:
    from _plant import tiny_plant_problem
    from pd_tool.fit.stages import material_iteration

    grads, kept = {}, {}
    for label, mb in (("auto", None), ("none", 0.0)):
        _, pb, v0 = tiny_plant_problem(tmp_path / label, 500, seed=3, size=24, stored_frames_mb=mb)
        if mb is not None:
            assert pb.sim.config.keep_budget_mb == mb
        pb.material.zero_grad(set_to_none=True)
        material_iteration(pb, [v0], None)
        grads[label] = torch.cat([p.grad.flatten() for p in pb.material.parameters()])
        kept[label] = len(pb.sim._kept)
    assert kept["auto"] > 0 and kept["none"] == 0
    assert grads["auto"].abs().max() > 0
    # on the CPU a stored frame and a recomputed one run the same kernels in the same order
    assert torch.equal(grads["auto"], grads["none"])


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf])
def test_a_bad_stored_frames_budget_is_refused(bad) -> None:
    from pd_tool.fit.settings import FitSettings

    with pytest.raises(ValueError, match="stored_frames_mb"):
        FitSettings(stored_frames_mb=bad).resolved()
