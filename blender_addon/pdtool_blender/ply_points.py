"""A minimal .ply reader for the point preview: positions and display colours only.

I/O for display, not pdtool logic: the preview shows where the Gaussians are so that
the user can place the static box and the force. numpy only (Blender ships it), no
relative imports (the tests load this file on its own).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814  # degree-0 SH basis; colour = 0.5 + SH_C0 * f_dc
_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertex positions and RGBA display colours of a 3DGS (or any point) .ply.

    Returns:
        positions [N, 3] float32 in the file's units; colours [N, 4] float32 in 0-1
        (from f_dc_0..2 and the opacity logit, else red/green/blue, else grey).
    Raises:
        ValueError with one line naming the file, when it is not a readable point .ply.
    """
    path = Path(path)
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise ValueError(f"{path}: not a PLY file (it does not start with 'ply')")
        fmt, count, props, element = None, None, [], None
        while True:
            raw = f.readline()
            if not raw:
                raise ValueError(f"{path}: PLY header has no end_header line")
            words = raw.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format" and len(words) > 1:
                fmt = words[1]
            elif words[0] == "element" and len(words) > 2:
                element = words[1]
                if element == "vertex":
                    count = int(words[2])
                elif count is None and int(words[2]) > 0:
                    raise ValueError(f"{path}: a '{element}' element comes before the vertices")
            elif words[0] == "property" and element == "vertex":
                if words[1] == "list" or words[1] not in _TYPES:
                    raise ValueError(f"{path}: vertex property {' '.join(words[1:])!r} is not supported")
                props.append((words[2], _TYPES[words[1]]))
        if count is None or fmt is None:
            raise ValueError(f"{path}: no vertex element in the PLY header")
        if fmt == "ascii":
            table = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2)
            data = {name: table[:, i] for i, (name, _) in enumerate(props)}
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            dtype = np.dtype([(name, order + t) for name, t in props])
            buf = f.read(dtype.itemsize * count)
            if len(buf) < dtype.itemsize * count:
                raise ValueError(f"{path}: file is truncated ({len(buf)} of {dtype.itemsize * count} vertex bytes)")
            data = np.frombuffer(buf, dtype=dtype, count=count)
    names = [n for n, _ in props]
    if not all(k in names for k in "xyz"):
        raise ValueError(f"{path}: vertices have no x, y, z")
    pos = np.stack([np.asarray(data[k], np.float32) for k in "xyz"], 1)
    col = np.full((count, 4), 0.8, np.float32)
    col[:, 3] = 1.0
    if all(f"f_dc_{i}" in names for i in range(3)):
        col[:, :3] = 0.5 + SH_C0 * np.stack([np.asarray(data[f"f_dc_{i}"], np.float32) for i in range(3)], 1)
    elif all(k in names for k in ("red", "green", "blue")):
        scale = 255.0 if dict(props)["red"] == "u1" else 1.0
        col[:, :3] = np.stack([np.asarray(data[k], np.float32) for k in ("red", "green", "blue")], 1) / scale
    if "opacity" in names:
        col[:, 3] = 1.0 / (1.0 + np.exp(-np.asarray(data["opacity"], np.float32)))
    return pos, np.clip(np.nan_to_num(col), 0.0, 1.0)

