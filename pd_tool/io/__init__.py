"""Splat file I/O: INRIA 3DGS .ply (binary and ASCII) and antimatter15 .splat read and
written here; the animated outputs of `bake --format` (formats.py names them) in
sequence.py (.ply and .spz frames), spz.py and gltf.py."""
from __future__ import annotations

from pathlib import Path

import torch

from pd_tool.core.errors import SplatFormatError
from pd_tool.io.ply import load_ply, save_ply
from pd_tool.io.splat import load_splat, save_splat
from pd_tool.core.scene import GaussianScene

SPLAT_SUFFIXES = (".ply", ".splat")


def load_splats(path: str | Path, device: str | torch.device = "cpu") -> GaussianScene:
    """Read a .ply or .splat file into a GaussianScene (torch tensors on `device`)."""
    path = Path(path)
    if not path.exists():
        raise SplatFormatError(f"{path}: no such file")
    if path.is_dir():
        raise SplatFormatError(f"{path}: is a folder; pass a .ply or .splat file")
    if not path.is_file():  # a FIFO or device would block or never end
        raise SplatFormatError(f"{path}: is not a regular file (a pipe or device?); pass a .ply or .splat file")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return load_ply(path, device)
    if suffix == ".splat":
        return load_splat(path, device)
    raise SplatFormatError(f"{path}: unknown extension '{path.suffix}'; pdtool reads .ply (INRIA 3DGS) and .splat")


def save_splats(scene: GaussianScene, path: str | Path) -> Path:
    """Write by extension: .ply (lossless for scenes read from .ply) or .splat (quantised)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".ply":
        return save_ply(scene, path)
    if suffix == ".splat":
        return save_splat(scene, path)
    raise SplatFormatError(f"{path}: unknown extension '{Path(path).suffix}'; write .ply or .splat")


__all__ = ["load_splats", "save_splats", "load_ply", "save_ply", "load_splat", "save_splat", "SPLAT_SUFFIXES"]
