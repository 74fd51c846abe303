"""Animated splats as one binary glTF 2.0 file with KHR_gaussian_splatting
(`bake --format gltf`).

The extension (Khronos, release candidate) puts splats on a POINTS primitive: POSITION,
KHR_gaussian_splatting:ROTATION (x, y, z, w), :SCALE (linear), :OPACITY (linear, 0-1)
and :SH_DEGREE_0_COEF_0 (the DC coefficient; colour = 0.5 + 0.2821 * it). It says nothing
about animating splats, so the frames are a flipbook in core glTF: one node per frame,
each with its own positions and rotations, shown by a STEP animation of its scale (1 on
its frames, 0 on the others). Scale, opacity and colour never change in a bake, so every
frame's primitive shares one copy of them, and the splats that never move (the static
region, splats left out of the simulation) sit once in a node of their own that is
always shown. Frame 0's node is the one shown by a viewer that plays no animation.

glTF is +Y up: the scene is turned so that its up axis is +Y. Only the DC colour is
written (higher SH degrees would have to be rotated with the scene).

Frames stream into an anonymous temporary file as the bake makes them; close() writes
the .glb (header, JSON chunk, binary chunk) through pd_tool.core.atomic, so the file
appears whole or not at all.
"""
from __future__ import annotations

import json
import shutil
import struct
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from pd_tool.core.atomic import WRITTEN_BY, atomic_output
from pd_tool.core.errors import OutputError
from pd_tool.core.quaternion import matrix_to_quat, quat_multiply
from pd_tool.core.scene import GaussianScene

EXTENSION = "KHR_gaussian_splatting"
FLOAT, ARRAY_BUFFER, POINTS, STEP = 5126, 34962, 0, "STEP"
GLB_MAGIC, GLB_VERSION, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 2, 0x4E4F534A, 0x004E4942
# scene axes turned so that +z is up (pd_tool.prepare.preparation.up_rotation), then
# (x, y, z) -> (x, z, -y): z-up to glTF's y-up
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


class GltfSplatWriter:
    """Write the frames of an animation as a .glb flipbook of KHR_gaussian_splatting
    primitives (module doc).

    scene: the rest splats (their scales, opacities and colours are written once);
    static [N] bool: splats that never move; to_gltf [3, 3]: rotation from scene axes to
    glTF's (x_gltf = to_gltf @ x_scene). `write_frame(f, positions, quats)` takes frame f's
    positions [N, 3] and (w, x, y, z) rotations [N, 4] in scene units and axes, frames in
    order from 0; `hold_frames(last)` shows the last written frame up to frame `last`.
    own_only: replace an existing file only when pdtool wrote it (an output the user did
    not name)."""

    def __init__(self, path: str | Path, scene: GaussianScene, *, static: np.ndarray, to_gltf: np.ndarray,
                 fps: float, what: str | None = None, own_only: bool = False) -> None:
        self.path, self.fps = Path(path), float(fps)
        self.static = np.asarray(static, bool)
        self.moving = ~self.static
        self._R = np.asarray(to_gltf, np.float64)
        self._qR = matrix_to_quat(torch.as_tensor(self._R)).float()
        self.n_frames = 0  # frames on the timeline (written or held)
        self.frame_nodes: list[int] = []  # frame -> index into self._frames (held frames repeat the last)
        self._frames: list[tuple[int, int]] = []  # (positions accessor, rotations accessor) per written frame
        self.bytes_written = 0
        self.seconds = 0.0
        self._views: list[dict] = []
        self._accessors: list[dict] = []
        self._bin = tempfile.TemporaryFile(dir=self.path.parent if self.path.parent.is_dir() else None)
        self._size = 0
        self._open = True
        self._what, self._own_only = what, own_only
        scales = scene.scales.detach().cpu().numpy().astype(np.float32)
        opac = scene.opacities.detach().cpu().numpy().astype(np.float32).clip(0.0, 1.0)
        dc = scene.sh.detach().cpu().numpy()[:, 0].astype(np.float32)
        self._shared = {name: self._accessor(a[self.moving], kind) for name, a, kind in (
            ("SCALE", scales, "VEC3"), ("OPACITY", opac, "SCALAR"), ("SH", dc, "VEC3"))}
        self._static_prim = None
        if self.static.any():
            pos, q = self._to_gltf(scene.positions.detach().cpu().numpy()[self.static],
                                   scene.quats.detach().cpu().numpy()[self.static])
            self._static_prim = {
                "POSITION": self._accessor(pos, "VEC3", bounds=True), "ROTATION": self._accessor(q, "VEC4"),
                "SCALE": self._accessor(scales[self.static], "VEC3"),
                "OPACITY": self._accessor(opac[self.static], "SCALAR"),
                "SH": self._accessor(dc[self.static], "VEC3")}

    def __enter__(self) -> "GltfSplatWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # ---- binary chunk
    def _accessor(self, a: np.ndarray, kind: str, *, bounds: bool = False, vertex: bool = True) -> int:
        data = np.ascontiguousarray(a, dtype="<f4")
        pad = (-self._size) % 4
        if pad:
            self._bin.write(b"\0" * pad)
            self._size += pad
        view = {"buffer": 0, "byteOffset": self._size, "byteLength": data.nbytes}
        if vertex:  # vertex attributes; an animation's keys are not
            view["target"] = ARRAY_BUFFER
        self._views.append(view)
        self._bin.write(data.tobytes())
        self._size += data.nbytes
        acc = {"bufferView": len(self._views) - 1, "componentType": FLOAT, "count": int(len(data)), "type": kind}
        if bounds:
            flat = data.reshape(len(data), -1)
            acc["min"] = flat.min(0).tolist() if len(flat) else [0.0] * flat.shape[1]
            acc["max"] = flat.max(0).tolist() if len(flat) else [0.0] * flat.shape[1]
        self._accessors.append(acc)
        return len(self._accessors) - 1

    def _to_gltf(self, positions: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pos = np.asarray(positions, np.float64) @ self._R.T
        q = quat_multiply(self._qR.expand(len(quats), 4), torch.as_tensor(np.asarray(quats, np.float32)))
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return pos, q.numpy()[:, [1, 2, 3, 0]]  # glTF stores x, y, z, w

    # ---- frames
    def write_frame(self, frame: int, positions: np.ndarray, quats: np.ndarray) -> None:
        if frame != self.n_frames:
            raise ValueError(f"frame {frame} written out of order (next is {self.n_frames})")
        t = time.perf_counter()
        pos, q = self._to_gltf(positions[self.moving], quats[self.moving])
        try:
            p_acc = self._accessor(pos, "VEC3", bounds=True)
            q_acc = self._accessor(q, "VEC4")
        except OSError as e:
            raise OutputError(f"cannot write {self.path}: {e.strerror or e}", path=self.path) from None
        self._frames.append((p_acc, q_acc))
        self.frame_nodes.append(len(self._frames) - 1)
        self.n_frames += 1
        self.seconds += time.perf_counter() - t

    def hold_frames(self, last: int) -> None:
        if not self._frames:
            raise ValueError("hold_frames before any frame was written")
        while self.n_frames <= last:
            self.frame_nodes.append(len(self._frames) - 1)
            self.n_frames += 1

    # ---- the file
    def _primitive(self, pos: int, rot: int, scale: int, opacity: int, sh: int) -> dict:
        return {"mode": POINTS, "attributes": {
            "POSITION": pos, f"{EXTENSION}:ROTATION": rot, f"{EXTENSION}:SCALE": scale,
            f"{EXTENSION}:OPACITY": opacity, f"{EXTENSION}:SH_DEGREE_0_COEF_0": sh},
            "extensions": {EXTENSION: {"kernel": "ellipse", "colorSpace": "srgb_rec709_display"}}}

    def _document(self) -> dict:
        meshes, nodes = [], []
        children = []
        if self._static_prim is not None:
            s = self._static_prim
            meshes.append({"name": "static", "primitives": [self._primitive(s["POSITION"], s["ROTATION"], s["SCALE"],
                                                                           s["OPACITY"], s["SH"])]})
            nodes.append({"name": "static", "mesh": 0})
            children.append(0)
        sh = self._shared
        frame_node = []
        for i, (p_acc, q_acc) in enumerate(self._frames):
            meshes.append({"name": f"frame_{i}", "primitives": [self._primitive(p_acc, q_acc, sh["SCALE"],
                                                                               sh["OPACITY"], sh["SH"])]})
            node = {"name": f"frame_{i}", "mesh": len(meshes) - 1}
            if i > 0:
                node["scale"] = [0.0, 0.0, 0.0]  # shown by the animation only
            nodes.append(node)
            frame_node.append(len(nodes) - 1)
            children.append(len(nodes) - 1)
        nodes.append({"name": "pdtool_bake", "children": children})
        doc = {"asset": {"version": "2.0", "generator": f"{WRITTEN_BY} bake"},
               "extensionsUsed": [EXTENSION], "scene": 0, "scenes": [{"nodes": [len(nodes) - 1]}],
               "nodes": nodes, "meshes": meshes}
        if len(self._frames) > 1:
            times = np.arange(self.n_frames, dtype=np.float32) / self.fps
            t_acc = self._accessor(times, "SCALAR", bounds=True, vertex=False)
            samplers, channels = [], []
            shown = np.asarray(self.frame_nodes)
            for i, node in enumerate(frame_node):
                on = (shown == i).astype(np.float32)[:, None].repeat(3, 1)
                samplers.append({"input": t_acc, "output": self._accessor(on, "VEC3", vertex=False),
                                 "interpolation": STEP})
                channels.append({"sampler": i, "target": {"node": node, "path": "scale"}})
            doc["animations"] = [{"name": "bake", "samplers": samplers, "channels": channels}]
        doc["bufferViews"] = self._views
        doc["accessors"] = self._accessors
        doc["buffers"] = [{"byteLength": self._size}]
        return doc

    def close(self) -> Path:
        """Write the .glb and move it into place; returns its path."""
        if not self._open:
            return self.path
        t = time.perf_counter()
        doc = self._document()  # may add the animation's accessors to the binary chunk
        js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        js += b" " * ((-len(js)) % 4)
        pad = (-self._size) % 4
        total = 12 + 8 + len(js) + 8 + self._size + pad
        with atomic_output(self.path, what=self._what, own_only=self._own_only) as tmp:
            with open(tmp, "wb") as f:
                f.write(struct.pack("<III", GLB_MAGIC, GLB_VERSION, total))
                f.write(struct.pack("<II", len(js), CHUNK_JSON))
                f.write(js)
                f.write(struct.pack("<II", self._size + pad, CHUNK_BIN))
                self._bin.seek(0)
                shutil.copyfileobj(self._bin, f, 1 << 24)
                f.write(b"\0" * pad)
        self._bin.close()
        self._open = False
        self.bytes_written = total
        self.seconds += time.perf_counter() - t
        return self.path

    def abort(self) -> None:
        if self._open:
            self._bin.close()
            self._open = False
