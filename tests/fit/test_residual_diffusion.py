"""The residuals' diffusion step (pd_tool/fit/diffusion.py): against a float64 reference,
against the analytic decay of a mode on a ring (the same per-step decay at two driver
densities), the maximum principle, and wired into a fit's stage 2."""
from __future__ import annotations

import math

import pytest
import torch

from pd_tool.fit.diffusion import MAX_FRACTION, diffuse, diffusion_fractions


def _ring(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n points on a unit circle: each one's two neighbours [n, 2], its distance to them
    (the chord) [n], and the angles [n]."""
    theta = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    i = torch.arange(n)
    spacing = torch.full((n,), 2 * math.sin(math.pi / n), dtype=torch.float64)
    return torch.stack([(i - 1) % n, (i + 1) % n], 1), spacing, theta


def test_step_matches_a_dense_float64_reference() -> None:
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(60, 3, generator=g, dtype=torch.float64)
    d = torch.cdist(pos, pos)
    d.fill_diagonal_(math.inf)
    pairs = d.topk(6, largest=False).indices
    r = torch.randn(60, generator=g, dtype=torch.float64)
    dx, cells2 = 0.2, 0.03
    h = torch.tensor([float(d[i, pairs[i]].mean()) for i in range(60)], dtype=torch.float64)
    frac = torch.minimum(cells2 * dx**2 / h**2, torch.tensor(MAX_FRACTION, dtype=torch.float64))
    want = torch.tensor([float(r[i] + frac[i] * (r[pairs[i]].mean() - r[i])) for i in range(60)], dtype=torch.float64)
    got = r.clone()
    diffuse(got, pairs, diffusion_fractions(h, dx, cells2))
    assert torch.allclose(got, want, rtol=0, atol=1e-12)
    # float32 on the same data agrees to float32 rounding
    got32 = r.float()
    diffuse(got32, pairs, diffusion_fractions(h.float(), dx, cells2))
    assert torch.allclose(got32.double(), want, atol=1e-5)


def test_a_mode_decays_as_analysed_and_the_same_at_two_densities() -> None:
    dx, cells2, m, steps = 0.05, 0.02, 3, 40
    decay = {}
    for n in (200, 400):
        pairs, spacing, theta = _ring(n)
        h = float(spacing[0])
        frac = diffusion_fractions(spacing, dx, cells2)
        assert torch.allclose(frac, torch.full_like(frac, cells2 * dx**2 / h**2))
        r = torch.cos(m * theta)
        for _ in range(steps):
            diffuse(r, pairs, frac)
        amplitude = float((r * torch.cos(m * theta)).sum() * 2 / n)
        exact = (1 - cells2 * dx**2 / h**2 * (1 - math.cos(2 * math.pi * m / n))) ** steps
        assert amplitude == pytest.approx(exact, rel=1e-9)
        # the long-wavelength limit, exp(-steps D dx^2 m^2 / 2) on a unit circle
        assert amplitude == pytest.approx(math.exp(-steps * cells2 * dx**2 * m**2 / 2), rel=2e-3)
        decay[n] = 1 - amplitude
    assert decay[400] == pytest.approx(decay[200], rel=1e-3)  # 4x the fraction, the same smoothing


def test_fraction_is_capped_and_constants_and_bounds_are_kept() -> None:
    pairs, spacing, _ = _ring(50)
    frac = diffusion_fractions(spacing, dx=10.0, cells2=1.0)
    assert float(frac.max()) == pytest.approx(MAX_FRACTION)
    r = torch.full((50,), 0.7, dtype=torch.float64)
    diffuse(r, pairs, frac)
    assert torch.equal(r, torch.full((50,), 0.7, dtype=torch.float64))
    g = torch.Generator().manual_seed(1)
    r = torch.randn(50, generator=g, dtype=torch.float64)
    lo, hi, spread = float(r.min()), float(r.max()), float(r.std())
    for _ in range(20):
        diffuse(r, pairs, frac)
        assert lo - 1e-12 <= float(r.min()) and float(r.max()) <= hi + 1e-12
    assert float(r.std()) < 0.5 * spread
    # a single driver has no neighbours: nothing to average, and no NaN written
    one = torch.tensor([0.3])
    diffuse(one, torch.zeros((1, 0), dtype=torch.long), torch.tensor([0.5]))
    assert float(one) == pytest.approx(0.3)


def test_settings_refuse_a_negative_or_non_finite_diffusion() -> None:
    from pd_tool.fit.settings import FitSettings

    for bad in (-0.01, math.nan, math.inf):
        with pytest.raises(ValueError, match="residual_diffusion"):
            FitSettings(quality="draft", residual_diffusion=bad).resolved()
    assert FitSettings(quality="draft", residual_diffusion=0.0).resolved().residual_diffusion == 0.0


def test_stage_two_diffuses_the_residuals(tmp_path, monkeypatch) -> None:
    """A two-iteration stage 2 calls the step once per iteration with the setting's D, and
    not at all when it is 0."""
    from _plant import tiny_plant_video
    from pd_tool.fit.problem import FitProblem
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(tmp_path, 600, seed=2, size=32, n_frames=3)
    refs = [load_reference_video(tmp_path / "video", working_size=32)]
    calls: list[tuple[float, float]] = []
    original = FitProblem.diffuse_residuals

    def spy(self, cells2):
        # the spacing it scales by: each driver's mean distance to its paired neighbours
        x = self.x_rest.double()
        want = torch.stack([(x[self.driver_pairs[i]] - x[i]).norm(dim=1).mean() for i in range(len(x))])
        assert torch.allclose(self.driver_spacing.double(), want, rtol=1e-5)
        before = self.log_e_residual.detach().clone()
        original(self, cells2)
        calls.append((cells2, float((self.log_e_residual.detach() - before).abs().max())))

    monkeypatch.setattr(FitProblem, "diffuse_residuals", spy)
    for cells2, want in ((0.05, 2), (0.0, 0)):
        calls.clear()
        run_fit(scene, tmp_path / "plant.ply", refs, tmp_path / f"m{cells2}.pdmat",
                prepare_options=PrepareOptions(static_below=POT_TOP),
                settings=FitSettings(quality="draft", velocity_iters=1, material_iters=2, working_long_side=32,
                                     residual_diffusion=cells2))
        assert len(calls) == want
        assert all(c == cells2 for c, _ in calls)
        if want:
            # after a material step the residuals differ between drivers, so the step moves them
            assert calls[-1][1] > 0.0, calls
