"""bench/peer_newton.py at CI scale: both solvers run the same block from the same sway,
and the comparison it prints is computed from their trajectories."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
pytest.importorskip("newton")


def _bench():
    spec = importlib.util.spec_from_file_location("peer_newton", REPO / "bench" / "peer_newton.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_sway_is_zero_at_the_clamp_and_speed_at_the_top() -> None:
    mod = _bench()
    x = np.array([[0, 0, 0.0], [0, 0, 0.5], [0, 0, 1.0]], np.float32)
    v = mod.sway(x, np.array([True, False, False]), 0.3)
    np.testing.assert_allclose(v[:, 0], [0.0, 0.15, 0.3], rtol=1e-6)
    assert not v[:, 1:].any()


@pytest.mark.slow
def test_both_solvers_sway_the_same_block() -> None:
    mod = _bench()
    row = mod.compare(3000, 20, 0.2, 0.3, [2], "cpu")
    ours, theirs = row["pdtool"], row["newton"][0]
    # both move the block, and neither flies apart: the sway's peak over 0.2 s is at most
    # its top speed times the time, and a pdtool frame takes CFL substeps (more than one)
    assert 0.005 < ours["peak_m"] <= 0.3 * 0.2 * 1.05
    assert 0.05 < theirs["peak_ratio"] < 1.5
    assert ours["steps_per_frame"] > 1 and theirs["steps_per_frame"] == 2
    assert np.isfinite(theirs["rms_diff_over_peak"]) and theirs["time_ratio"] > 0
    assert len(ours["motion_m"]) == len(theirs["motion_m"]) == row["frames"] + 1
