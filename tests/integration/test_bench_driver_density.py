"""bench/driver_density.py on a tiny plant: the reference against itself, and the
discretisations per grid, each with the drivers a cell it claims."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests._bench import load_bench

dd = load_bench("driver_density")


def test_a_tiny_plant_gives_the_reference_and_each_discretisation_per_grid() -> None:
    args = SimpleNamespace(gaussians=400, grids=[16], reference=24, per_cell=8, E=3e5, seconds=0.2, device="cpu",
                           data=None, ratio=None)
    rows = dd.run_scene("plant", args)
    assert [r["mode"] for r in rows] == ["reference (split)", "ratio", "split", "k-means 8 a cell", "product"]
    ref, ratio, split, km, product = rows
    assert ref["rms"] == 0.0 and ref["peak_ratio"] == pytest.approx(1.0) and ref["peak"] > 0
    assert split["drivers"] > ratio["drivers"] and km["per_cell"] > ratio["per_cell"]
    # 400 Gaussians at the ratio 0.5 hold fewer than 8 a cell even on 16 cells: the floor clusters sub-particles
    assert {k: v for k, v in product.items() if k != "mode"} == {k: v for k, v in km.items() if k != "mode"}
    assert km["per_cell"] == pytest.approx(8.0, rel=0.35)  # K-Means over the split cloud, 8 a cell
    for r in rows[1:]:
        assert np.isfinite(r["rms"]) and r["rms"] > 0 and r["grid"] == 16


def test_ratio_sets_the_ratio_rows_drivers() -> None:
    """--ratio 0.1 (the fit's) gives the ratio row a fifth of the default quality's 0.5 drivers."""
    base = dict(gaussians=400, grids=[16], reference=20, per_cell=8, E=3e5, seconds=0.1, device="cpu", data=None)
    rows = {r: dd.run_scene("plant", SimpleNamespace(**base, ratio=r))[1] for r in (None, 0.1)}
    assert rows[None]["mode"] == rows[0.1]["mode"] == "ratio"
    assert rows[0.1]["drivers"] == pytest.approx(rows[None]["drivers"] / 5, rel=0.2)
