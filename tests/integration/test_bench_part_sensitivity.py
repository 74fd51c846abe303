"""bench/part_sensitivity.py at a tiny scale: an unchanged E changes nothing, a softer part
moves, most of all its own Gaussians."""
from __future__ import annotations

import pytest

from tests._bench import load_bench

ps = load_bench("part_sensitivity")


def test_a_part_moves_its_own_gaussians_when_softened_and_nothing_when_not() -> None:
    same = ps.sensitivity(12, ["flower"], 1.0, 1500, 0.2, "cpu")
    assert same["parts"]["flower"] == {"all": 0.0, "own": 0.0}  # the CPU runs are bit-identical
    softer = ps.sensitivity(12, ["flower"], 100.0, 1500, 0.2, "cpu")
    moved = softer["parts"]["flower"]
    assert 0 < moved["all"] < moved["own"], moved
    assert softer["peak"] == pytest.approx(same["peak"]) and softer["dx_m"] > 0
