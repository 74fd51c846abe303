"""Material file and working-directory record: round trip, versioning, scene check, errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pd_tool.core.errors import MaterialFileError
from pd_tool.materials.file import FORMAT, MaterialFile, read_record, scene_fingerprint, write_record


def _material(scene: Path) -> MaterialFile:
    rng = np.random.default_rng(0)
    q = 40
    return MaterialFile(
        driver_E=10 ** rng.uniform(4, 6, q), driver_v0=rng.normal(size=(q, 3)).astype(np.float32),
        driver_rest=rng.uniform(0, 1, (q, 3)),
        meta={"scene_sha256": scene_fingerprint(scene), "scene_path": str(scene), "metrics": {"loss": 0.1}},
        fields={"material": {"planes": rng.normal(size=(3, 4, 8, 8)).astype(np.float32)}},
    )


def test_round_trip(tmp_path: Path) -> None:
    scene = tmp_path / "s.ply"
    scene.write_bytes(b"ply\nfake")
    m = _material(scene)
    back = MaterialFile.load(m.save(tmp_path / "m.pdmat"))
    np.testing.assert_array_equal(back.driver_E, m.driver_E)
    np.testing.assert_array_equal(back.driver_v0, m.driver_v0)
    np.testing.assert_array_equal(back.fields["material"]["planes"], m.fields["material"]["planes"])
    assert back.meta["format"] == FORMAT and back.meta["metrics"] == {"loss": 0.1}
    back.check_scene(scene)
    other = tmp_path / "o.ply"
    other.write_bytes(b"ply\nother")
    with pytest.raises(MaterialFileError, match="fingerprints differ"):
        back.check_scene(other)


@pytest.mark.parametrize("content,match", [(b"", "not a pdtool material"), (b"garbage" * 10, "not a pdtool material")])
def test_corrupt(tmp_path: Path, content: bytes, match: str) -> None:
    p = tmp_path / "bad.pdmat"
    p.write_bytes(content)
    with pytest.raises(MaterialFileError, match=match):
        MaterialFile.load(p)


def test_version_and_nan(tmp_path: Path) -> None:
    scene = tmp_path / "s.ply"
    scene.write_bytes(b"ply")
    m = _material(scene)
    m.meta["version"] = 99  # save() puts its own version first, a meta key overrides it
    with pytest.raises(MaterialFileError, match="version 99"):
        MaterialFile.load(m.save(tmp_path / "v.pdmat"))
    m = _material(scene)
    m.driver_E[3] = np.nan
    with pytest.raises(MaterialFileError, match="NaN"):
        MaterialFile.load(m.save(tmp_path / "n.pdmat"))


def test_record(tmp_path: Path) -> None:
    assert read_record(tmp_path) is None
    scene, mat = tmp_path / "a.ply", tmp_path / "a.pdmat"
    scene.write_bytes(b"x")
    mat.write_bytes(b"y")
    write_record(scene, mat, tmp_path)
    assert read_record(tmp_path) == (scene.resolve(), mat.resolve())
    mat.unlink()
    with pytest.raises(MaterialFileError, match="is gone"):
        read_record(tmp_path)


def test_fit_simulation_from_the_header(tmp_path: Path) -> None:
    scene = tmp_path / "s.ply"
    scene.write_bytes(b"ply\nfake")
    m = _material(scene)
    assert m.fit_simulation() is None  # a hand-made file says nothing: bake uses its quality preset
    # files from before "simulation" was recorded: grid and drivers from their own entries
    m.meta.update(prepare={"grid_res": 24}, drivers={"count": 40, "ratio": 0.1, "seed": 3})
    assert m.fit_simulation() == {"grid_res": 24, "driver_ratio": 0.1, "driver_seed": 3, "cfl_safety": None,
                                  "min_per_cell": 0.0}
    # a header without the fit's floor of drivers a cell was fitted without one
    m.meta["simulation"] = {"grid_res": 32, "driver_ratio": 0.25, "driver_seed": 0, "cfl_safety": 0.4}
    back = MaterialFile.load(m.save(tmp_path / "m.pdmat"))
    assert back.fit_simulation() == {"grid_res": 32, "driver_ratio": 0.25, "driver_seed": 0, "cfl_safety": 0.4,
                                     "min_per_cell": 0.0}
    back.meta["simulation"]["min_drivers_per_cell"] = 8
    assert back.fit_simulation()["min_per_cell"] == 8.0
    for bad in ({"grid_res": "many"}, {**back.meta["simulation"], "min_drivers_per_cell": 1e9},
                {**back.meta["simulation"], "min_drivers_per_cell": float("nan")}):
        back.meta["simulation"] = bad
        with pytest.raises(MaterialFileError, match="malformed 'simulation'"):
            back.fit_simulation()
