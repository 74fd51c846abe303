"""Pinhole cameras (OpenCV/COLMAP convention) and loaders for the usual camera files.

Inside pdtool a camera maps world points to pixels with
``x_cam = world_to_camera @ [x_world, 1]`` (x right, y down, z forward) and
``u = fx * x / z + cx``, ``v = fy * y / z + cy``, where pixel (i, j) covers
[i, i + 1) x [j, j + 1), so its centre is (i + 0.5, j + 0.5) and cx = width / 2 is the
image centre.

Files read by ``load_cameras`` (auto-detected):

- INRIA 3DGS ``cameras.json``: a list of {id, img_name, width, height, position [3],
  rotation [3][3] (camera-to-world rotation, OpenCV axes), fx, fy}.
- NeRF/Blender ``transforms.json``: {camera_angle_x | fl_x [, fl_y, cx, cy, w, h],
  frames: [{file_path, transform_matrix (camera-to-world, OpenGL axes)}]}.
- pdtool ``camera.json`` (one camera beside a video's frames), schema version 1::

      {"version": 1, "width": 512, "height": 512,
       "fx": 600.0, "fy": 600.0, "cx": 256.0, "cy": 256.0,
       "world_to_camera": [[...4...], [...], [...], [0, 0, 0, 1]],
       "fps": 30.0, "name": "view0"}

  Instead of ``world_to_camera`` it may give ``position`` [3] (camera centre in world)
  and ``rotation`` [3][3] (camera-to-world rotation, OpenCV axes), as cameras.json does.
  ``cx``/``cy`` default to the image centre, ``fy`` to ``fx``; ``fps`` and ``name``
  are optional. A list of such objects, or {"cameras": [...]}, holds several views.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from pd_tool.core.atomic import WRITTEN_BY, atomic_output
from pd_tool.core.errors import CameraError
from pd_tool.core.inputs import MiB, read_small_file

CAMERA_JSON_VERSION = 1
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips camera y and z (OpenGL <-> OpenCV)


@dataclass
class Camera:
    """One pinhole view.

    width, height: image size in pixels. fx, fy, cx, cy: intrinsics in pixels.
    world_to_camera: [4, 4] float64 rigid transform, OpenCV axes (x right, y down, z forward).
    name: view name (image file stem for loaded cameras). fps: frame rate of a video, or None.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    name: str = ""
    fps: float | None = None

    def __post_init__(self) -> None:
        self.width = int(self.width)
        self.height = int(self.height)
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in (self.fx, self.fy, self.cx, self.cy))
        self.world_to_camera = np.asarray(self.world_to_camera, dtype=np.float64).reshape(4, 4)
        if self.fps is not None:
            self.fps = float(self.fps)

    @property
    def K(self) -> np.ndarray:
        """[3, 3] float64 intrinsic matrix in pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """[3] camera position in world units."""
        r = self.world_to_camera[:3, :3]
        return -r.T @ self.world_to_camera[:3, 3]

    @property
    def camera_to_world(self) -> np.ndarray:
        """[4, 4] inverse of world_to_camera (OpenCV axes)."""
        return np.linalg.inv(self.world_to_camera)

    def resized(self, width: int, height: int) -> "Camera":
        """Same view at another resolution: intrinsics scale with the image, so the field of
        view is kept (a different aspect ratio stretches the pixels instead of cropping)."""
        if int(width) <= 0 or int(height) <= 0:
            raise CameraError(f"camera resize to {width}x{height}: width and height must be positive")
        sx = int(width) / self.width
        sy = int(height) / self.height
        return Camera(
            int(width), int(height), self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
            self.world_to_camera.copy(), self.name, self.fps,
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points [N, 3] -> pixel coordinates [N, 2] and depth [N] as [N, 3] (u, v, z)."""
        p = np.asarray(points, dtype=np.float64) @ self.world_to_camera[:3, :3].T + self.world_to_camera[:3, 3]
        z = p[:, 2]
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy, z], -1)

    def to_dict(self) -> dict[str, Any]:
        """The pdtool camera.json object (schema version 1)."""
        d: dict[str, Any] = {
            "version": CAMERA_JSON_VERSION,
            "name": self.name,
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "world_to_camera": self.world_to_camera.tolist(),
        }
        if self.fps is not None:
            d["fps"] = self.fps
        return d


# ----------------------------------------------------------------------------- loaders


def _read_json(path: Path) -> Any:
    if not path.exists():
        raise CameraError(f"{path}: camera file not found; pass an existing cameras.json, transforms.json or camera.json")
    if path.is_dir():
        for name in ("camera.json", "cameras.json", "transforms.json"):
            if (path / name).is_file():
                return _read_json(path / name)
        raise CameraError(f"{path}: folder holds no camera.json, cameras.json or transforms.json; pass the camera file itself")

    # a transforms.json of thousands of frames is a few MiB
    data = read_small_file(path, limit=256 * MiB, error=CameraError,
                           fix="pass a cameras.json, transforms.json or camera.json file")
    try:
        return json.loads(data.decode("utf-8")), path
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CameraError(f"{path}: not valid JSON ({e}); fix the file or re-export the cameras") from None
    except RecursionError:  # json recurses per nesting level; a corrupt file can nest thousands deep
        raise CameraError(f"{path}: JSON nested too deeply to be a camera file; fix the file or re-export the cameras") from None


def _num(path: Path, where: str, obj: dict, key: str, default: Any = None) -> float:
    if key not in obj:
        if default is not None:
            return default
        raise CameraError(f"{path}: {where} has no '{key}'; add it (see the camera.json schema in docs)")
    v = obj[key]
    if not _is_finite_number(v):
        raise CameraError(f"{path}: {where} '{key}' must be a finite number, found {v!r:.40}")
    return float(v)


def _is_finite_number(v: Any) -> bool:
    """A JSON number that is finite as a float (an integer beyond 1e308 is not: float() and
    math.isfinite() raise OverflowError on it)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _focal(path: Path, where: str, obj: dict, key: str, default: Any = None) -> float:
    """A focal length in pixels: finite and positive (0 divides by zero when projecting,
    a negative one mirrors the image)."""
    v = _num(path, where, obj, key, default)
    if not v > 0:
        raise CameraError(f"{path}: {where} '{key}' must be a positive focal length in pixels, found {v!r}")
    return v


def _fov_focal(path: Path, where: str, obj: dict, key: str, size: int) -> float:
    """Focal length in pixels from a NeRF field of view (radians, strictly between 0 and pi)."""
    angle = _num(path, where, obj, key)
    if not 0.0 < angle < math.pi:
        raise CameraError(f"{path}: {where} '{key}' = {angle!r} is not a field of view in radians (0 < angle < pi)")
    focal = 0.5 * size / math.tan(0.5 * angle)
    if not math.isfinite(focal):  # an angle like 1e-320 gives an infinite focal length
        raise CameraError(f"{path}: {where} '{key}' = {angle!r} is too small a field of view; give it in radians")
    return focal


def _matrix(path: Path, where: str, v: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        m = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float range
        m = None
    if m is None or m.shape != shape or not np.all(np.isfinite(m)):
        raise CameraError(f"{path}: {where} must be a finite {'x'.join(map(str, shape))} array of numbers, found {v!r:.80}")
    return m


def _rigid(path: Path, where: str, rot: np.ndarray) -> np.ndarray:
    """Check that rot is a rotation (allowing float noise); re-orthonormalise it."""
    if np.abs(rot).max() > 1.0 + 1e-3:  # a rotation's entries lie in [-1, 1]; 1e308 would overflow the SVD
        raise CameraError(f"{path}: {where} rotation is not a proper rotation matrix (an entry is "
                          f"{np.abs(rot).max():.3g}); fix the extrinsics")
    u, sv, vt = np.linalg.svd(rot)
    if np.max(np.abs(sv - 1.0)) > 1e-3 or np.linalg.det(u @ vt) < 0:
        raise CameraError(f"{path}: {where} rotation is not a proper rotation matrix (singular values {np.round(sv, 4).tolist()}); fix the extrinsics")
    if np.max(np.abs(sv - 1.0)) < 1e-9:
        return rot  # already orthonormal: keep the file's values exactly (lossless round trip)
    return u @ vt


def _size(path: Path, where: str, obj: dict, key: str, default: int | None = None) -> int:
    v = obj.get(key, default)
    if v is None:
        raise CameraError(f"{path}: {where} has no '{key}'; add the image {key} in pixels")
    # isfinite first: int(inf) raises OverflowError and int(nan) ValueError (JSON allows both)
    if not _is_finite_number(v) or v != int(v) or v <= 0:
        raise CameraError(f"{path}: {where} '{key}' must be a positive integer, found {v!r:.40}")
    return int(v)


def _from_position_rotation(path: Path, where: str, obj: dict) -> np.ndarray:
    pos = _matrix(path, f"{where} 'position'", obj["position"], (3,))
    rot = _rigid(path, where, _matrix(path, f"{where} 'rotation'", obj["rotation"], (3, 3)))
    w2c = np.eye(4)
    w2c[:3, :3] = rot.T
    w2c[:3, 3] = -rot.T @ pos
    return w2c


def _load_inria(path: Path, data: list) -> list[Camera]:
    cams = []
    for i, c in enumerate(data):
        where = f"camera {i}"
        if not isinstance(c, dict) or "position" not in c or "rotation" not in c:
            raise CameraError(f"{path}: {where} lacks 'position' and 'rotation'; an INRIA cameras.json entry needs id, img_name, width, height, position, rotation, fx, fy")
        w, h = _size(path, where, c, "width"), _size(path, where, c, "height")
        fx = _focal(path, where, c, "fx")
        fy = _focal(path, where, c, "fy", fx)
        cams.append(Camera(w, h, fx, fy, w / 2.0, h / 2.0, _from_position_rotation(path, where, c),
                           name=str(c.get("img_name", c.get("id", i)))))
    return cams


def _load_nerf(path: Path, data: dict) -> list[Camera]:
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CameraError(f"{path}: transforms.json has no 'frames' list; add frames with transform_matrix")
    cams = []
    for i, f in enumerate(frames):
        where = f"frame {i}"
        if not isinstance(f, dict) or "transform_matrix" not in f:
            raise CameraError(f"{path}: {where} has no 'transform_matrix'; add the camera-to-world 4x4")
        merged = {**data, **f}  # per-frame intrinsics override the global ones
        # 'w'/'h' (nerfstudio) or 'width'/'height'; _size validates either (int() of a string or inf would raise)
        w = _size(path, where, merged, "w" if "w" in merged else "width") if ("w" in merged or "width" in merged) else None
        h = _size(path, where, merged, "h" if "h" in merged else "height") if ("h" in merged or "height" in merged) else None
        if w is None or h is None:
            raise CameraError(f"{path}: {where} has no image size; add 'w' and 'h' (pixels) to transforms.json (Blender exports omit them: use the rendered image size)")
        if "fl_x" in merged:
            fx = _focal(path, where, merged, "fl_x")
        elif "camera_angle_x" in merged:
            fx = _fov_focal(path, where, merged, "camera_angle_x", w)
        else:
            raise CameraError(f"{path}: {where} has neither 'fl_x' nor 'camera_angle_x'; add the focal length")
        if "fl_y" in merged:
            fy = _focal(path, where, merged, "fl_y")
        elif "camera_angle_y" in merged:
            fy = _fov_focal(path, where, merged, "camera_angle_y", h)
        else:
            fy = fx
        cx = _num(path, where, merged, "cx", w / 2.0)
        cy = _num(path, where, merged, "cy", h / 2.0)
        c2w_gl = _matrix(path, f"{where} 'transform_matrix'", f["transform_matrix"], (4, 4))
        if not np.allclose(c2w_gl[3], [0, 0, 0, 1], atol=1e-6):  # else its inverse is not a rigid transform
            raise CameraError(f"{path}: {where} 'transform_matrix' last row must be [0, 0, 0, 1], found {c2w_gl[3].tolist()}")
        c2w_gl[:3, :3] = _rigid(path, where, c2w_gl[:3, :3])
        w2c = np.linalg.inv(c2w_gl @ _GL_TO_CV)
        name = Path(str(f.get("file_path", f"frame_{i:04d}"))).stem
        cams.append(Camera(w, h, fx, fy, cx, cy, w2c, name=name))
    return cams


def _load_pdtool(path: Path, obj: dict, where: str) -> Camera:
    if not isinstance(obj, dict):  # e.g. {"cameras": [[...]]}
        raise CameraError(f"{path}: {where} is not a JSON object; each camera is {{\"width\": ..., \"fx\": ..., \"world_to_camera\": ...}}")
    version = obj.get("version", CAMERA_JSON_VERSION)
    if version != CAMERA_JSON_VERSION:
        raise CameraError(f"{path}: {where} has camera.json version {version!r}, this pdtool reads version {CAMERA_JSON_VERSION}; upgrade pdtool or rewrite the file")
    w, h = _size(path, where, obj, "width"), _size(path, where, obj, "height")
    fx = _focal(path, where, obj, "fx")
    fy = _focal(path, where, obj, "fy", fx)
    cx = _num(path, where, obj, "cx", w / 2.0)
    cy = _num(path, where, obj, "cy", h / 2.0)
    if "world_to_camera" in obj:
        w2c = _matrix(path, f"{where} 'world_to_camera'", obj["world_to_camera"], (4, 4))
        if not np.allclose(w2c[3], [0, 0, 0, 1], atol=1e-6):
            raise CameraError(f"{path}: {where} 'world_to_camera' last row must be [0, 0, 0, 1], found {w2c[3].tolist()}")
        w2c[:3, :3] = _rigid(path, where, w2c[:3, :3])
    elif "position" in obj and "rotation" in obj:
        w2c = _from_position_rotation(path, where, obj)
    else:
        raise CameraError(f"{path}: {where} has no extrinsics; add 'world_to_camera' (4x4) or 'position' + 'rotation'")
    fps = obj.get("fps")
    if fps is not None:
        fps = _num(path, where, obj, "fps")
        if fps <= 0:
            raise CameraError(f"{path}: {where} 'fps' must be positive, found {fps}")
    return Camera(w, h, fx, fy, cx, cy, w2c, name=str(obj.get("name", "")), fps=fps)


def load_cameras(path: str | os.PathLike) -> list[Camera]:
    """Read every view of a camera file (INRIA cameras.json, NeRF transforms.json or pdtool
    camera.json; see the module docstring). A folder is searched for those names.

    Raises CameraError (one line: file, problem, fix) for missing or malformed files.
    """
    data, path = _read_json(Path(path))
    if isinstance(data, dict) and "frames" in data:
        cams = _load_nerf(path, data)
    elif isinstance(data, dict) and isinstance(data.get("cameras"), list):
        cams = [_load_pdtool(path, c, f"camera {i}") for i, c in enumerate(data["cameras"])]
    elif isinstance(data, dict) and ("world_to_camera" in data or "fx" in data):
        cams = [_load_pdtool(path, data, "camera")]
    elif isinstance(data, list) and data and all(isinstance(c, dict) for c in data):
        if "world_to_camera" in data[0] or "version" in data[0]:
            cams = [_load_pdtool(path, c, f"camera {i}") for i, c in enumerate(data)]
        else:
            cams = _load_inria(path, data)
    else:
        raise CameraError(f"{path}: not a known camera file (expected an INRIA cameras.json list, a NeRF transforms.json with 'frames', or a pdtool camera.json)")
    if not cams:
        raise CameraError(f"{path}: holds no cameras; add at least one view")
    return cams


def select_view(cameras: list[Camera], view: int | str | None = None) -> Camera:
    """Pick a view: None -> the first; int -> that index; str -> the camera of that name
    (a string of digits that names no camera is taken as an index)."""
    if not cameras:
        raise CameraError("no cameras to choose a view from; pass a camera file with at least one view")
    if view is None:
        return cameras[0]
    if isinstance(view, str):
        for c in cameras:
            if c.name == view or Path(c.name).stem == view:
                return c
        if view.lstrip("-").isdigit():
            view = int(view)
        else:
            names = ", ".join(c.name for c in cameras[:8]) + (", ..." if len(cameras) > 8 else "")
            raise CameraError(f"no camera named {view!r}; choose one of: {names} (or an index 0..{len(cameras) - 1})")
    if not -len(cameras) <= int(view) < len(cameras):
        raise CameraError(f"view {view} out of range; the file has {len(cameras)} cameras (0..{len(cameras) - 1})")
    return cameras[int(view)]


def save_camera_json(path: str | os.PathLike, camera: Camera, *, own_only: bool = True) -> None:
    """Write ``camera`` as a pdtool camera.json (version 1) atomically (temp file + rename),
    marked as pdtool's ("written_by"). By default it replaces only a camera file that
    pdtool wrote: `render --write-camera DIR` names a folder, not this file, and a
    camera.json already there may be the user's own. Raises OutputError."""

    with atomic_output(Path(path), own_only=own_only, what="pdtool's camera") as tmp:
        tmp.write_text(json.dumps({"written_by": WRITTEN_BY, **camera.to_dict()}, indent=2) + "\n", encoding="utf-8")


def look_at(eye: Iterable[float], target: Iterable[float], up: Iterable[float]) -> np.ndarray:
    """[4, 4] world_to_camera (OpenCV) of a camera at eye looking at target, with world
    ``up`` pointing up in the image."""
    eye = np.asarray(eye, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)  # right = forward x up; then y = z x x points down (OpenCV)
    if np.linalg.norm(x) < 1e-9:
        raise CameraError("look_at: view direction is parallel to the up axis; choose another up axis")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    rot = np.stack([x, y, z])  # rows: camera axes in world
    w2c = np.eye(4)
    w2c[:3, :3] = rot
    w2c[:3, 3] = -rot @ eye
    return w2c


_UP = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
       "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0), "-z": (0.0, 0.0, -1.0)}
_UP.update({"+" + k: v for k, v in list(_UP.items()) if not k.startswith("-")})


def auto_camera(
    positions: np.ndarray,
    width: int = 512,
    height: int = 512,
    up_axis: str = "z",
    *,
    fov_y_deg: float = 40.0,
    azimuth_deg: float = 45.0,
    elevation_deg: float = 25.0,
    margin: float = 1.15,
) -> Camera:
    """A camera framing the object from a 3/4 view (azimuth 45 deg, 25 deg above).

    positions: [N, 3] Gaussian centres in world units. The bounds are the 1st-99th
    percentiles per axis so that a few stray floaters do not shrink the object; the camera
    sits where the bounding sphere of that box fits the smaller field of view with
    ``margin``. up_axis: world axis shown upward: "x", "y", "z" (or "+z" ...) or negated
    ("-y" for COLMAP-style scenes whose y points down).
    """
    pts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if len(pts) == 0:
        raise CameraError("auto_camera: no finite positions to frame; the scene is empty")
    if up_axis not in _UP:
        raise CameraError(f"auto_camera: unknown up axis {up_axis!r}; use one of {', '.join(_UP)}")
    lo = np.percentile(pts, 1, axis=0)
    hi = np.percentile(pts, 99, axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    up = np.asarray(_UP[up_axis])
    # Two horizontal axes perpendicular to up, in a fixed right-handed order.
    h1 = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(up, h1)
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    direction = math.cos(el) * (math.cos(az) * h1 + math.sin(az) * h2) + math.sin(el) * up
    fy = 0.5 * height / math.tan(0.5 * math.radians(fov_y_deg))
    fx = fy
    half_fov = math.atan(0.5 * min(width, height) / fy)
    # Start where the bounding sphere surely fits, then move closer until the points seen
    # from this side (those inside the 1-99th percentile box) fill 1/margin of the frame:
    # the sphere of a flat or long object wastes most of the picture.
    dist = margin * radius / math.sin(half_fov)
    inner = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    if len(inner) == 0:
        inner = pts
    safe = dist  # the smallest distance measured to fit
    for _ in range(6):
        cam = Camera(int(width), int(height), fx, fy, width / 2.0, height / 2.0,
                     look_at(centre + dist * direction, centre, up), name="auto")
        uvz = cam.project(inner)
        if np.any(uvz[:, 2] <= 0.05 * dist):
            break  # points too close to the camera: keep the last safe distance
        ext = max(np.abs(uvz[:, 0] - cam.cx).max() / (0.5 * width),
                  np.abs(uvz[:, 1] - cam.cy).max() / (0.5 * height))
        if ext * margin <= 1.0 + 1e-6:
            safe = min(safe, dist)
        # Image extent scales about like 1 / distance for a far camera; iterate for near ones.
        new = dist * ext * margin
        if ext <= 0 or abs(new - dist) < 0.005 * dist:
            break
        dist = new
    dist = safe
    eye = centre + dist * direction
    w2c = look_at(eye, centre, up)
    return Camera(int(width), int(height), fx, fy, width / 2.0, height / 2.0, w2c, name="auto")
