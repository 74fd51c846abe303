"""Where a bake's frames go: the USD file and the splat formats of `--format`
(pd_tool.io.formats names them), all written in one pass over the simulation."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from pd_tool.core.quaternion import quat_left_matrix
from pd_tool.io.gltf import Z_UP_TO_Y_UP, GltfSplatWriter
from pd_tool.io.sequence import SplatSequenceWriter
from pd_tool.prepare.preparation import up_rotation


def gltf_axes(up_axis: str) -> np.ndarray:
    """Rotation [3, 3] from a scene whose up axis is `up_axis` to glTF's (+Y up)."""
    return Z_UP_TO_Y_UP @ up_rotation(up_axis)


class FrameOutputs:
    """Each frame to every writer the bake asked for.

    usd: a usd_export.UsdBakeWriter (or None) and R_usd / q_usd, the rotation from scene
    axes to the USD file's; splat: {format: SplatSequenceWriter | GltfSplatWriter}. Frames
    arrive in scene units and axes: positions [N, 3], (w, x, y, z) rotations [N, 4]."""

    def __init__(self, usd, R_usd: np.ndarray, q_usd, scales: np.ndarray, splat: dict) -> None:
        self.usd, self.splat = usd, splat
        self._scales = scales
        # Each frame is rotated into the USD file's axes by two float32 matrix products
        # (q_usd * q is linear in q); none where the axes agree. A torch Hamilton product
        # costs 13-20 ms a frame on the host at 300k Gaussians, a fifth of a frame's write.
        R = np.asarray(R_usd, np.float64)
        self._rotate = not np.array_equal(R, np.eye(3))
        self._R_usd_t = np.ascontiguousarray(R.T, np.float32)
        self._L_usd_t = np.ascontiguousarray(quat_left_matrix(np.asarray(torch.as_tensor(q_usd), np.float64)).T,
                                             np.float32)
        self.seconds = {f: 0.0 for f in (["usd"] if usd is not None else []) + list(splat)}  # writing, per format

    def write_frame(self, frame: int, positions: np.ndarray, quats: np.ndarray) -> None:
        if self.usd is not None:
            t = time.perf_counter()
            pos_usd, q_usd = positions, quats  # the splat writers below keep the scene's axes
            if self._rotate:
                pos_usd = np.asarray(positions, np.float32) @ self._R_usd_t
                q_usd = np.asarray(quats, np.float32) @ self._L_usd_t
            self.usd.write_frame(frame, pos_usd, q_usd, self._scales)
            self.seconds["usd"] += time.perf_counter() - t
        for fmt, w in self.splat.items():
            t = time.perf_counter()
            w.write_frame(frame, positions, quats)
            self.seconds[fmt] += time.perf_counter() - t

    def hold_frames(self, last: int) -> None:
        if self.usd is not None:
            self.usd.hold_frames(last)
        for w in self.splat.values():
            w.hold_frames(last)

    def close(self) -> dict[str, tuple[Path, int]]:
        """Publish every output; {format: (path, bytes)}. A writer that fails aborts the rest."""
        done: dict[str, tuple[Path, int]] = {}
        try:
            if self.usd is not None:
                t = time.perf_counter()
                self.usd.close()
                self.seconds["usd"] += time.perf_counter() - t
                done["usd"] = (self.usd.path, self.usd.path.stat().st_size)
            for fmt, w in self.splat.items():
                t = time.perf_counter()
                path = w.close()
                self.seconds[fmt] += time.perf_counter() - t
                done[fmt] = (path, w.bytes_written)
        except BaseException:
            self.abort()
            raise
        return done

    def abort(self) -> None:
        if self.usd is not None:
            self.usd.abort()
        for w in self.splat.values():
            w.abort()


def open_splat_writers(paths: dict[str, Path], scene, *, static: np.ndarray, up_axis: str, fps: float,
                       named: Path | None = None) -> dict:
    """The splat writers of `paths` (output_paths); each opens its temporary output. A
    file output other than `named` (OUT, which the user named) replaces only pdtool's own."""
    writers: dict = {}
    try:
        for fmt, path in paths.items():
            if fmt == "usd":
                continue
            what = f"--format {fmt} output {path}"
            if fmt == "gltf":
                writers[fmt] = GltfSplatWriter(path, scene, static=static, to_gltf=gltf_axes(up_axis), fps=fps,
                                               what=what, own_only=Path(path) != named)
            else:
                writers[fmt] = SplatSequenceWriter(path, scene, fmt=fmt.split("-")[0], fps=fps, up_axis=up_axis,
                                                   what=what)
    except BaseException:
        for w in writers.values():
            w.abort()
        raise
    return writers
