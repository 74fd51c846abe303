"""Animated splats as a folder of complete 3DGS files, one per frame (`bake --format ply-seq`
and `spz-seq`): what Blender's 3DGS add-ons and most splat viewers load as a sequence.

The folder holds `frame_000000.ply` (or `.spz`), `frame_000001.ply`, ... (the frame
number last, zero-padded, so that a sort by name or by the trailing number gives frame
order) and `sequence.json`, a small manifest: format, frame count, fps, the files, the
scene's up axis and the axes the files use. Every file is a whole frame, so any frame
opens on its own.

- ply: the INRIA layout of the source scene, every property it had (normals, higher SH
  and extra properties included); positions and rotations change per frame, scales,
  opacities and colours stay (a bake moves and turns splats, it does not stretch them).
  Binary little-endian, in the scene's own axes, so that a frame lines up with the
  captured .ply.
- spz: SPZ version 3 (pd_tool.io.spz), in SPZ's right-up-back axes.

Frames stream to disk as the bake makes them (memory stays at one frame), into a hidden
temporary folder that replaces the destination only when the bake finishes
(pd_tool.core.atomic): an error or Ctrl-C leaves no half-written sequence.
"""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np

from pd_tool.core.atomic import MARK_TEXT, WRITTEN_BY, atomic_output
from pd_tool.core.errors import OutputError
from pd_tool.core.scene import GaussianScene
from pd_tool.io.ply import scene_to_records
from pd_tool.io.spz import FRACTIONAL_BITS, encode_spz, rdf_to_rub

SEQUENCE_FORMATS = ("ply", "spz")
MANIFEST_NAME = "sequence.json"
FRAME_DIGITS = 6
_PLY_TYPES = {"f4": "float", "f8": "double", "i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort",
              "i4": "int", "u4": "uint"}
SPZ_LIMIT = float(1 << (23 - FRACTIONAL_BITS))  # scene units: SPZ's 24-bit fixed-point positions


def frame_name(frame: int, fmt: str) -> str:
    return f"frame_{frame:0{FRAME_DIGITS}d}.{fmt}"


def _little_endian(records: np.ndarray) -> np.ndarray:
    dtype = np.dtype([(name, records.dtype[name].newbyteorder("<")) for name in records.dtype.names])
    return records.astype(dtype)


def ply_header(records: np.ndarray) -> bytes:
    """A binary little-endian PLY header for one vertex element with these records' fields."""
    lines = ["ply", "format binary_little_endian 1.0", f"comment {MARK_TEXT}", f"element vertex {len(records)}"]
    for name in records.dtype.names:
        dt = records.dtype[name]
        key = f"{dt.kind}{dt.itemsize}"
        if key not in _PLY_TYPES:
            raise OutputError(f"the scene's property {name!r} has type {dt}, which a PLY sequence cannot hold; "
                              f"use --format spz-seq or gltf")
        lines.append(f"property {_PLY_TYPES[key]} {name}")
    lines.append("end_header")
    return ("\n".join(lines) + "\n").encode("ascii")


class SplatSequenceWriter:
    """Write the frames of an animation as a folder of .ply or .spz files (module doc).

    Use as a context manager, or call close() (publishes the folder) or abort() (removes
    the temporary). `write_frame(f, positions, quats)`: frame f's positions [N, 3] and (w,
    x, y, z) rotations [N, 4], scene units and axes; frames must come in order from 0.
    `hold_frames(last)`: frames after the last written one up to `last` repeat it."""

    def __init__(self, folder: str | Path, scene: GaussianScene, *, fmt: str, fps: float, up_axis: str,
                 what: str | None = None) -> None:
        if fmt not in SEQUENCE_FORMATS:
            raise ValueError(f"sequence format must be one of {SEQUENCE_FORMATS}, not {fmt!r}")
        self.folder, self.fmt, self.fps, self.up_axis = Path(folder), fmt, float(fps), up_axis
        self.files: list[str] = []
        self.bytes_written = 0
        self.seconds = 0.0  # spent encoding and writing
        if fmt == "ply":
            self._records = _little_endian(scene_to_records(scene))
            self._header = ply_header(self._records)
        else:
            pos = scene.positions.detach().cpu().numpy()
            if len(pos) and float(np.abs(pos).max()) >= SPZ_LIMIT:
                raise OutputError(f"{what or self.folder}: the scene reaches {float(np.abs(pos).max()):.4g} scene "
                                  f"units from its origin, and SPZ holds positions within +-{SPZ_LIMIT:g}; "
                                  f"use --format ply-seq")
            sh = scene.sh.detach().cpu().numpy().astype(np.float32)
            rest = sh[:, 1:] if sh.shape[1] > 1 else None
            if rest is not None and rest.shape[1] > 15:
                rest = rest[:, :15]  # SPZ stops at degree 3
            _, _, self._sh_rest = rdf_to_rub(np.zeros((0, 3)), np.zeros((0, 4)), rest)
            self._sh_dc = sh[:, 0]
            self._log_scales = np.log(np.clip(scene.scales.detach().cpu().numpy().astype(np.float64), 1e-30, None))
            op = np.clip(scene.opacities.detach().cpu().numpy().astype(np.float64), 1e-7, 1 - 1e-7)
            self._logits = np.log(op / (1 - op))
        self._cm = atomic_output(self.folder, directory=True, what=what)
        self._tmp = self._cm.__enter__()
        self._open = True

    def __enter__(self) -> "SplatSequenceWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def write_frame(self, frame: int, positions: np.ndarray, quats: np.ndarray) -> None:
        if frame != len(self.files):
            raise ValueError(f"frame {frame} written out of order (next is {len(self.files)})")
        t = time.perf_counter()
        if self.fmt == "ply":
            rec = self._records.copy()
            for i, c in enumerate("xyz"):
                rec[c] = positions[:, i]
            for i in range(4):
                rec[f"rot_{i}"] = quats[:, i]
            data = self._header + rec.tobytes()
        else:
            pos, q, _ = rdf_to_rub(np.asarray(positions, np.float64), np.asarray(quats, np.float64), None)
            data = encode_spz(pos, q, self._log_scales, self._logits, self._sh_dc, self._sh_rest)
        name = frame_name(frame, self.fmt)
        (self._tmp / name).write_bytes(data)
        self.files.append(name)
        self.bytes_written += len(data)
        self.seconds += time.perf_counter() - t

    def hold_frames(self, last: int) -> None:
        """Frames len(files) .. last repeat the last written frame (a bake that came to rest)."""
        if not self.files:
            raise ValueError("hold_frames before any frame was written")
        src = self._tmp / self.files[-1]
        size = src.stat().st_size
        for f in range(len(self.files), last + 1):
            name = frame_name(f, self.fmt)
            shutil.copyfile(src, self._tmp / name)
            self.files.append(name)
            self.bytes_written += size

    def close(self) -> Path:
        """Write the manifest and move the folder into place; returns its path."""
        if not self._open:
            return self.folder
        manifest = {"written_by": WRITTEN_BY, "format": self.fmt, "frames": len(self.files), "fps": self.fps,
                    "start_frame": 0, "files": self.files, "scene_up_axis": self.up_axis,
                    "axes": "scene" if self.fmt == "ply" else "spz (right, up, back: the scene turned half a turn "
                                                                "about x)"}
        (self._tmp / MANIFEST_NAME).write_text(json.dumps(manifest, indent=1))
        self._open = False
        self._cm.__exit__(None, None, None)
        return self.folder

    def abort(self) -> None:
        """Remove the temporary folder; the destination is left as it was."""
        if not self._open:
            return
        self._open = False
        try:
            self._cm.__exit__(_Aborted, _Aborted(), None)
        except (_Aborted, OutputError):  # cleaned up; the error that stopped the bake is the one to report
            pass


class _Aborted(Exception):
    """Raised into the atomic output's context to make it clean up."""
