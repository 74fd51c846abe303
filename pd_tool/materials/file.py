"""The material file a fit writes and a bake reads, and the working-directory record.

Material file (`*.pdmat`, a numpy .npz without pickles, so it is safe to open):
    meta            uint8 [bytes] UTF-8 JSON: format, version, scene fingerprint and path,
                    preparation options, sim transform, driver settings, fit settings,
                    fit metrics, field names
    driver_E        float64 [Q]     Young's modulus per driving particle, Pa
    driver_v0       float32 [Q, 3]  fitted initial velocity per driver, m/s (sim axes)
    driver_rest     float64 [Q, 3]  driver rest positions, scene units (so any bake grid can use them)
    field.<name>.<param>            float32 arrays: the fitted fields' weights
Record (`.pdtool/last-fit.json` in the working directory): which scene and material file
the most recent `pdtool fit` there produced; a bare `pdtool bake` uses it.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import struct
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import zlib

from pd_tool.core.atomic import WRITTEN_BY, atomic_output, check_destination, check_own_file, path_kind
from pd_tool.core.errors import MaterialFileError, OutputError
from pd_tool.core.inputs import MiB, read_small_file
from pd_tool.drivers import nearest_drivers
from pd_tool.materials.presets import DRIVERS_PER_CELL_RANGE

FORMAT = "pdtool-material"
VERSION = 1
SUFFIX = ".pdmat"
RECORD_PATH = Path(".pdtool") / "last-fit.json"


def scene_fingerprint(path: str | Path) -> str:
    """sha256 of the scene file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@dataclass
class MaterialFile:
    """A fitted material. Arrays per driver; meta is JSON-ready."""

    driver_E: np.ndarray
    driver_v0: np.ndarray
    driver_rest: np.ndarray
    meta: dict[str, Any]
    fields: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        meta = {"format": FORMAT, "version": VERSION, **self.meta}
        arrays: dict[str, np.ndarray] = {
            "meta": np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), np.uint8),
            "driver_E": np.asarray(self.driver_E, np.float64),
            "driver_v0": np.asarray(self.driver_v0, np.float32),
            "driver_rest": np.asarray(self.driver_rest, np.float64),
        }
        for fname, params in self.fields.items():
            for pname, arr in params.items():
                arrays[f"field.{fname}.{pname}"] = np.asarray(arr, np.float32)
        # np.savez stamps each member with the current time; a fixed stamp makes the same
        # fit give the same bytes (determinism, fingerprints in batch --resume)
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
            for name in sorted(arrays):
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                member = io.BytesIO()
                np.lib.format.write_array(member, np.ascontiguousarray(arrays[name]), allow_pickle=False)
                zf.writestr(info, member.getvalue())
        with atomic_output(path) as tmp:
            tmp.write_bytes(buf.getvalue())
        return path

    @classmethod
    def load(cls, path: str | Path) -> "MaterialFile":
        """Read a .pdmat file. Raises MaterialFileError (one line) for anything that is not
        a well-formed material file of this version: a corrupt zip, arrays of the wrong
        type or shape, NaN/inf, header values out of range."""
        path = Path(path)
        if not path.is_file():
            raise MaterialFileError(f"{path}: no such material file; run `pdtool fit` first or pass --preset")
        data = _read_npz(path)
        meta_arr = data.pop("meta", None)
        if meta_arr is None or meta_arr.dtype != np.uint8 or meta_arr.ndim != 1:
            raise MaterialFileError(f"{path}: material file has no readable header; run `pdtool fit` again")
        try:
            meta = json.loads(meta_arr.tobytes().decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
            raise MaterialFileError(f"{path}: material file has no readable header; run `pdtool fit` again") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise MaterialFileError(f"{path}: not a pdtool material file; run `pdtool fit` again")
        if meta.get("version") != VERSION:
            raise MaterialFileError(
                f"{path}: material file version {meta.get('version')!r:.40} is not supported by this pdtool "
                f"(reads version {VERSION}); fit again or update pdtool"
            )
        _check_meta(path, meta)
        try:
            E, v0, rest = data.pop("driver_E"), data.pop("driver_v0"), data.pop("driver_rest")
        except KeyError as e:
            raise MaterialFileError(f"{path}: material file lacks {e}; run `pdtool fit` again") from None
        if not all(a.dtype.kind in "iuf" for a in (E, v0, rest)):
            raise MaterialFileError(f"{path}: material arrays are not real numbers; the file is corrupt")
        q = len(E) if E.ndim == 1 else -1
        if q < 1 or v0.shape != (q, 3) or rest.shape != (q, 3):
            raise MaterialFileError(f"{path}: material arrays disagree in shape; the file is corrupt")
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow to inf is refused below
            # the dtypes save() writes (a no-op for pdtool's own files)
            E, v0, rest = E.astype(np.float64), v0.astype(np.float32), rest.astype(np.float64)
        if not (np.isfinite(E).all() and (E > 0).all() and np.isfinite(v0).all() and np.isfinite(rest).all()):
            raise MaterialFileError(f"{path}: material holds NaN/inf or non-positive E; the file is corrupt")
        fields: dict[str, dict[str, np.ndarray]] = {}
        for key, arr in data.items():
            parts = key.split(".", 2)
            if len(parts) == 3 and parts[0] == "field":
                if arr.dtype.kind not in "iuf":
                    raise MaterialFileError(f"{path}: {key} is not an array of real numbers; the file is corrupt")
                with np.errstate(over="ignore", invalid="ignore"):
                    arr = arr.astype(np.float32)  # the fields' own dtype (save() writes float32)
                if not np.isfinite(arr).all():
                    raise MaterialFileError(f"{path}: {key} holds NaN/inf; the file is corrupt, run `pdtool fit` again")
                fields.setdefault(parts[1], {})[parts[2]] = arr
        return cls(driver_E=E, driver_v0=v0, driver_rest=rest, meta=meta, fields=fields)

    def _header_number(self, key: str, default: float | None = None) -> float:
        if key not in self.meta and default is not None:
            return default
        if key not in self.meta:
            raise MaterialFileError(f"material file has no '{key}' in its header; run `pdtool fit` again")
        return float(self.meta[key])

    @property
    def nu(self) -> float:
        """Poisson's ratio (MaterialFileError when the header lacks it)."""
        return self._header_number("nu")

    @property
    def density(self) -> float:
        """Density, kg/m^3 (MaterialFileError when the header lacks it)."""
        return self._header_number("density")

    @property
    def damping(self) -> float:
        """Damping, 1/s (0 when the header lacks it)."""
        return self._header_number("damping", 0.0)

    @property
    def scene_path(self) -> Path | None:
        """The scene the material was fitted to (absolute path as the fit saw it), or None
        when the header does not say (a hand-made file)."""
        p = self.meta.get("scene_path")
        return Path(p) if isinstance(p, str) and p else None

    @property
    def prepare(self) -> dict[str, Any]:
        """The fit's scene-preparation options (PrepareOptions.to_dict()); MaterialFileError
        when the header lacks them, so a bake cannot silently prepare the scene differently."""
        p = self.meta.get("prepare")
        if not isinstance(p, dict):
            raise MaterialFileError("material file has no 'prepare' settings in its header; run `pdtool fit` again "
                                    "(a bake must prepare the scene as the fit did)")
        return p

    def fit_simulation(self) -> dict[str, Any] | None:
        """How the fit simulated: grid_res (cells along the longest side), driver_ratio,
        driver_seed, min_per_cell (the floor of drivers a cell; 0 where the header names
        none) and cfl_safety (None in files written before it was recorded); None
        when the header does not say (a hand-made file). A bake that simulates the same way
        moves as the fit's model did: the fitted E is calibrated to that discretisation."""
        sim = self.meta.get("simulation")
        drivers = self.meta.get("drivers")
        grid = (self.meta.get("prepare") or {}).get("grid_res")
        try:
            if isinstance(sim, dict):
                floor = float(sim.get("min_drivers_per_cell") or 0.0)
                lo, hi = DRIVERS_PER_CELL_RANGE
                if not lo <= floor <= hi:  # NaN too: a bake would cluster without bound
                    raise ValueError(floor)
                return {"grid_res": int(sim["grid_res"]), "driver_ratio": float(sim["driver_ratio"]),
                        "driver_seed": int(sim["driver_seed"]), "cfl_safety": float(sim["cfl_safety"]),
                        "min_per_cell": floor}
            if isinstance(drivers, dict) and grid is not None:
                return {"grid_res": int(grid), "driver_ratio": float(drivers["ratio"]),
                        "driver_seed": int(drivers.get("seed", 0)), "cfl_safety": None, "min_per_cell": 0.0}
        except (KeyError, TypeError, ValueError):
            raise MaterialFileError("material file header has malformed 'simulation' settings; run `pdtool fit` "
                                    "again") from None
        return None

    def E_at(self, points_scene: np.ndarray) -> np.ndarray:
        """Young's modulus [M] (Pa) at points [M, 3] in scene units: the value of the
        nearest fitted driver, so a bake may use another grid or driver ratio than the fit."""
        import torch

        idx = nearest_drivers(torch.as_tensor(points_scene, dtype=torch.float64),
                              torch.as_tensor(self.driver_rest, dtype=torch.float64), k=1)
        return self.driver_E[idx[:, 0].numpy()]

    def check_scene(self, scene_path: str | Path, material_path: str | Path = "material") -> None:
        """Refuse a material fitted to another scene file."""
        want = self.meta.get("scene_sha256")
        got = scene_fingerprint(scene_path)
        if want != got:
            raise MaterialFileError(
                f"{material_path}: was fitted to {self.meta.get('scene_path', 'another scene')}, not to {scene_path} "
                f"(fingerprints differ); pass the scene it was fitted to, or fit this one"
            )


# Header values a bake reads, checked when present: (low, high, high is exclusive).
_META_RANGES = {"nu": (0.0, 0.5, True), "density": (0.0, math.inf, True), "damping": (0.0, math.inf, False)}
_META_TYPES = {"scene_path": str, "scene_sha256": str, "prepare": dict, "transform": dict, "fields": dict}
# A deflate stream expands at most ~1032:1; a member claiming more is corrupt (or a zip bomb).
_MAX_DEFLATE_RATIO = 1100


def _check_meta(path: Path, meta: dict[str, Any]) -> None:
    """Refuse header values of the wrong type or out of range (a hand-edited or corrupt file)."""
    for key, (lo, hi, hi_open) in _META_RANGES.items():
        if key not in meta:
            continue
        v = meta[key]
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= lo
        ok = ok and (v < hi if hi_open else v <= hi) and (v > 0 if key == "density" else True)
        if not ok:
            raise MaterialFileError(f"{path}: header '{key}' = {v!r:.40} is not a valid value; the file is corrupt, "
                                    f"run `pdtool fit` again")
    for key, typ in _META_TYPES.items():
        if key in meta and not isinstance(meta[key], typ):
            raise MaterialFileError(f"{path}: header '{key}' is not a {typ.__name__}; the file is corrupt, "
                                    f"run `pdtool fit` again")


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every .npy member of an .npz, without pickles. Each member's header is checked
    against the member's size before reading, so a corrupt header cannot make numpy
    allocate terabytes; every zip/npy failure becomes one MaterialFileError line."""
    bad = f"{path}: not a pdtool material file"
    try:
        with zipfile.ZipFile(path) as zf:
            out: dict[str, np.ndarray] = {}
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue  # np.savez writes only .npy members; anything else is not ours
                if info.compress_type == zipfile.ZIP_STORED:
                    limit = info.compress_size
                else:
                    limit = _MAX_DEFLATE_RATIO * info.compress_size + 1024
                if info.file_size > limit:
                    raise MaterialFileError(f"{bad} (member {info.filename} claims {info.file_size} bytes); "
                                            f"run `pdtool fit` again")
                with zf.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    if version == (1, 0):
                        shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                    elif version == (2, 0):
                        shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
                    else:
                        raise MaterialFileError(f"{bad} (.npy format {version}); run `pdtool fit` again")
                    if dtype.hasobject:
                        raise MaterialFileError(f"{bad} ({info.filename} holds Python objects); run `pdtool fit` again")
                    if dtype.itemsize * math.prod(shape) > info.file_size:
                        raise MaterialFileError(f"{bad} ({info.filename} declares shape {shape} but holds "
                                                f"{info.file_size} bytes); run `pdtool fit` again")
                with zf.open(info) as fh:
                    out[info.filename[:-4]] = np.lib.format.read_array(fh, allow_pickle=False)
            return out
    except MaterialFileError:
        raise
    # zipfile, zlib and numpy raise many types for damaged files (BadZipFile, zlib.error,
    # NotImplementedError for unknown compression, RuntimeError for encrypted members...)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, ValueError, OSError, EOFError, KeyError,
            NotImplementedError, RuntimeError, struct.error, MemoryError, TypeError) as e:
        raise MaterialFileError(f"{bad} ({type(e).__name__}); run `pdtool fit` again") from None


_RECORD_FIX = "move it away, or fit in another folder"


def is_material_file(path: str | Path) -> bool:
    """Whether `path` is a material file pdtool wrote (of any version): a regular file
    whose header names pdtool's format. Reads no pickle; a damaged one is not."""
    path = Path(path)
    if path.is_symlink() or not path.is_file():
        return False
    try:
        meta = _read_npz(path).get("meta")
        head = json.loads(meta.tobytes().decode("utf-8")) if meta is not None and meta.dtype == np.uint8 else None
    except (MaterialFileError, UnicodeDecodeError, ValueError, RecursionError):
        return False
    return isinstance(head, dict) and head.get("format") == FORMAT


def check_record(workdir: str | Path = ".") -> None:
    """Refuse (OutputError), before a fit runs, a fit record that cannot be written in
    `workdir`: .pdtool is a file or a link, or .pdtool/last-fit.json is not a record pdtool wrote
    (nobody named it, so it never replaces someone else's file), or the folder is not
    writable."""

    path = Path(workdir) / RECORD_PATH
    kind = path_kind(path.parent)
    if kind == "link":  # a project folder from elsewhere must not steer where pdtool writes
        raise OutputError(f"cannot write {path}: {path.parent} is a symbolic link; {_RECORD_FIX}", path=path)
    if kind not in (None, "dir"):
        raise OutputError(f"cannot write {path}: {path.parent} is a file, not a folder; {_RECORD_FIX}", path=path)
    check_own_file(path, "the record of the latest fit", _RECORD_FIX)
    check_destination(path)


def write_record(scene: str | Path, material: str | Path, workdir: str | Path = ".") -> Path:
    """Remember the latest fit in `workdir` (absolute paths), atomically. It replaces only
    a record that pdtool wrote (`check_record`); raises OutputError otherwise or when the
    folder cannot be written."""
    check_record(workdir)
    path = Path(workdir) / RECORD_PATH
    rec = {"written_by": WRITTEN_BY, "scene": str(Path(scene).resolve()), "material": str(Path(material).resolve()),
           "written": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    with atomic_output(path, own_only=True, what="the record of the latest fit") as tmp:
        tmp.write_text(json.dumps(rec, indent=2))
    return path


def read_record(workdir: str | Path = ".") -> tuple[Path, Path] | None:
    """(scene, material) of the latest fit in `workdir`, or None when there is none."""
    path = Path(workdir) / RECORD_PATH
    if not path.is_file():
        return None

    fix = "delete it, or pass --scene and --material"
    try:
        rec = json.loads(read_small_file(path, limit=MiB, error=MaterialFileError, fix=fix).decode("utf-8"))
        scene, material = Path(rec["scene"]), Path(rec["material"])
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError, RecursionError):
        raise MaterialFileError(f"{path}: unreadable fit record; delete it, or pass --scene and --material") from None
    for p in (scene, material):
        if not p.is_file():
            raise MaterialFileError(f"{path}: the last fit's file {p} is gone; pass --scene and --preset or --material")
    return scene, material
