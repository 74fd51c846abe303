"""The synthetic speed-benchmark scenes of pd_tool.io.synthetic: shapes, units, ranges and
determinism."""
from __future__ import annotations

import numpy as np
import torch

from pd_tool.io.synthetic import make_block, make_splat_ball


def test_make_block_fills_a_centred_cube_at_eight_per_cell() -> None:
    n, res = 4000, 16
    x, vol, mass, E, static = make_block(n, res)
    assert x.shape == (n, 3) and x.dtype == np.float32
    assert vol.shape == mass.shape == E.shape == static.shape == (n,)
    side = (n / 8.0) ** (1.0 / 3.0) / res
    assert np.all(np.abs(x - 0.5) <= side / 2 + 1e-6)
    assert np.isclose(vol.sum(), side ** 3) and np.allclose(mass, vol * 1000.0) and np.all(E == 1.0e5)
    occupied = len(np.unique(np.floor(x * res).astype(int), axis=0))
    assert 4 < n / occupied < 12  # about 8 per occupied cell
    assert 0 < static.sum() < n / 10 and np.all(x[static, 2] < x[~static, 2].min())  # a thin bottom layer
    again = make_block(n, res)
    assert all(np.array_equal(a, b) for a, b in zip((x, vol, mass, E, static), again))


def test_make_splat_ball_ranges_and_seed() -> None:
    s = make_splat_ball(300, seed=3)
    assert s.count == 300 and s.sh.shape == (300, 16, 3) and s.labels is None
    assert float(s.positions.norm(dim=1).max()) <= 1.0 + 1e-6
    assert torch.allclose(s.quats.norm(dim=1), torch.ones(300), atol=1e-5)
    assert 0.005 - 1e-7 <= float(s.scales.min()) and float(s.scales.max()) <= 0.04 + 1e-7
    assert 0.1 <= float(s.opacities.min()) and float(s.opacities.max()) <= 0.9
    assert torch.equal(make_splat_ball(300, seed=3).positions, s.positions)
    assert not torch.equal(make_splat_ball(300, seed=4).positions, s.positions)
    assert torch.allclose(make_splat_ball(300, seed=3, scale_factor=2.0).scales, 2.0 * s.scales)
