"""Presets: materials, quality levels and forces, shipped as TOML in the `presets` package.

A preset is named (e.g. `flower`) or given as a path to the user's own TOML file with the
same keys (one table, or a file whose single table is used).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from pd_tool.core.errors import PresetError
from pd_tool.core.inputs import MiB, read_small_file

KINDS = ("materials", "quality", "forces")
_REQUIRED = {
    "materials": {"E": float, "nu": float, "density": float},
    "quality": {"grid_res": int, "cfl_safety": float, "driver_ratio": float,
                "fit_velocity_iters": int, "fit_material_iters": int},
    "forces": {"at": str, "radius": float, "start": float, "duration": float, "magnitude": float},
}
# Bounds of every number a preset may hold, and why:
#   E 1 Pa - 1e12 Pa: foam to diamond; the work estimate refuses what a stiff E costs in substeps
#   nu 0 - 0.499: the elastic model needs nu < 0.5 (lambda grows without bound at 0.5)
#   density 1e-3 - 1e5 kg/m^3: aerogel to beyond osmium
#   grid_res 10 - 256 cells: 10 leaves room for the solver's walls; at 256 the fit's tape of
#       grids already needs about 18 GB (pd_tool/prepare/memory.py), at 512 about 140 GB
#   cfl_safety 0.05 - 1: above 1 the substep is unstable; below 0.05 it costs 20x the
#       substeps for no accuracy the physics benchmarks can see (0.25 vs 0.5: 0.2 points)
#   driver_ratio 1e-4 - 1: at most one driving particle per simulated Gaussian
#   min_drivers_per_cell 0 - 64: more than MAX_PER_CELL's 64 add time and no accuracy
#   fit_*_iters 0 - 10000: the shipped presets use at most 200
#   radius 0 - 10 (fraction of the object's size), start / duration 0 - 600 s (the longest
#       animation, pd_tool/cli_types.py), magnitude 0 - 1e6, damping 0 - 1000 1/s
# drivers a cell a floor may ask for (min_drivers_per_cell, fit_min_drivers_per_cell, and the
# fit's record of it in a material file): pd_tool.drivers.build's MAX_PER_CELL
DRIVERS_PER_CELL_RANGE = (0.0, 64.0)
_RANGES = {
    "E": (1.0, 1e12), "nu": (0.0, 0.499), "density": (1e-3, 1e5), "grid_res": (10, 256),
    "cfl_safety": (0.05, 1.0), "driver_ratio": (1e-4, 1.0), "fit_velocity_iters": (0, 10000),
    "fit_material_iters": (0, 10000), "radius": (0.0, 10.0), "start": (0.0, 600.0),
    "duration": (0.0, 600.0), "magnitude": (0.0, 1e6), "damping": (0.0, 1e3),
    "fit_grid_res": (10, 256), "thin_grid_res": (10, 256), "fit_cfl_safety": (0.05, 1.0), "fit_driver_ratio": (1e-4, 1.0),
    "min_drivers_per_cell": DRIVERS_PER_CELL_RANGE, "fit_min_drivers_per_cell": DRIVERS_PER_CELL_RANGE,
}
_OPTIONAL = {"materials": {"damping": float},
             # the fit's simulation settings; a quality preset without them fits with its bake settings
             "quality": {"fit_grid_res": int, "fit_cfl_safety": float, "fit_driver_ratio": float,
                         # the bake's grid for a scene with parts thinner than grid_res resolves
                         # (pd_tool.prepare.preparation.refine_for_thin); a preset without it keeps grid_res
                         "thin_grid_res": int,
                         # the bake's floor of drivers in each cell its moving particles occupy
                         # (PreparedScene.build_drivers); 0 turns it off, a preset without it keeps 8
                         "min_drivers_per_cell": float,
                         # the same floor in the fit's own simulation; a preset without it keeps 0
                         "fit_min_drivers_per_cell": float}}
_CHOICES = {"at": ("top", "all")}  # string settings with a fixed set of values


def _parse_toml(text: str, where: str) -> dict[str, Any]:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise PresetError(f"{where}: not valid TOML ({e}); check the file's syntax") from None
    except RecursionError:  # tomllib recurses per nested array / inline table
        raise PresetError(f"{where}: arrays or tables nested too deeply to be a preset; check the file") from None


def builtin(kind: str) -> dict[str, dict[str, Any]]:
    """All shipped presets of one kind, by name."""
    if kind not in KINDS:
        raise PresetError(f"unknown preset kind '{kind}'; choose one of {', '.join(KINDS)}")
    text = resources.files("presets").joinpath(f"{kind}.toml").read_text(encoding="utf-8")
    return _parse_toml(text, f"presets/{kind}.toml")


def _validate(kind: str, name: str, table: Any, where: str) -> dict[str, Any]:
    if not isinstance(table, dict):
        raise PresetError(f"{where}: '{name}' is not a table of settings")
    out = dict(table)
    optional = {k: t for k, t in _OPTIONAL.get(kind, {}).items() if k in table}
    for key, typ in {**_REQUIRED[kind], **optional}.items():
        if key not in table:
            raise PresetError(f"{where}: {kind} preset '{name}' lacks '{key}' (needs {', '.join(_REQUIRED[kind])})")
        val = table[key]
        if typ is str:
            if not isinstance(val, str):
                raise PresetError(f"{where}: '{name}.{key}' must be a string")
            if key in _CHOICES and val not in _CHOICES[key]:
                # caught here, not after the scene is prepared: a force aimed at nothing pushes nothing
                raise PresetError(f"{where}: '{name}.{key}' = {val!r:.40} is not one of "
                                  f"{', '.join(repr(c) for c in _CHOICES[key])}")
            continue
        if isinstance(val, bool) or not isinstance(val, (int, float)):
            raise PresetError(f"{where}: '{name}.{key}' must be a number, got {val!r:.40}")
        lo, hi = _RANGES.get(key, (-math.inf, math.inf))
        try:
            fval = float(val)
        except OverflowError:  # a TOML integer beyond float range
            fval = math.inf
        # finite first: int(nan) / int(inf) raise ValueError / OverflowError (TOML allows nan and inf)
        if not (math.isfinite(fval) and lo <= fval <= hi):
            raise PresetError(f"{where}: '{name}.{key}' = {val!r:.40} is outside [{lo:g}, {hi:g}]")
        if typ is int and fval != int(fval):
            raise PresetError(f"{where}: '{name}.{key}' must be a whole number, got {val!r:.40}")
        val = typ(val)
        out[key] = val
    return out


def load_preset(kind: str, name_or_path: str | Path) -> dict[str, Any]:
    """One preset: a shipped name, or a user's TOML file (path ending in .toml)."""
    text = str(name_or_path)
    if text.endswith(".toml") or Path(text).is_file():
        path = Path(text)
        if not path.is_file():
            raise PresetError(f"{path}: no such preset file")

        raw = read_small_file(path, limit=MiB, error=PresetError, fix="a preset is a small TOML file")
        try:
            data = _parse_toml(raw.decode("utf-8"), str(path))
        except UnicodeDecodeError:
            raise PresetError(f"{path}: not a text file; a preset is a TOML file") from None
        # one flat table, or a file with exactly one named table
        if set(_REQUIRED[kind]) & set(data):
            return _validate(kind, path.stem, data, str(path))
        tables = {k: v for k, v in data.items() if isinstance(v, dict)}
        if len(tables) != 1:
            raise PresetError(
                f"{path}: expected the keys {', '.join(_REQUIRED[kind])} at the top or in one table"
            )
        (name, table), = tables.items()
        return _validate(kind, name, table, str(path))
    presets = builtin(kind)
    if text not in presets:
        raise PresetError(
            f"unknown {kind} preset '{text}'; choose one of {', '.join(presets)} or pass a .toml file "
            f"(see `pdtool presets {kind}`)"
        )
    return _validate(kind, text, presets[text], f"presets/{kind}.toml")


def fit_simulation(quality: dict[str, Any]) -> tuple[int, float, float]:
    """(grid_res, cfl_safety, driver_ratio) the fit simulates with under a quality preset.

    The bake's grids come from bench/convergence.py (32 to 128 cells). The fit runs its
    differentiable simulation once per iteration, so it keeps coarser grids of its own
    (24 to 64 cells, a stem several cells wide), and a bake of a fitted material simulates
    as its fit did, the discretisation its E is calibrated to. The reference videos of the
    demo and the benchmarks use the fit's values."""
    return (int(quality.get("fit_grid_res", quality["grid_res"])),
            float(quality.get("fit_cfl_safety", quality["cfl_safety"])),
            float(quality.get("fit_driver_ratio", quality["driver_ratio"])))


def fit_min_per_cell(quality: dict[str, Any]) -> float:
    """The fit's floor of drivers in each cell its moving particles occupy under a quality
    preset (PreparedScene.build_drivers); 0: the fit's driver ratio alone."""
    return float(quality.get("fit_min_drivers_per_cell", 0.0))


@dataclass(frozen=True)
class Material:
    """A homogeneous material: E (Pa), nu, density (kg/m^3), damping (1/s)."""

    E: float
    nu: float
    density: float
    damping: float = 0.0

    @classmethod
    def from_preset(cls, name_or_path: str | Path) -> "Material":
        p = load_preset("materials", name_or_path)
        return cls(p["E"], p["nu"], p["density"], p.get("damping", 0.0))
