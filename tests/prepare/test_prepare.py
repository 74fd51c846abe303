"""Scene preparation: selection, static region, invertible box mapping, volumes, mass."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pd_tool.core.errors import PreparationError
from pd_tool.prepare.preparation import (
    WALL_CELLS, Box, PrepareOptions, SimTransform, fit_transform, particle_volumes,
    prepare_scene, up_rotation,
)
from pd_tool.prepare.outliers import select_outliers
from pd_tool.io.synthetic import POT_TOP, REGIONS, make_plant


@pytest.mark.parametrize("up", ["+x", "-x", "+y", "-y", "+z", "-z"])
def test_up_rotation_is_proper_and_maps_up_to_z(up: str) -> None:
    R = up_rotation(up)
    assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
    v = np.zeros(3)
    v["xyz".index(up[1])] = 1.0 if up[0] == "+" else -1.0
    assert np.allclose(R @ v, [0, 0, 1])


def test_box_parse_and_contains() -> None:
    b = Box.parse("1,1,1,0,0,0")
    assert b.lo == (0, 0, 0) and b.hi == (1, 1, 1)
    assert b.contains(np.array([[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]])).tolist() == [True, False]
    with pytest.raises(PreparationError, match="six"):
        Box.parse("1,2,3")


@pytest.mark.parametrize("up", ["+z", "-y"])
def test_transform_round_trip_and_box(up: str) -> None:
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [3.0, 1.0, 0.5] + [10, -4, 2]
    opts = PrepareOptions(up_axis=up, grid_res=32, padding=0.2)
    tr, dx, dims = fit_transform(pts, opts)
    sim = tr.to_sim(pts)
    np.testing.assert_allclose(tr.to_scene(sim), pts, rtol=0, atol=1e-12)
    # default scale: the longest extent becomes 1 m
    assert np.isclose(np.ptp(sim, axis=0).max(), 1.0)
    # the object stays clear of the wall cells, and the box only covers it plus padding
    box = np.array(dims) * dx
    assert (sim.min(0) >= WALL_CELLS * dx).all() and (sim.max(0) <= box - WALL_CELLS * dx).all()
    assert max(dims) == 32 and min(dims) < 32
    # a vector maps like a point difference
    np.testing.assert_allclose(tr.vector_to_sim(pts[1] - pts[0]), sim[1] - sim[0], atol=1e-12)
    again = SimTransform.from_dict(tr.to_dict())
    np.testing.assert_array_equal(again.to_sim(pts), sim)


def test_particle_volumes_sum_to_occupied_cells() -> None:
    rng = np.random.default_rng(1)
    pts = rng.uniform(0, 1, size=(3000, 3))
    dx = 0.1
    vol = particle_volumes(pts, dx)
    occupied = len(np.unique(np.floor(pts / dx), axis=0))
    assert np.isclose(vol.sum(), occupied * dx ** 3)
    # four points in one cell share it equally
    four = np.array([[0.01, 0.01, 0.01], [0.02, 0.02, 0.02], [0.05, 0.05, 0.05], [0.09, 0.01, 0.03]])
    np.testing.assert_allclose(particle_volumes(four, dx), dx ** 3 / 4)


def test_outliers_found() -> None:
    rng = np.random.default_rng(2)
    pts = np.concatenate([rng.uniform(0, 1, size=(5000, 3)), [[5.0, 5.0, 5.0]]])
    out = select_outliers(pts)
    assert out[-1] and out[:-1].mean() < 0.01


def test_prepare_plant_static_pot_and_mass() -> None:
    plant = make_plant(2000, seed=0)
    prep = prepare_scene(plant, PrepareOptions(static_below=POT_TOP, density_kg_m3=500.0))
    labels = plant.labels[prep.foreground]
    pot = labels == REGIONS.index("pot")
    assert prep.static[pot].all()
    assert not prep.static[labels == REGIONS.index("flower")].any()
    np.testing.assert_allclose(prep.masses, prep.volumes * 500.0)
    assert prep.positions_sim.shape == (prep.count, 3)
    assert any("static" in line for line in prep.report)


def test_foreground_box_and_errors() -> None:
    plant = make_plant(1000, seed=0)
    prep = prepare_scene(plant, PrepareOptions(foreground_box=(-1, -1, 0.3, 1, 1, 2)))
    assert (plant.positions[torch.as_tensor(prep.foreground)][:, 2] >= 0.3).all()
    with pytest.raises(PreparationError, match="keeps no Gaussians"):
        prepare_scene(plant, PrepareOptions(foreground_box=(5, 5, 5, 6, 6, 6)))
    with pytest.raises(PreparationError, match="density"):
        prepare_scene(plant, PrepareOptions(density_kg_m3=-1))


def test_synthetic_plant_is_deterministic() -> None:
    a, b, c = make_plant(600, seed=5), make_plant(600, seed=5), make_plant(600, seed=6)
    assert torch.equal(a.positions, b.positions) and torch.equal(a.sh, b.sh)
    assert not torch.equal(a.positions, c.positions)
    assert set(np.unique(a.labels)) == set(range(len(REGIONS)))


def test_fill_adds_simulated_particles_after_the_gaussians() -> None:
    from pd_tool.prepare.selection import selection_scene

    plant = make_plant(1500, seed=0)
    hollow = prepare_scene(plant, PrepareOptions(static_below=POT_TOP, fill="off"))
    filled = prepare_scene(plant, PrepareOptions(static_below=POT_TOP, fill="on"))
    assert hollow.n_filled == 0 and hollow.n_particles == hollow.count
    assert filled.n_filled > 0 and filled.n_particles == filled.count + filled.n_filled
    for arr in (filled.static, filled.volumes, filled.masses):
        assert len(arr) == filled.n_particles
    # filled particles inherit the static flag of their source Gaussian
    np.testing.assert_array_equal(filled.static[filled.count:], filled.static[:filled.count][filled.fill_source])
    assert any(line.startswith("fill (on)") for line in filled.report)
    assert selection_scene(filled).count == plant.count
