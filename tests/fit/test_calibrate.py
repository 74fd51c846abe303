"""Stage 3, calibration (FitSettings.calibrate_iters): a few whole-clip numbers fitted with
the exact gradient, then folded into the per-driver residuals and the velocity scales."""
from __future__ import annotations

import math

import pytest
import torch


def test_stiffness_clusters_find_distinct_levels() -> None:
    from pd_tool.fit.stages import stiffness_clusters

    g = torch.Generator().manual_seed(0)
    levels = torch.cat([10.0 + 0.1 * torch.randn(100, generator=g), 13.0 + 0.1 * torch.randn(50, generator=g),
                        14.5 + 0.1 * torch.randn(30, generator=g)])
    labels = stiffness_clusters(levels, 3)
    assert torch.bincount(labels).tolist() == [100, 50, 30]  # softest first
    assert torch.equal(stiffness_clusters(levels, 3), labels)  # deterministic
    assert stiffness_clusters(levels, 1).unique().tolist() == [0]
    many = stiffness_clusters(levels, 10)  # more clusters than levels: some stay empty, none is lost
    assert len(many) == len(levels) and int(many.max()) < 10
    assert stiffness_clusters(levels[:2], 5).max() <= 1  # never more clusters than points


def test_calibration_lowers_the_whole_clip_loss_and_folds_exactly(tmp_path) -> None:
    from _plant import tiny_plant_problem
    from pd_tool.fit.problem import sequence_loss
    from pd_tool.fit.stages import calibrate

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _, pb, v0_true = tiny_plant_problem(tmp_path, 500, seed=3, size=24)
        # a uniform push along x from the velocity field (its last layer starts at zero),
        # two thirds of the video's top speed: the gain has something to scale
        with torch.no_grad():
            pb.velocities[0].net.last_layer.bias.copy_(torch.tensor([0.4, 0.0, 0.0]))
        s = pb.s
        s.calibrate_iters, s.lr_calibrate, s.calibrate_clusters = 5, 0.1, 2
        with torch.no_grad():
            E0 = pb.driver_E().clone()
        out = calibrate(pb, s)
        with torch.no_grad():
            after = float(sequence_loss(pb, pb.driver_E(), [pb.driver_v0(0)], None))
            E1 = pb.driver_E()
    finally:
        torch.set_num_threads(threads)
    history = out["losses"]
    assert len(history) == 5
    assert min(history) < 0.98 * history[0]  # the exact gradient found a lower loss
    # the kept parameters are the best seen, and folding them reproduces that loss
    assert after == pytest.approx(min(history), rel=1e-4)
    assert len(out["offsets"]) == 2 and len(out["gains"]) == 1
    moving = ~pb.static
    ratio = torch.log(E1[moving] / E0[moving])
    # every moving driver moved by one of the offsets (bounds far away: 1e3..1e8 Pa)
    offsets = torch.tensor(out["offsets"], dtype=ratio.dtype)
    assert float((ratio[:, None] - offsets[None, :]).abs().min(1).values.max()) < 1e-3
    assert max(abs(o) for o in out["offsets"]) > 1e-2  # and they did move
    assert torch.allclose(E1[pb.static], E0[pb.static], rtol=1e-5)  # static drivers keep their E
    assert pb.velocities[0].scale == pytest.approx(s.velocity_scale * out["gains"][0])
    assert math.isfinite(out["gains"][0]) and out["gains"][0] > 0


def test_calibration_needs_the_residuals() -> None:
    from pd_tool.fit.settings import FitSettings

    with pytest.raises(ValueError, match="calibration folds its offsets into the per-driver residuals"):
        FitSettings(quality="draft", calibrate_iters=3, driver_residual=False, stage1_level=False).resolved()
    with pytest.raises(ValueError, match="calibrate_clusters"):
        FitSettings(quality="draft", calibrate_clusters=0).resolved()


def _stage1_loss(pb, level: float) -> float:
    """velocity_iteration's loss with the level set to `level` (nats); leaves no gradients."""
    from pd_tool.fit.stages import velocity_iteration

    with torch.no_grad():
        pb.log_e_level.fill_(level)
    value = velocity_iteration(pb)
    for p in [pb.log_e_level, *pb.velocities.parameters()]:
        p.grad = None
    return value


def test_stage1_level_gradient_matches_finite_differences(tmp_path) -> None:
    """FitSettings.stage1_level: stage 1 fits one shared log-E offset with v0; its gradient
    through the three frames against central differences of the same loss."""
    from _plant import tiny_plant_problem
    from pd_tool.fit.stages import velocity_iteration

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        # 2 cm leaves: 500 Gaussians of 3 mm leaves on a 24-cell grid make the loss rough
        # at this scale (central differences from h = 0.05 to 0.005 scatter by 60%). Where
        # the loss is nearly flat in the level, its roughness swamps the slope (a plant
        # with |slope| 4e-5 scatters from 0.01 to 1.1 of the gradient over those h), so the
        # problem is one where E clearly moves the frames (slope 1.8e-4, steady to 5%)
        _, pb, _ = tiny_plant_problem(tmp_path, 500, seed=2, size=24, thin=False)
        pb.s.stage1_level = True
        with torch.no_grad():  # a push along x, so that E changes the frames
            pb.velocities[0].net.last_layer.bias.copy_(torch.tensor([0.4, 0.0, 0.0]))
            pb.log_e_level.fill_(0.2)
            # a fixed substep count, safe above the finite difference's largest E: the CFL
            # count steps with E, which the difference would see and the gradient does not
            sub = pb.substeps(pb.driver_E() * math.exp(0.3), pb.driver_v0(0))
        pb.substeps = lambda E, v0: sub
        velocity_iteration(pb)
        grad = float(pb.log_e_level.grad)
        h = 0.02
        fd = (_stage1_loss(pb, 0.2 + h) - _stage1_loss(pb, 0.2 - h)) / (2 * h)
    finally:
        torch.set_num_threads(threads)
    assert abs(fd) > 1e-4  # E is visible in the first frames
    assert grad == pytest.approx(fd, rel=0.05)


def test_stage1_level_folds_into_the_residuals_exactly(tmp_path) -> None:
    from _plant import tiny_plant_problem
    from pd_tool.fit.settings import FitSettings
    from pd_tool.fit.stages import fold_level

    _, pb, _ = tiny_plant_problem(tmp_path, 300, seed=1, size=16)
    pb.s.stage1_level = True
    with torch.no_grad():
        pb.log_e_residual.copy_(0.3 * torch.randn(len(pb.log_e_residual), generator=torch.Generator().manual_seed(0)))
        E0 = pb.driver_E().clone()
        pb.log_e_level.fill_(0.7)
    fold_level(pb)
    with torch.no_grad():
        E1 = pb.driver_E()
    assert float(pb.log_e_level.detach()) == 0.0
    assert torch.allclose(torch.log(E1), torch.log(E0) + 0.7, atol=1e-4)
    with pytest.raises(ValueError, match="stage1_level folds its offset into the per-driver residuals"):
        FitSettings(quality="draft", stage1_level=True, driver_residual=False).resolved()


def test_cli_level_default_is_the_settings_default() -> None:
    from cli import main
    from pd_tool.fit.settings import FitSettings

    level = next(p for p in main.commands["fit"].params if p.name == "level")
    assert level.default is FitSettings().stage1_level is True
    # the CLI writes its defaults out (it imports pd_tool lazily); --diffusion's is the settings' too
    diffusion = next(p for p in main.commands["fit"].params if p.name == "diffusion")
    assert diffusion.default == FitSettings().residual_diffusion > 0
