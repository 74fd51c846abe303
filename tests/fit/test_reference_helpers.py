"""pd_tool.fit.reference's helpers for synthetic references: the frame height, the plant
with its video on disk, and the Gaussians' motion under a drag."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pd_tool.fit.reference import reference_height, simulate_positions, write_plant_with_video
from pd_tool.io.synthetic import POT_TOP, make_plant
from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
from pd_tool.video.folder import load_reference_video


def test_reference_height_square_below_512_then_16_9() -> None:
    assert reference_height(192) == 192 and reference_height(511) == 511
    assert reference_height(512) == 288 and reference_height(1024) == 576


def test_write_plant_with_video(tmp_path: Path) -> None:
    out = write_plant_with_video(tmp_path / "w", 300, size=24, frames=3)
    assert (out / "plant.ply").is_file()
    ref = load_reference_video(out / "video", working_size=24)
    assert ref.num_frames == 3 and tuple(ref.frames[0].shape[:2]) == (24, 24)


@pytest.fixture(scope="module")
def plant():
    scene = make_plant(400, seed=0)
    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=16))
    return scene, prep, prep.build_drivers(ratio=0.5, seed=0)


def test_simulate_positions_moves_the_free_part_only(plant) -> None:
    scene, prep, drivers = plant
    E = np.full(len(drivers.positions), 1.0e5)
    stats: dict = {}
    x = simulate_positions(scene, prep, drivers, E, nu=0.3, seconds=0.2, fps=30.0, accel=(0.0, 6.0, 0.0),
                           device="cpu", cfl_safety=0.5, stats=stats)
    assert x.shape == (7, scene.count, 3)  # rest + round(0.2 * 30) frames, scene units
    assert np.array_equal(x[0], scene.positions.numpy())
    assert stats["substeps"] >= 1
    moved = np.linalg.norm(x[-1] - x[0], axis=1)
    fg = prep.foreground
    static = fg[prep.static[: prep.count]]
    assert moved[static].max() < 1e-6 and moved[fg].max() > 1e-3
    assert (x[-1, fg, 1] - x[0, fg, 1]).mean() > 0  # dragged along +y
