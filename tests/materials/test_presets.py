"""Presets: every shipped preset validates; user TOML files work; bad ones fail clearly."""
from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main
from pd_tool.core.errors import PresetError
from pd_tool.materials.presets import KINDS, Material, builtin, fit_simulation, load_preset


@pytest.mark.parametrize("kind", KINDS)
def test_builtin_presets_validate(kind: str) -> None:
    names = list(builtin(kind))
    assert names
    for name in names:
        assert isinstance(load_preset(kind, name), dict)


def test_required_names_shipped() -> None:
    assert {"flower", "leafy-plant", "fabric-hat", "rubber-cord", "jelly"} <= set(builtin("materials"))
    assert {"draft", "default", "final"} <= set(builtin("quality"))
    assert {"poke", "gust", "drag"} <= set(builtin("forces"))


def test_fit_has_its_own_simulation_settings(tmp_path: Path) -> None:
    q = load_preset("quality", "default")
    grid, cfl, ratio = fit_simulation(q)
    assert (grid, cfl, ratio) == (q["fit_grid_res"], q["fit_cfl_safety"], q["fit_driver_ratio"])
    # every shipped fit keeps a stem several cells wide (24 cells or more), and every bake
    # grid is one that bench/convergence.py measured (32 cells or more)
    for name in builtin("quality"):
        q = load_preset("quality", name)
        assert fit_simulation(q)[0] >= 24 and q["grid_res"] >= 32
    # a user's quality file without fit_* values fits with its bake values
    mine = tmp_path / "mine.toml"
    mine.write_text("grid_res = 40\ncfl_safety = 0.4\ndriver_ratio = 0.2\nfit_velocity_iters = 1\n"
                    "fit_material_iters = 1\n")
    assert fit_simulation(load_preset("quality", mine)) == (40, 0.4, 0.2)
    mine.write_text(mine.read_text() + "fit_grid_res = 2\n")
    with pytest.raises(PresetError, match="fit_grid_res"):
        load_preset("quality", mine)


def test_user_toml_file(tmp_path: Path) -> None:
    flat = tmp_path / "mine.toml"
    flat.write_text("E = 1e4\nnu = 0.2\ndensity = 900\n")
    assert Material.from_preset(flat) == Material(1e4, 0.2, 900.0)
    nested = tmp_path / "nested.toml"
    nested.write_text("[soft]\nE = 5e3\nnu = 0.1\ndensity = 100\n")
    assert Material.from_preset(str(nested)).E == 5e3


@pytest.mark.parametrize(
    "text,match",
    [("E = 1e4\nnu = 0.2\n", "lacks 'density'"), ("E = 'x'\nnu = 0.2\ndensity = 1\n", "must be a number"),
     ("E = 1e4\nnu = 0.7\ndensity = 1\n", "outside"), ("E = = 3", "not valid TOML")],
)
def test_bad_user_toml(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(PresetError, match=match):
        load_preset("materials", path)


def test_unknown_name_names_the_choices() -> None:
    with pytest.raises(PresetError, match="flower"):
        load_preset("materials", "granite")


def test_cli_lists_presets() -> None:
    res = CliRunner().invoke(main, ["presets", "materials"])
    assert res.exit_code == 0 and "rubber-cord" in res.stdout and "E=2e+06" in res.stdout
