"""pd_tool.prepare.split: sub-particles over each Gaussian's extent, several a cell."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from pd_tool.core.scene import GaussianScene
from pd_tool.prepare.split import split_particles
from pd_tool.io.synthetic import POT_TOP, make_plant
from pd_tool.prepare.preparation import PrepareOptions, SimTransform, prepare_scene


def _rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' rotation matrix (float64), independent of the quaternion helpers."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _two_gaussian_prep():
    """Two Gaussians (one flat and turned, one small and static) and one filled particle,
    in a scene whose transform rotates z-up to y-up and doubles lengths."""
    axis, angle = (1.0, 2.0, 0.5), 0.7
    half = angle / 2
    k = np.asarray(axis) / np.linalg.norm(axis)
    q = np.array([[math.cos(half), *(math.sin(half) * k)], [1.0, 0.0, 0.0, 0.0]])
    scales = np.array([[0.06, 0.03, 0.001], [0.001, 0.001, 0.001]])
    pos = np.array([[0.1, 0.2, 0.3], [0.5, 0.5, 0.5]])
    scene = GaussianScene(positions=torch.tensor(pos, dtype=torch.float32), quats=torch.tensor(q, dtype=torch.float32),
                          scales=torch.tensor(scales, dtype=torch.float32), opacities=torch.ones(2),
                          sh=torch.zeros(2, 1, 3))
    R = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    tr = SimTransform(rotation=tuple(map(tuple, R)), scale=2.0, shift=(0.1, 0.1, 0.1))
    sim = tr.to_sim(pos)
    prep = SimpleNamespace(positions_sim=np.concatenate([sim, [[0.9, 0.9, 0.9]]]), count=2,
                           foreground=np.array([0, 1]), transform=tr, dx=0.04,
                           static=np.array([False, True, False]), volumes=np.array([8.0, 1.0, 2.0]),
                           masses=np.array([16.0, 2.0, 4.0]))
    return scene, prep, _rotation(axis, angle), R, scales


def test_a_flat_gaussian_becomes_a_sheet_over_its_extent() -> None:
    scene, prep, Rq, R, scales = _two_gaussian_prep()
    drivers, owner = split_particles(scene, prep, per_cell=2, most=4)
    # sigma in metres 0.12 / 0.06 / 0.002 against a spacing of 0.02: 4 (clipped from 12) x 4 (6) x 1
    assert np.bincount(owner).tolist() == [16, 1, 1]
    sub = drivers.positions.double().numpy()[owner == 0]
    local = (sub - prep.positions_sim[0]) @ (R @ Rq)  # back to the Gaussian's own axes, metres
    sigma = scales[0] * 2.0
    for a, n in enumerate((4, 4, 1)):
        want = ((np.arange(n) + 0.5) / n * 2 - 1) * sigma[a]
        assert np.allclose(np.unique(local[:, a].round(6)), want, atol=1e-6)
    assert np.allclose(sub.mean(0), prep.positions_sim[0], atol=1e-6)


def test_mass_volume_and_pins_are_shared_per_particle() -> None:
    scene, prep, *_ = _two_gaussian_prep()
    drivers, owner = split_particles(scene, prep, per_cell=2, most=4)
    for name, want in (("mass", prep.masses), ("volume", prep.volumes)):
        got = np.bincount(owner, getattr(drivers, name).double().numpy())
        assert np.allclose(got, want, rtol=1e-6)
    assert np.array_equal(drivers.static.numpy(), prep.static[owner])
    # the filled particle (after the Gaussians) stays one particle where it was
    assert np.allclose(drivers.positions.numpy()[owner == 2], prep.positions_sim[2:], atol=1e-6)
    # each particle's first sub-particle, and the sub-particles in particle order
    assert np.array_equal(owner[drivers.labels.numpy()], np.arange(3)) and np.all(np.diff(owner) >= 0)


@pytest.fixture(scope="module")
def plant():
    scene = make_plant(400, seed=0)
    return scene, prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=32))


def test_a_prepared_plant_gets_several_particles_a_cell(plant) -> None:
    scene, prep = plant
    drivers, owner = split_particles(scene, prep)
    x = drivers.positions.double().numpy()

    def per_cell(p):
        return len(p) / len(np.unique(np.floor(p / prep.dx).astype(np.int64), axis=0))

    assert len(x) > 2 * prep.n_particles and per_cell(x) > 2 * per_cell(np.asarray(prep.positions_sim))
    assert np.isclose(drivers.mass.double().sum().item(), prep.masses.sum(), rtol=1e-5)
    # every Gaussian hangs on its 8 nearest sub-particles (a dense search)
    pts = np.asarray(prep.positions_sim)
    d = ((pts[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    near = np.sort(np.take_along_axis(d, drivers.neighbors.numpy(), 1), 1)
    assert np.allclose(near, np.sort(d, 1)[:, :8], atol=1e-9)
