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
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pd_tool.atomic import atomic_output
from pd_tool.errors import MaterialFileError

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
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        with atomic_output(path) as tmp:
            tmp.write_bytes(buf.getvalue())
        return path

    @classmethod
    def load(cls, path: str | Path) -> "MaterialFile":
        path = Path(path)
        if not path.is_file():
            raise MaterialFileError(f"{path}: no such material file; run `pdtool fit` first or pass --preset")
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as e:
            raise MaterialFileError(f"{path}: not a pdtool material file ({type(e).__name__}); run `pdtool fit` again") from None
        try:
            meta = json.loads(bytes(data.pop("meta")).decode("utf-8"))
        except (KeyError, UnicodeDecodeError, json.JSONDecodeError, TypeError):
            raise MaterialFileError(f"{path}: material file has no readable header; run `pdtool fit` again") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise MaterialFileError(f"{path}: not a pdtool material file; run `pdtool fit` again")
        if meta.get("version") != VERSION:
            raise MaterialFileError(
                f"{path}: material file version {meta.get('version')} is not supported by this pdtool "
                f"(reads version {VERSION}); fit again or update pdtool"
            )
        try:
            E, v0, rest = data.pop("driver_E"), data.pop("driver_v0"), data.pop("driver_rest")
        except KeyError as e:
            raise MaterialFileError(f"{path}: material file lacks {e}; run `pdtool fit` again") from None
        q = len(E)
        if E.shape != (q,) or v0.shape != (q, 3) or rest.shape != (q, 3) or q == 0:
            raise MaterialFileError(f"{path}: material arrays disagree in shape; the file is corrupt")
        if not (np.isfinite(E).all() and (E > 0).all() and np.isfinite(v0).all() and np.isfinite(rest).all()):
            raise MaterialFileError(f"{path}: material holds NaN/inf or non-positive E; the file is corrupt")
        fields: dict[str, dict[str, np.ndarray]] = {}
        for key, arr in data.items():
            parts = key.split(".", 2)
            if len(parts) == 3 and parts[0] == "field":
                fields.setdefault(parts[1], {})[parts[2]] = arr
        return cls(driver_E=E, driver_v0=v0, driver_rest=rest, meta=meta, fields=fields)

    @property
    def nu(self) -> float:
        return float(self.meta["nu"])

    @property
    def density(self) -> float:
        return float(self.meta["density"])

    @property
    def damping(self) -> float:
        return float(self.meta.get("damping", 0.0))

    def E_at(self, points_scene: np.ndarray) -> np.ndarray:
        """Young's modulus [M] (Pa) at points [M, 3] in scene units: the value of the
        nearest fitted driver, so a bake may use another grid or driver ratio than the fit."""
        import torch

        from pd_tool.drivers import nearest_drivers

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


def write_record(scene: str | Path, material: str | Path, workdir: str | Path = ".") -> Path:
    """Remember the latest fit in `workdir` (absolute paths), atomically."""
    path = Path(workdir) / RECORD_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    rec = {"scene": str(Path(scene).resolve()), "material": str(Path(material).resolve()),
           "written": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(rec, indent=2))
    return path


def read_record(workdir: str | Path = ".") -> tuple[Path, Path] | None:
    """(scene, material) of the latest fit in `workdir`, or None when there is none."""
    path = Path(workdir) / RECORD_PATH
    if not path.is_file():
        return None
    try:
        rec = json.loads(path.read_text())
        scene, material = Path(rec["scene"]), Path(rec["material"])
    except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError):
        raise MaterialFileError(f"{path}: unreadable fit record; delete it, or pass --scene and --material") from None
    for p in (scene, material):
        if not p.is_file():
            raise MaterialFileError(f"{path}: the last fit's file {p} is gone; pass --scene and --preset or --material")
    return scene, material
