"""GaussianAnimator: drivers' motion to every Gaussian, static and unsimulated ones untouched."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pd_tool.bake.animate import GaussianAnimator
from pd_tool.io.synthetic import POT_TOP, make_plant
from pd_tool.prepare.preparation import PrepareOptions, prepare_scene


@pytest.fixture(scope="module")
def rig():
    scene = make_plant(2000, seed=1)
    scene.opacities[::10] = 0.005  # left out of the simulation (below the default min_opacity)
    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=16))
    drivers = prep.build_drivers(ratio=0.2, seed=0)
    return scene, prep, drivers, GaussianAnimator(scene, prep, drivers)


def test_static_and_unsimulated_gaussians_keep_the_scene_values_bit_for_bit(rig):
    scene, prep, drivers, anim = rig
    static = np.zeros(scene.count, bool)
    static[prep.foreground] = np.asarray(prep.static[:prep.count], bool)
    kept = static.copy()
    kept[np.setdiff1d(np.arange(scene.count), prep.foreground)] = True
    assert static.any() and (kept & ~static).any(), "the scene must have static and unsimulated Gaussians"
    moved = drivers.positions + torch.randn_like(drivers.positions) * 0.05
    pos, q = anim(moved)
    assert torch.equal(pos[kept], scene.positions[kept])
    assert torch.equal(q[kept], scene.quats[kept])
    assert not torch.allclose(pos[~kept], scene.positions[~kept], atol=1e-3)  # the rest do follow


def test_a_rigid_shift_of_the_drivers_shifts_the_moving_gaussians(rig):
    scene, prep, drivers, anim = rig
    shift = torch.tensor([0.02, -0.01, 0.03])  # metres, simulation axes
    pos, q = anim(drivers.positions + shift)
    moving = np.asarray(prep.foreground)[~np.asarray(prep.static[:prep.count], bool)]
    want = scene.positions[moving] + (shift / float(prep.transform.scale)) @ torch.as_tensor(prep.transform.R, dtype=torch.float32)
    torch.testing.assert_close(pos[moving], want, atol=2e-5, rtol=0)
    # a translation turns nothing
    dots = (q[moving] * scene.quats[moving]).sum(1).abs() / scene.quats[moving].norm(dim=1) / q[moving].norm(dim=1)
    assert float(dots.min()) > 1 - 1e-5
