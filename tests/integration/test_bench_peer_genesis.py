"""bench/peer_genesis.py's side of the match, without Genesis: the block it hands over is
the one Genesis's box sampler fills (k^3 particles in a box of k particle sizes centred on
the block), each particle weighing particle_size^3 as Genesis weighs it, with pdtool's clamp
and sway."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parents[2] / "bench"


def _bench(name: str):
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_block_is_what_genesis_samples() -> None:
    mod = _bench("peer_genesis")
    b = mod.block_scene(20000, 32, 0.3)
    k = round(b["n"] ** (1 / 3))
    assert b["n"] == k ** 3 == 19683 and b["x"].shape == (b["n"], 3)
    side = b["particle_size"] * k  # the box Genesis fills
    assert np.all(np.abs(b["x"] - 0.5) <= side / 2 + 1e-6)
    assert np.ptp(b["x"], axis=0).min() > 0.98 * side  # and the block fills it
    np.testing.assert_allclose(b["vol"], b["particle_size"] ** 3, rtol=1e-9)
    np.testing.assert_allclose(b["mass"], mod.DENSITY * b["vol"], rtol=1e-9)
    assert 0 < b["static"].mean() < 0.2 and np.all(b["v0"][b["static"]] == 0) and b["v0"][:, 0].max() > 0.29
