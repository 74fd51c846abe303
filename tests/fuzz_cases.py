"""Fuzz every pdtool loader with generated malformed inputs.

Each *target* turns a random source into one input on disk (a mutated copy of a valid
file or folder) and loads it with the real loader. The property checked for every input:

* it loads, and the loaded object is sane (finite arrays, consistent shapes, values in
  the ranges the rest of pdtool assumes), or
* it raises a ``pd_tool.core.errors.PdToolError`` subclass whose message is one non-empty line.

Anything else (another exception type, a multi-line or empty message, an insane object,
a Python warning, a hang) is a *bug*. Targets (loaders):

    ply       pd_tool.io.load_splats on .ply: binary LE / BE and ASCII
    splat     pd_tool.io.load_splats on .splat
    cameras   pd_tool.core.cameras.load_cameras: INRIA cameras.json, NeRF transforms.json,
              pdtool camera.json (single, list, {"cameras": [...]}), and folders of them
    video     pd_tool.video.folder.load_reference_video: frames, masks/, camera.json, .mp4
    material  pd_tool.materials.file.MaterialFile.load (.pdmat)
    record    pd_tool.materials.file.read_record (.pdtool/last-fit.json)
    preset    pd_tool.materials.presets.load_preset (user TOML for materials / quality / forces)

Mutations: bit flips, byte overwrites, truncation, insertion, deletion, duplication;
header edits (element counts incl. huge/negative, formats, property types, dropped /
renamed / duplicated properties, huge PNG sizes, huge .npy shapes); NaN / inf / huge
value injection; JSON / TOML tree edits (deleted keys, wrong types, NaN, inf, huge ints,
deep nesting, wrong shapes); folder edits (missing / extra / resized frames, masks, mp4).

The same generators drive the CI tests (tests/integration/test_fuzz_*.py, through hypothesis's
``st.randoms()``) and this full run:

    python tests/fuzz_cases.py --n 12000 --seed 0 --json fuzz.json [--cli 300] [--device cpu]

--n is the total number of inputs, split over the targets by WEIGHTS. Exit code 1 when
any bug was found; --save-failures DIR keeps each failing input for replay.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import io
import json
import math
import os
import random
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pd_tool.core.errors import PdToolError  # noqa: E402

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# Warnings Python's default filters hide from users (imageio's ffmpeg reader leaves a pipe to
# the garbage collector, for example); every other warning is a bug: the CLI would print it.
QUIET_WARNINGS = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)
PER_INPUT_TIMEOUT_S = 20.0  # a loader that takes longer on a tiny input counts as a hang


# ============================================================================ outcomes
@dataclass
class Outcome:
    """What one input did: kind is 'ok' (loaded and sane), 'error' (one-line PdToolError)
    or 'bug' (anything else); detail is the error line or the bug's description."""

    kind: str
    detail: str = ""
    signature: str = ""  # bugs only: a short key that groups identical bugs


class _Hang(BaseException):
    """Raised by the alarm when a loader runs past PER_INPUT_TIMEOUT_S (BaseException so that
    a loader's `except Exception` cannot swallow it)."""


def _where(tb: traceback.StackSummary) -> str:
    """The innermost pdtool frame of a traceback, as 'file:line' (the bug's location)."""
    for fr in reversed(tb):
        if "pd_tool" in fr.filename or "usd_export" in fr.filename:
            return f"{Path(fr.filename).name}:{fr.lineno}"
    return f"{Path(tb[-1].filename).name}:{tb[-1].lineno}" if tb else "?"


def run_checked(load: Callable[[], Any], sanity: Callable[[Any], list[str]],
                timeout_s: float = PER_INPUT_TIMEOUT_S) -> Outcome:
    """Run one loader call and classify it (see the module docstring)."""
    import threading

    # signals can only be set from the main thread (pytest-xdist workers and plain pytest run there)
    use_alarm = (timeout_s > 0 and hasattr(signal, "setitimer") and os.name == "posix"
                 and threading.current_thread() is threading.main_thread())

    def on_alarm(signum, frame):  # noqa: ARG001
        raise _Hang()

    def loud_warning() -> Outcome | None:
        loud = [w for w in caught if not issubclass(w.category, QUIET_WARNINGS)]
        if not loud:
            return None
        w = loud[0]
        return Outcome("bug", f"warning {w.category.__name__}: {w.message} ({Path(w.filename).name}:{w.lineno})",
                       f"warning {w.category.__name__} {Path(w.filename).name}:{w.lineno}")

    caught: list[warnings.WarningMessage] = []
    old = signal.signal(signal.SIGALRM, on_alarm) if use_alarm else None
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if use_alarm:
                signal.setitimer(signal.ITIMER_REAL, timeout_s)
            try:
                obj = load()
            finally:
                if use_alarm:
                    signal.setitimer(signal.ITIMER_REAL, 0)
            problems = sanity(obj)
    except _Hang:
        return Outcome("bug", f"no answer within {timeout_s:g} s", "hang")
    except PdToolError as e:
        msg = str(e)
        if not msg.strip():
            return Outcome("bug", f"{type(e).__name__} with an empty message", f"empty-message {type(e).__name__}")
        if "\n" in msg or "\r" in msg:
            tb = traceback.extract_tb(e.__traceback__)
            return Outcome("bug", f"{type(e).__name__} message spans lines: {msg[:300]!r}",
                           f"multi-line {type(e).__name__} {_where(tb)}")
        # a warning printed before the error line breaks the one-line promise too
        return loud_warning() or Outcome("error", msg)
    except BaseException as e:  # noqa: BLE001 - the point is to catch everything else
        if isinstance(e, KeyboardInterrupt):
            raise
        tb = traceback.extract_tb(e.__traceback__)
        first = (str(e).splitlines() or [""])[0][:200]
        return Outcome("bug", f"{type(e).__name__}: {first}\n{''.join(traceback.format_tb(e.__traceback__)[-4:])}",
                       f"{type(e).__name__} {_where(tb)}")
    finally:
        if use_alarm:
            signal.signal(signal.SIGALRM, old)
    if problems:
        return Outcome("bug", "loaded but insane: " + "; ".join(problems), "insane: " + problems[0].split(":")[0])
    return loud_warning() or Outcome("ok")


# ============================================================================ byte mutations
NASTY_BYTES = [b"\x00", b"\xff", b"\n", b"\r\n", b" ", b"-", b"nan", b"inf", b"1e999", b"\xc3\x28", b"\xef\xbb\xbf",
               b"{", b"}", b"[", b"]", b'"', b"=", b"#", b"\\", b"\x7f"]


def mutate_bytes(rng: random.Random, data: bytes, n_ops: int | None = None) -> bytes:
    """Generic byte-level mutations: bit flips, overwrites, truncation, insertion, deletion,
    duplication, nasty tokens, zeroed spans."""
    b = bytearray(data)
    for _ in range(n_ops or rng.choice([1, 1, 1, 2, 3, 8])):
        op = rng.randrange(9)
        n = len(b)
        if op == 0 and n:  # flip bits
            for _ in range(rng.choice([1, 1, 2, 4, 16])):
                i = rng.randrange(n)
                b[i] ^= 1 << rng.randrange(8)
        elif op == 1 and n:  # overwrite bytes with random ones
            i = rng.randrange(n)
            for j in range(i, min(n, i + rng.choice([1, 2, 4, 8, 32]))):
                b[j] = rng.randrange(256)
        elif op == 2:  # truncate
            del b[rng.randrange(n + 1) if n else 0:]
        elif op == 3:  # insert random bytes
            i = rng.randrange(n + 1)
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.choice([1, 3, 17, 100])))
        elif op == 4 and n:  # delete a span
            i = rng.randrange(n)
            del b[i:i + rng.choice([1, 2, 7, 64, 1000])]
        elif op == 5 and n:  # duplicate a span
            i = rng.randrange(n)
            span = b[i:i + rng.choice([1, 8, 64, 512])]
            j = rng.randrange(n + 1)
            b[j:j] = span
        elif op == 6:  # nasty token
            i = rng.randrange(n + 1)
            b[i:i] = rng.choice(NASTY_BYTES)
        elif op == 7 and n:  # zero a span
            i = rng.randrange(n)
            for j in range(i, min(n, i + rng.choice([1, 4, 32, 256]))):
                b[j] = 0
        elif op == 8:  # append garbage
            b += bytes(rng.randrange(256) for _ in range(rng.choice([1, 5, 40])))
    return bytes(b)


# ============================================================================ value pools
HUGE_INTS = [2 ** 31, 2 ** 32 + 1, 2 ** 63 - 1, 2 ** 64, 10 ** 30, -(2 ** 63), 10 ** 400]
JSON_NASTY: list[Any] = [None, True, False, 0, -1, 1, 2, 0.5, -0.0, 1e-320, 1e6, 1e308, -1e308,
                         float("inf"), float("-inf"), float("nan"), 2 ** 64, -(2 ** 63), 10 ** 400,
                         "", "abc", "12", "NaN", "\x00", "\u202e", [], [1, 2, 3], [[1, 2], [3, 4]],
                         [[0.0] * 4] * 4, {}, {"a": 1}, [None], [float("nan")] * 3]


def nasty_number(rng: random.Random) -> Any:
    return rng.choice([0, -1, 1, 0.0, -0.0, 1e-320, 1e-45, 1e38, 3.5e38, 1e300, 1e308, -1e308,
                       float("inf"), float("-inf"), float("nan"), 2 ** 63, -(2 ** 63), 10 ** 30, 709.0, 710.0,
                       88.8, 89.0, -1e30, 1e30, rng.uniform(-1e6, 1e6)])


def deep_json(depth: int) -> str:
    return "[" * depth + "]" * depth


def _tree_paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += _tree_paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out += _tree_paths(v, prefix + (i,))
    return out


def _get(obj: Any, path: tuple) -> Any:
    for k in path:
        obj = obj[k]
    return obj


def mutate_tree(rng: random.Random, obj: Any, pool: list[Any], n_ops: int | None = None,
                number: Callable[[random.Random], Any] = nasty_number) -> Any:
    """Structural edits of a JSON/TOML-like tree: delete keys, wrong types, nasty numbers,
    perturbed numbers (non-rigid matrices, negative sizes), wrapped values, renamed keys."""
    obj = json.loads(json.dumps(obj))  # deep copy (the trees hold JSON values only)
    for _ in range(n_ops or rng.choice([1, 1, 2, 3])):
        paths = _tree_paths(obj)
        path = rng.choice(paths)
        if not path:
            if rng.random() < 0.1:
                obj = rng.choice(pool)
            continue
        parent, key = _get(obj, path[:-1]), path[-1]
        val = parent[key]
        op = rng.randrange(7)
        if op == 0:  # delete
            del parent[key]
        elif op == 1:  # a copy: the same pool list inserted into itself would make a cycle
            parent[key] = copy.deepcopy(rng.choice(pool))
        elif op == 2:
            parent[key] = number(rng)
        elif op == 3 and isinstance(val, (int, float)) and not isinstance(val, bool):
            parent[key] = rng.choice([-val, val * rng.choice([1.5, 0.0, 1e-9, 1e9, 3]), val + rng.uniform(-2, 2),
                                      int(val) if math.isfinite(val) else val, float(val)])
        elif op == 4:
            parent[key] = [val] if rng.random() < 0.5 else {"value": val}
        elif op == 5 and isinstance(parent, dict):
            parent[rng.choice(["x", key.upper() if isinstance(key, str) else "k", "", " " + str(key)])] = parent.pop(key)
        elif op == 6 and isinstance(parent, list):
            parent.insert(key, copy.deepcopy(val if rng.random() < 0.5 else rng.choice(pool)))
    return obj


def json_text(rng: random.Random, obj: Any) -> bytes:
    """Serialise with Python's json (NaN / Infinity literals allowed), sometimes mangled."""
    text = json.dumps(obj, indent=rng.choice([None, 2]))
    r = rng.random()
    if r < 0.15:
        return mutate_bytes(rng, text.encode())
    if r < 0.18:
        return b"\xef\xbb\xbf" + text.encode()  # UTF-8 BOM
    if r < 0.20:
        return text.encode("utf-16")
    return text.encode()


# ============================================================================ sanity checks
def _finite(name: str, a: Any) -> list[str]:
    import torch

    if isinstance(a, torch.Tensor):
        ok = bool(torch.isfinite(a).all()) if a.is_floating_point() else True
    else:
        a = np.asarray(a)
        ok = bool(np.isfinite(a).all()) if np.issubdtype(a.dtype, np.number) else False
    return [] if ok else [f"{name}: not finite (or not numeric)"]


def sane_scene(scene: Any) -> list[str]:
    """GaussianScene: N >= 1; positions [N,3], quats [N,4] unit, scales [N,3] >= 0,
    opacities [N] in 0-1, sh [N,K,3] with K in 1,4,9,16; all finite float32."""
    import torch

    from pd_tool.core.scene import GaussianScene

    if not isinstance(scene, GaussianScene):
        return [f"type: {type(scene).__name__} is not a GaussianScene"]
    p: list[str] = []
    n = scene.positions.shape[0]
    if n < 1:
        p.append("count: 0 Gaussians")
    shapes = {"positions": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
    for name, shape in shapes.items():
        t = getattr(scene, name)
        if tuple(t.shape) != shape:
            p.append(f"{name}: shape {tuple(t.shape)} != {shape}")
        if t.dtype != torch.float32:
            p.append(f"{name}: dtype {t.dtype}")
        p += _finite(name, t)
    if scene.sh.ndim != 3 or scene.sh.shape[0] != n or scene.sh.shape[2] != 3 or scene.sh.shape[1] not in (1, 4, 9, 16):
        p.append(f"sh: shape {tuple(scene.sh.shape)}")
    p += _finite("sh", scene.sh)
    if not p:
        norms = scene.quats.double().norm(dim=1)
        if not bool(((norms - 1).abs() < 1e-3).all()):
            p.append("quats: not unit")
        if bool((scene.scales < 0).any()):
            p.append("scales: negative")
        if bool(((scene.opacities < 0) | (scene.opacities > 1)).any()):
            p.append("opacities: outside 0-1")
    return p


def sane_camera(cam: Any, where: str = "camera") -> list[str]:
    """Camera: positive integer size, positive finite focal lengths, finite principal point,
    rigid finite world_to_camera with last row 0 0 0 1, fps None or positive finite."""
    from pd_tool.core.cameras import Camera

    if not isinstance(cam, Camera):
        return [f"{where}: {type(cam).__name__} is not a Camera"]
    p: list[str] = []
    if not (isinstance(cam.width, int) and isinstance(cam.height, int) and cam.width > 0 and cam.height > 0):
        p.append(f"{where} size: {cam.width}x{cam.height}")
    for k in ("fx", "fy"):
        v = getattr(cam, k)
        if not (math.isfinite(v) and v > 0):
            p.append(f"{where} {k}: {v} is not a positive finite focal length")
    for k in ("cx", "cy"):
        if not math.isfinite(getattr(cam, k)):
            p.append(f"{where} {k}: not finite")
    m = cam.world_to_camera
    if m.shape != (4, 4) or not np.isfinite(m).all():
        p.append(f"{where} world_to_camera: not a finite 4x4")
    else:
        r = m[:3, :3]
        if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0 or np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
            p.append(f"{where} world_to_camera: not rigid")
        if not np.isfinite(cam.center).all():
            p.append(f"{where} center: not finite")
    if cam.fps is not None and not (math.isfinite(cam.fps) and cam.fps > 0):
        p.append(f"{where} fps: {cam.fps}")
    return p


def sane_cameras(cams: Any) -> list[str]:
    if not isinstance(cams, list) or not cams:
        return ["cameras: not a non-empty list"]
    return [q for i, c in enumerate(cams) for q in sane_camera(c, f"camera {i}")]


def sane_video(v: Any) -> list[str]:
    """ReferenceVideo: frames [T>=3,H,W,3] float32 in 0-1, masks None or [T,H,W] in 0-1,
    camera sane and of size W x H, fps positive finite."""
    import torch

    from pd_tool.video.folder import MIN_FRAMES, ReferenceVideo

    if not isinstance(v, ReferenceVideo):
        return [f"type: {type(v).__name__} is not a ReferenceVideo"]
    p: list[str] = []
    f = v.frames
    if f.ndim != 4 or f.shape[-1] != 3 or f.shape[0] < MIN_FRAMES or f.dtype != torch.float32:
        return [f"frames: shape {tuple(f.shape)} dtype {f.dtype}"]
    p += _finite("frames", f)
    if not p and bool(((f < 0) | (f > 1)).any()):
        p.append("frames: outside 0-1")
    t, h, w = f.shape[:3]
    if v.masks is not None:
        if tuple(v.masks.shape) != (t, h, w):
            p.append(f"masks: shape {tuple(v.masks.shape)} != {(t, h, w)}")
        else:
            p += _finite("masks", v.masks)
            if bool(((v.masks < 0) | (v.masks > 1)).any()):
                p.append("masks: outside 0-1")
    p += sane_camera(v.camera)
    if not (0 < v.camera.cx < v.camera.width and 0 < v.camera.cy < v.camera.height):
        p.append(f"camera principal point: ({v.camera.cx}, {v.camera.cy}) outside the {w}x{h} frames")
    if (v.camera.width, v.camera.height) != (w, h):
        p.append(f"camera size: {v.camera.width}x{v.camera.height} but frames {w}x{h}")
    if not (math.isfinite(v.fps) and v.fps > 0):
        p.append(f"fps: {v.fps}")
    return p


def sane_material(m: Any) -> list[str]:
    """MaterialFile: E [Q>=1] finite > 0 float, v0 / rest [Q,3] finite; the header values
    a bake reads (nu, density, damping, scene_path, scene_sha256, prepare) are present and
    valid; field arrays are finite real numbers."""
    from pd_tool.materials.file import MaterialFile

    if not isinstance(m, MaterialFile):
        return [f"type: {type(m).__name__} is not a MaterialFile"]
    p: list[str] = []
    E, v0, rest = (np.asarray(a) for a in (m.driver_E, m.driver_v0, m.driver_rest))
    for name, a in (("driver_E", E), ("driver_v0", v0), ("driver_rest", rest)):
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            p.append(f"{name}: dtype {a.dtype} is not real")
    if p:
        return p
    q = E.shape[0] if E.ndim == 1 else -1
    if q < 1 or v0.shape != (q, 3) or rest.shape != (q, 3):
        return [f"shapes: E {E.shape} v0 {v0.shape} rest {rest.shape}"]
    for name, a in (("driver_E", E), ("driver_v0", v0), ("driver_rest", rest)):
        p += _finite(name, a)
    if not p and not (E > 0).all():
        p.append("driver_E: not positive")
    if not isinstance(m.meta, dict):
        return p + ["meta: not a dict"]
    # what a bake reads: valid values, or a one-line PdToolError when the header lacks them
    for key, ok in (("nu", lambda v: 0 <= v < 0.5), ("density", lambda v: v > 0), ("damping", lambda v: v >= 0)):
        try:
            v = getattr(m, key)
        except PdToolError as e:
            if "\n" in str(e):
                p.append(f"{key}: multi-line error")
            continue
        except Exception as e:  # noqa: BLE001 - a header a bake cannot read is the finding
            p.append(f"meta: {key} unreadable ({type(e).__name__})")
            continue
        if not (isinstance(v, float) and math.isfinite(v) and ok(v)):
            p.append(f"{key}: {v!r}")
    for key, typ in (("scene_path", str), ("scene_sha256", str), ("prepare", dict)):
        if key in m.meta and not isinstance(m.meta[key], typ):
            p.append(f"meta: '{key}' is not a {typ.__name__}")
    for fname, params in m.fields.items():
        for pname, a in params.items():
            a = np.asarray(a)
            if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
                p.append(f"field.{fname}.{pname}: dtype {a.dtype}")
            else:
                p += _finite(f"field.{fname}.{pname}", a)
    return p


def sane_record(r: Any) -> list[str]:
    if r is None:
        return []
    if not (isinstance(r, tuple) and len(r) == 2 and all(isinstance(x, Path) for x in r)):
        return [f"record: {r!r} is not (Path, Path)"]
    return [f"record: {x} is not a file" for x in r if not x.is_file()]


def sane_preset(kind: str) -> Callable[[Any], list[str]]:
    def check(d: Any) -> list[str]:
        from pd_tool.materials.presets import _RANGES, _REQUIRED

        if not isinstance(d, dict):
            return [f"preset: {type(d).__name__} is not a dict"]
        p = []
        for key, typ in _REQUIRED[kind].items():
            v = d.get(key)
            if typ is str:
                if not isinstance(v, str) or (key == "at" and v not in ("top", "all")):
                    p.append(f"preset {key}: {v!r} is not a known string")
                continue
            if not isinstance(v, typ) or isinstance(v, bool):
                p.append(f"preset {key}: {v!r} is not a {typ.__name__}")
                continue
            lo, hi = _RANGES.get(key, (-math.inf, math.inf))
            if not (math.isfinite(v) and lo <= v <= hi):
                p.append(f"preset {key}: {v!r} out of range")
        if "damping" in d and not (isinstance(d["damping"], float) and math.isfinite(d["damping"]) and d["damping"] >= 0):
            p.append(f"preset damping: {d['damping']!r}")
        return p
    return check


# ============================================================================ targets
@dataclass
class Case:
    """One generated input: `load()` runs the loader on it; `sanity(obj)` lists problems;
    `path` is the file or folder (for the CLI and for --save-failures); `note` says how
    it was made."""

    load: Callable[[], Any]
    sanity: Callable[[Any], list[str]]
    path: Path
    note: str


# ---------------------------------------------------------------------------- splats
PLY_TYPES = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8", "int16",
             "uint16", "int32", "uint32", "float32", "float64", "float16", "foo", "list uchar float",
             "list uint int", "list char double"]


def _ply_records(rng: random.Random, n: int, degree: int, *, normals: bool, extra: bool,
                 dtype: str = "<f4") -> np.ndarray:
    from pd_tool.core.scene import REQUIRED_PLY_PROPERTIES

    k = (degree + 1) ** 2
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert set(REQUIRED_PLY_PROPERTIES) <= set(names)
    fields = [(nm, dtype) for nm in names]
    if extra:
        fields.append(("region", "<i4"))
    rec = np.zeros(n, dtype=fields)
    g = np.random.default_rng(rng.randrange(2 ** 32))
    for nm in names:
        rec[nm] = g.normal(size=n)
    for i in range(3):
        rec[f"scale_{i}"] = g.uniform(-6, -1, size=n)
    if extra:
        rec["region"] = g.integers(0, 3, size=n)
    return rec


_REAL_PLY: list[np.ndarray] = []


def _real_ply_records() -> np.ndarray | None:
    """The first 8 Gaussians of the real udon capture (SH3), when the shared data is here."""
    if not _REAL_PLY:
        src = SHARED_DATA / "udon.ply"
        if not src.is_file():
            return None
        from plyfile import PlyData

        _REAL_PLY.append(np.array(PlyData.read(str(src))["vertex"].data[:8]))
    return _REAL_PLY[0].copy()


def _ply_bytes(rec: np.ndarray, fmt: str) -> bytes:
    from plyfile import PlyData, PlyElement

    text = fmt == "ascii"
    order = {"ascii": "=", "le": "<", "be": ">"}[fmt]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(rec, "vertex")], text=text, byte_order=order).write(buf)
    return buf.getvalue()


def _split_header(data: bytes) -> tuple[list[bytes], bytes]:
    i = data.find(b"end_header\n")
    if i < 0:
        return data.split(b"\n"), b""
    return data[:i].split(b"\n")[:-1] + [b"end_header"], data[i + len(b"end_header\n"):]


def _header_edit(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    lines, body = _split_header(data)
    props = [i for i, ln in enumerate(lines) if ln.startswith(b"property ")]
    elem = next((i for i, ln in enumerate(lines) if ln.startswith(b"element vertex")), None)
    op = rng.randrange(10)
    note = ""
    if op == 0 and elem is not None:
        cur = int(lines[elem].split()[-1])
        cnt = rng.choice([0, -1, cur - 1, cur + 1, cur * 2, *HUGE_INTS, "abc", "1.5", "", "0x10"])
        lines[elem] = b"element vertex " + str(cnt).encode()
        note = f"vertex count {cnt}"
    elif op == 1:
        fmt = rng.choice(["ascii", "binary_little_endian", "binary_big_endian", "binary", "foo", ""])
        ver = rng.choice(["1.0", "2.0", "", "x"])
        lines[1] = f"format {fmt} {ver}".encode()
        note = f"format {fmt} {ver}"
    elif op == 2 and props:
        i = rng.choice(props)
        name = lines[i].split()[-1]
        typ = rng.choice(PLY_TYPES)
        lines[i] = f"property {typ} ".encode() + name
        note = f"property {name.decode()} as {typ}"
    elif op == 3 and props:
        i = rng.choice(props)
        note = f"dropped {lines[i].decode()}"
        del lines[i]
    elif op == 4 and props:
        i = rng.choice(props)
        lines.insert(i, lines[i])
        note = f"duplicated {lines[i].decode()}"
    elif op == 5 and props:
        i = rng.choice(props)
        new = rng.choice([b"q", b"x", b"f_rest_99", b"opacity", b"", b"a b", "\u00e9".encode()])
        lines[i] = b" ".join(lines[i].split()[:-1] + [new])
        note = f"renamed property to {new!r}"
    elif op == 6:
        extra = rng.choice([b"element face 1", b"element face 0", b"element vertex 2", b"comment x" * 50,
                            b"obj_info", b"element  vertex 1", b"property float w"])
        lines.insert(rng.randrange(2, len(lines) + 1), extra)
        note = f"inserted {extra[:20]!r}"
    elif op == 7:
        lines = [ln for ln in lines if ln != b"end_header"]
        note = "no end_header"
    elif op == 8:
        return (b"\r\n".join(lines) + b"\r\n" + body), "CRLF header"
    elif op == 9 and props:
        i, j = rng.choice(props), rng.choice(props)
        lines[i], lines[j] = lines[j], lines[i]
        note = "swapped properties"
    return b"\n".join(lines) + b"\n" + body, note or "header untouched"


def _ascii_token_edit(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    head_end = data.find(b"end_header\n")
    if head_end < 0:
        return data, "no header"
    head, body = data[:head_end + 11], data[head_end + 11:]
    rows = body.split(b"\n")
    r = rng.randrange(len(rows))
    toks = rows[r].split(b" ")
    op = rng.randrange(4)
    tok = rng.choice([b"nan", b"inf", b"-inf", b"1e999", b"abc", b"", b"1,5", b"0x1f", b"--1", b"1e38", b"3.5e38",
                      b"1e-50", b"99999999999999999999"])
    if op == 0 and toks:
        toks[rng.randrange(len(toks))] = tok
    elif op == 1 and toks:
        del toks[rng.randrange(len(toks))]
    elif op == 2:
        toks.insert(rng.randrange(len(toks) + 1), tok)
    else:
        del rows[r]
        return head + b"\n".join(rows), f"deleted row {r}"
    rows[r] = b" ".join(toks)
    return head + b"\n".join(rows), f"row {r} token edit {tok!r}"


def _set(rec: np.ndarray, name: str, i: int, v: Any) -> None:
    """rec[name][i] = v, clipped into integer fields (the point is the file, not numpy)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            rec[name][i] = v
        except (OverflowError, ValueError):
            info = np.iinfo(rec.dtype[name]) if np.issubdtype(rec.dtype[name], np.integer) else None
            rec[name][i] = (info.max if v > 0 else info.min) if info is not None and v == v else 0


def _inject_values(rng: random.Random, rec: np.ndarray) -> str:
    names = list(rec.dtype.names)
    op = rng.randrange(5)
    i = rng.randrange(len(rec))
    if op == 0:
        nm = rng.choice(names)
        v = nasty_number(rng)
        _set(rec, nm, i, v)
        return f"{nm}[{i}] = {v!r}"
    if op == 1 and "rot_0" in names:
        v = rng.choice([0.0, 0.0, 1e-30, 1e30, 1e200])
        for c in range(4):
            _set(rec, f"rot_{c}", i, v)
        return f"rot[{i}] = {v}"
    if op == 2:
        v = rng.choice([88.8, 89.0, 100.0, 709.0, 710.0, -100.0, -1000.0, 1e30])
        for c in range(3):
            if f"scale_{c}" in names:
                _set(rec, f"scale_{c}", i, v)
        return f"log scale[{i}] = {v}"
    if op == 3 and "opacity" in names:
        v = rng.choice([1e30, -1e30, 1e4, -1e4, 89.0, -89.0, -746.0, 746.0])
        _set(rec, "opacity", i, v)
        return f"opacity logit[{i}] = {v}"
    v = rng.choice([1e38, -1e38, 3.4e38, 1e-40, 1e300])
    for c in "xyz":
        if c in names:
            _set(rec, c, i, v)
    return f"position[{i}] = {v}"


def make_ply(rng: random.Random, work: Path, device: str = "cpu") -> Case:
    from pd_tool.io import load_splats

    fmt = rng.choice(["le", "le", "be", "ascii"])
    real = _real_ply_records() if rng.random() < 0.2 else None
    if real is not None:
        rec, note = real, "udon[:8]"
    else:
        n = rng.choice([1, 1, 2, 3, 5, 8])
        deg = rng.choice([0, 0, 1, 2, 3])
        dtype = rng.choice(["<f4", "<f4", "<f4", "<f8", "<i4", "u1"])
        rec = _ply_records(rng, n, deg, normals=rng.random() < 0.5, extra=rng.random() < 0.2, dtype=dtype)
        note = f"n={n} deg={deg} {dtype}"
    kind = rng.randrange(8)
    if kind == 0:  # structural: drop / rename / add properties, then a valid PLY with that layout
        names = list(rec.dtype.names)
        op = rng.randrange(4)
        if op == 0:
            drop = rng.choice(names)
            rec = rec[[nm for nm in names if nm != drop]]
            rec = np.array(rec.tolist(), dtype=[(nm, rec.dtype[nm]) for nm in rec.dtype.names]) if len(rec.dtype.names) else rec
            note += f" without {drop}"
        elif op == 1:  # wrong f_rest count / gap
            k = rng.choice([1, 5, 8, 10, 44, 46, 100])
            fields = [(nm, "<f4") for nm in names if not nm.startswith("f_rest_")] + [(f"f_rest_{i}", "<f4") for i in range(k)]
            if rng.random() < 0.5 and k > 2:
                fields = [f for f in fields if f[0] != "f_rest_1"] + [("f_rest_999", "<f4")]
            new = np.zeros(len(rec), dtype=fields)
            for nm in new.dtype.names:
                if nm in names:
                    new[nm] = rec[nm]
            rec = new
            note += f" f_rest x{k}"
        elif op == 2:
            rec = rec[:0]
            note += " empty"
        else:
            fields = [(nm, rec.dtype[nm]) for nm in names] + [(rng.choice(["w", "nx", "region2", "label"]), rng.choice(["<f8", "u1", "<i2"]))]
            try:
                new = np.zeros(len(rec), dtype=fields)
            except ValueError:  # duplicate name
                new = rec
            else:
                for nm in names:
                    new[nm] = rec[nm]
            rec = new
            note += " extra property"
        data = _ply_bytes(rec, fmt)
    elif kind == 1:
        note += " " + _inject_values(rng, rec)
        data = _ply_bytes(rec, fmt)
    elif kind in (2, 3):
        data, how = _header_edit(rng, _ply_bytes(rec, fmt))
        note += " " + how
    elif kind == 4 and fmt == "ascii":
        data, how = _ascii_token_edit(rng, _ply_bytes(rec, fmt))
        note += " " + how
    elif kind == 5:  # header + value edits together
        note += " " + _inject_values(rng, rec)
        data, how = _header_edit(rng, _ply_bytes(rec, fmt))
        note += " " + how
    else:
        data = mutate_bytes(rng, _ply_bytes(rec, fmt))
        note += " bytes"
    path = work / rng.choice(["scene.ply", "scene.PLY", "s p.ply"])
    path.write_bytes(data)
    return Case(lambda: load_splats(path, device=device), sane_scene, path, f"ply {fmt} {note}")


def make_splat(rng: random.Random, work: Path, device: str = "cpu") -> Case:
    from pd_tool.io import load_splats
    from pd_tool.io.splat import SPLAT_DTYPE

    n = rng.choice([1, 2, 3, 8])
    g = np.random.default_rng(rng.randrange(2 ** 32))
    rec = np.zeros(n, SPLAT_DTYPE)
    rec["position"] = g.normal(size=(n, 3))
    rec["scale"] = g.uniform(0.001, 0.1, size=(n, 3))
    rec["rgba"] = g.integers(0, 256, size=(n, 4))
    rec["rot"] = g.integers(0, 256, size=(n, 4))
    rec["rot"][:, 0] = 255
    op = rng.randrange(5)
    i = rng.randrange(n)
    note = f"n={n}"
    if op == 0:
        field_ = rng.choice(["position", "scale"])
        v = nasty_number(rng)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                rec[field_][i, rng.randrange(3)] = v
            except (OverflowError, ValueError):
                rec[field_][i, 0] = -1
        note += f" {field_}[{i}] = {v!r}"
        data = rec.tobytes()
    elif op == 1:
        rec["rot"][i] = rng.choice([[128, 128, 128, 128], [127, 128, 129, 128], [0, 0, 0, 0]])
        note += " rot ~ 0"
        data = rec.tobytes()
    else:
        data = mutate_bytes(rng, rec.tobytes())
        note += " bytes"
    path = work / rng.choice(["scene.splat", "scene.SPLAT"])
    path.write_bytes(data)
    return Case(lambda: load_splats(path, device=device), sane_scene, path, f"splat {note}")


# ---------------------------------------------------------------------------- cameras
def _rot(rng: random.Random) -> list[list[float]]:
    q = np.random.default_rng(rng.randrange(2 ** 32)).normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]]


def _pdtool_cam(rng: random.Random) -> dict:
    w, h = rng.choice([(512, 512), (64, 48), (16, 16), (1, 1), (1920, 1080)])
    d: dict[str, Any] = {"version": 1, "width": w, "height": h, "fx": rng.uniform(10, 1000)}
    if rng.random() < 0.5:
        d.update(fy=rng.uniform(10, 1000), cx=w / 2, cy=h / 2)
    r, t = np.array(_rot(rng)), np.random.default_rng(rng.randrange(2 ** 32)).normal(size=3)
    if rng.random() < 0.6:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, t
        d["world_to_camera"] = m.tolist()
    else:
        d["position"], d["rotation"] = t.tolist(), r.tolist()
    if rng.random() < 0.5:
        d["fps"] = rng.choice([24.0, 30, 60.0])
    if rng.random() < 0.5:
        d["name"] = "view0"
    return d


def camera_tree(rng: random.Random) -> tuple[Any, str]:
    """A valid camera file's JSON tree and the file name it would have."""
    kind = rng.randrange(5)
    if kind == 0:  # INRIA
        cams = [{"id": i, "img_name": f"{i:05d}", "width": 64, "height": 48, "position": np.random.default_rng(i).normal(size=3).tolist(),
                 "rotation": _rot(rng), "fx": 50.0, "fy": 51.0} for i in range(rng.choice([1, 2, 3]))]
        return cams, "cameras.json"
    if kind == 1:  # NeRF
        d: dict[str, Any] = {"w": 64, "h": 48}
        if rng.random() < 0.5:
            d["camera_angle_x"] = 0.7
        else:
            d.update(fl_x=60.0, fl_y=60.0, cx=32.0, cy=24.0)
        frames = []
        for i in range(rng.choice([1, 2])):
            m = np.eye(4)
            m[:3, :3] = _rot(rng)
            m[:3, 3] = [0, 0, 4]
            frames.append({"file_path": f"./train/r_{i}", "transform_matrix": m.tolist()})
        d["frames"] = frames
        if rng.random() < 0.3:
            d["width"], d["height"] = d.pop("w"), d.pop("h")
        return d, "transforms.json"
    if kind == 2:
        return _pdtool_cam(rng), "camera.json"
    if kind == 3:
        return [_pdtool_cam(rng) for _ in range(rng.choice([1, 2]))], "camera.json"
    return {"cameras": [_pdtool_cam(rng) for _ in range(rng.choice([1, 2]))]}, "camera.json"


def camera_bytes(rng: random.Random) -> tuple[bytes, str, str]:
    tree, name = camera_tree(rng)
    r = rng.random()
    if r < 0.03:
        return deep_json(rng.choice([100, 5000, 200000])).encode(), name, "deep nesting"
    if r < 0.12:
        return json_text(rng, tree), name, "valid"
    tree = mutate_tree(rng, tree, JSON_NASTY)
    return json_text(rng, tree), name, "tree edit"


def make_cameras(rng: random.Random, work: Path, device: str = "cpu") -> Case:  # noqa: ARG001
    from pd_tool.core.cameras import load_cameras

    data, name, note = camera_bytes(rng)
    if rng.random() < 0.1:  # a folder holding the file (or a folder named like it)
        folder = work / "cams"
        folder.mkdir()
        target = folder / name
        if rng.random() < 0.2:
            target.mkdir()
            note += ", as a folder"
        else:
            target.write_bytes(data)
        path = folder
    else:
        path = work / name
        path.write_bytes(data)
    return Case(lambda: load_cameras(path), sane_cameras, path, f"{name} {note}")


# ---------------------------------------------------------------------------- video folder
_MP4_CACHE: dict[tuple, bytes] = {}


def _mp4_bytes(w: int, h: int, t: int) -> bytes:
    key = (w, h, t)
    if key not in _MP4_CACHE:
        import imageio.v3 as iio

        g = np.random.default_rng(0)
        frames = g.integers(0, 256, size=(t, h, w, 3), dtype=np.uint8)
        with tempfile.TemporaryDirectory() as d:
            p = Path(d) / "v.mp4"
            iio.imwrite(p, frames, plugin="FFMPEG", fps=10, macro_block_size=1)
            _MP4_CACHE[key] = p.read_bytes()
    return _MP4_CACHE[key]


def _png_bytes(arr: np.ndarray, mode: str | None = None, fmt: str = "PNG") -> bytes:
    from PIL import Image

    img = Image.fromarray(arr)
    if mode is not None and mode != img.mode:
        img = img.convert(mode)
    buf = io.BytesIO()
    img.save(buf, format=fmt)
    return buf.getvalue()


def _png_with_size(data: bytes, w: int, h: int) -> bytes:
    """Rewrite a PNG's IHDR width/height (CRC fixed), leaving the pixel data as it was."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR":
        return data
    ihdr = bytearray(data[16:29])
    ihdr[0:8] = struct.pack(">II", w & 0xFFFFFFFF, h & 0xFFFFFFFF)
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + bytes(ihdr)) & 0xFFFFFFFF)
    return data[:16] + bytes(ihdr) + crc + data[33:]


IMAGE_MODES = ["RGB", "RGB", "L", "LA", "RGBA", "P", "1", "I;16"]


def make_video(rng: random.Random, work: Path, device: str = "cpu") -> Case:
    from pd_tool.video.folder import load_reference_video

    folder = work / "video"
    folder.mkdir()
    g = np.random.default_rng(rng.randrange(2 ** 32))
    w, h = rng.choice([(16, 12), (12, 16), (8, 8), (20, 10)])
    t = rng.choice([3, 3, 4, 5])
    notes = [f"{w}x{h}x{t}"]
    cam = _pdtool_cam(rng)
    cam["width"], cam["height"] = w * 4, h * 4
    cam.pop("cx", None), cam.pop("cy", None)
    use_mp4 = rng.random() < 0.08
    frames = [g.integers(0, 256, size=(h, w, 3), dtype=np.uint8) for _ in range(t)]
    ext = rng.choice([".png", ".png", ".jpg", ".PNG", ".jpeg"])
    mode = rng.choice(IMAGE_MODES) if ext.lower() == ".png" else rng.choice(["RGB", "RGB", "L", "CMYK"])
    if use_mp4:
        (folder / "clip.mp4").write_bytes(_mp4_bytes(w, h, t))
        notes.append("mp4")
    else:
        fmt = "PNG" if ext.lower() == ".png" else "JPEG"
        for i, f in enumerate(frames):
            (folder / f"frame_{i:04d}{ext}").write_bytes(_png_bytes(f, mode, fmt))
        notes.append(f"{ext} {mode}")
    masks = rng.random() < 0.4
    if masks:
        (folder / "masks").mkdir()
        mmode = rng.choice(["L", "L", "1", "RGB", "RGBA", "LA", "I;16", "P"])
        for i in range(t):
            m = (g.random((h, w)) > 0.5).astype(np.uint8) * 255
            (folder / "masks" / f"mask_{i:04d}.png").write_bytes(_png_bytes(m, mmode))
        notes.append(f"masks {mmode}")
    cam_data = json.dumps(cam).encode()
    kwargs: dict[str, Any] = {"working_size": rng.choice([None, 16, 1024, (w, h)])}
    n_ops = rng.choice([1, 1, 1, 2, 3])
    for _ in range(n_ops):
        op = rng.randrange(15)
        files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() != ".json")
        if op == 0:  # camera.json mutated
            tree = mutate_tree(rng, cam, JSON_NASTY)
            cam_data = json_text(rng, tree)
            notes.append("camera edit")
        elif op == 1:  # camera with another aspect, or no camera
            if rng.random() < 0.5:
                cam["width"] = w * 4 + rng.choice([1, 7, 40])
                cam_data = json.dumps(cam).encode()
                notes.append("camera aspect")
            else:
                cam_data = b""
                notes.append("no camera.json")
        elif op == 2 and files:  # corrupt one frame's bytes
            p = rng.choice(files)
            p.write_bytes(mutate_bytes(rng, p.read_bytes()))
            notes.append(f"bytes {p.name}")
        elif op == 3 and files:  # delete frames
            for p in rng.sample(files, rng.randrange(1, len(files) + 1)):
                p.unlink()
            notes.append("frames deleted")
        elif op == 4 and files and not use_mp4:  # one frame of another size
            p = rng.choice(files)
            ow, oh = rng.choice([(w + 1, h), (w, h + 2), (2 * w, 2 * h), (1, 1)])
            p.write_bytes(_png_bytes(g.integers(0, 256, size=(oh, ow, 3), dtype=np.uint8)))
            notes.append(f"{p.name} is {ow}x{oh}")
        elif op == 5 and files:  # a frame that is not an image / empty / a folder
            p = rng.choice(files)
            what = rng.randrange(3)
            p.unlink()
            if what == 0:
                p.write_bytes(b"")
            elif what == 1:
                p.write_text("not an image")
            else:
                p.mkdir()
            notes.append(f"{p.name} not an image ({what})")
        elif op == 6 and files:  # huge declared image size
            p = rng.choice(files)
            big = rng.choice([(100000, 100000), (2 ** 31 - 1, 1), (0, 0), (1, 2 ** 31), (w * 2, h * 2), (65535, 65535), (10000, 10000)])
            p.write_bytes(_png_with_size(p.read_bytes(), *big))
            notes.append(f"{p.name} IHDR {big}")
        elif op == 7:  # mask edits
            mdir = folder / "masks"
            mdir.mkdir(exist_ok=True)
            ms = sorted(q for q in mdir.iterdir() if q.is_file())
            k = rng.randrange(4)
            if k == 0 and ms:
                rng.choice(ms).unlink()
                notes.append("mask deleted")
            elif k == 1:
                sz = rng.choice([(w + 1, h), (1, 1), (w, h)])
                (mdir / "mask_zz.png").write_bytes(_png_bytes(np.zeros((sz[1], sz[0]), np.uint8)))
                notes.append(f"extra mask {sz}")
            elif k == 2 and ms:
                p = rng.choice(ms)
                p.write_bytes(mutate_bytes(rng, p.read_bytes()))
                notes.append("mask bytes")
            else:
                for i in range(t):
                    (mdir / f"mask_{i:04d}.png").write_bytes(
                        _png_bytes(np.zeros((h + 1, w), np.uint8), rng.choice(["L", "I;16", "RGB"])))
                notes.append("masks of another size")
        elif op == 8:  # both mp4 and frames, or two videos
            (folder / rng.choice(["a.mp4", "b.mov"])).write_bytes(_mp4_bytes(w, h, t) if rng.random() < 0.5 else b"\x00" * 64)
            notes.append("extra video")
        elif op == 9 and use_mp4:
            p = folder / "clip.mp4"
            if p.is_file():
                p.write_bytes(mutate_bytes(rng, p.read_bytes()))
                notes.append("mp4 bytes")
        elif op == 10:
            cam["fps"] = rng.choice([0, -30, float("nan"), float("inf"), 1e-300, "30", None, 1e308])
            cam_data = json_text(rng, cam)
            notes.append(f"fps {cam['fps']!r}")
        elif op == 11:  # hidden / odd files beside the frames
            (folder / rng.choice([".frame_0000.png", "notes.txt", "frame_9999.png.bak"])).write_bytes(b"junk")
            notes.append("junk file")
        elif op == 12 and files and not use_mp4:  # frames of odd bit depth / modes
            p = rng.choice(files)
            arr = g.integers(0, 65535, size=(h, w), dtype=np.uint16)
            from PIL import Image

            buf = io.BytesIO()
            Image.fromarray(arr).save(buf, format="PNG")
            p.write_bytes(buf.getvalue())
            notes.append(f"{p.name} 16-bit")
        elif op == 13:
            kwargs["fps"] = rng.choice([None, 0.0, -1.0, float("nan"), 25.0])
            notes.append(f"fps arg {kwargs['fps']}")
        elif op == 14:  # --camera FILE --view ID: a (possibly mutated) camera file elsewhere
            data, name, how = camera_bytes(rng)
            ext = work / "cams"
            ext.mkdir(exist_ok=True)
            (ext / name).write_bytes(data)
            kwargs["camera_path"] = ext / name
            kwargs["view"] = rng.choice([None, 0, 1, -1, 7, "0", "view0", "00000", "r_0", "nope", ""])
            notes.append(f"--camera {name} ({how}) --view {kwargs['view']!r}")
    if cam_data:
        (folder / "camera.json").write_bytes(cam_data)
    src = folder / "clip.mp4" if use_mp4 and (folder / "clip.mp4").is_file() and rng.random() < 0.3 else folder
    return Case(lambda: load_reference_video(src, device=device, **kwargs), sane_video, src, "video " + ", ".join(notes))


# ---------------------------------------------------------------------------- material file
def _material_arrays(rng: random.Random) -> dict[str, np.ndarray]:
    from pd_tool.materials.file import FORMAT, VERSION

    q = rng.choice([1, 2, 5])
    g = np.random.default_rng(rng.randrange(2 ** 32))
    meta = {"format": FORMAT, "version": VERSION, "nu": 0.3, "density": 1000.0, "damping": 0.5,
            "scene_path": "/tmp/scene.ply", "scene_sha256": "0" * 64,
            "prepare": {"grid_res": 32, "up_axis": "+z", "static_box": None},
            "drivers": {"count": q, "ratio": 0.1, "seed": 0}}
    arrays = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8),
              "driver_E": g.uniform(1e4, 1e6, q), "driver_v0": g.normal(size=(q, 3)).astype(np.float32),
              "driver_rest": g.normal(size=(q, 3))}
    if rng.random() < 0.5:
        arrays["field.material.weight"] = g.normal(size=(4, 3)).astype(np.float32)
    return arrays


def _npy_with_shape(arr: np.ndarray, shape_text: str) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr)
    b = buf.getvalue()
    hlen = struct.unpack("<H", b[8:10])[0]
    header = b[10:10 + hlen].decode("latin1")
    import re

    header = re.sub(r"'shape': \([^)]*\)", f"'shape': {shape_text}", header)
    header = header.rstrip()
    header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
    return b[:8] + struct.pack("<H", len(header)) + header.encode("latin1") + b[10 + hlen:]


def _zip_of(members: dict[str, bytes], compress: bool) -> bytes:
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def _npy(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=True)
    return buf.getvalue()


def make_material(rng: random.Random, work: Path, device: str = "cpu") -> Case:  # noqa: ARG001
    from pd_tool.materials.file import MaterialFile

    arrays = _material_arrays(rng)
    notes = []
    compress = rng.random() < 0.3
    op = rng.randrange(9)
    members = {f"{k}.npy": _npy(v) for k, v in arrays.items()}
    if op == 0:  # meta JSON edits
        meta = json.loads(bytes(arrays["meta"]).decode())
        meta = mutate_tree(rng, meta, JSON_NASTY)
        members["meta.npy"] = _npy(np.frombuffer(json_text(rng, meta), np.uint8))
        notes.append("meta tree edit")
    elif op == 1:  # drop / wrong-type / wrong-shape array
        key = rng.choice(list(arrays))
        k = rng.randrange(3)
        if k == 0:
            del members[f"{key}.npy"]
            notes.append(f"no {key}")
        else:
            a = arrays[key]
            with np.errstate(all="ignore"):
                alt = rng.choice([a.astype(np.int64), a.astype(np.complex64), a.astype(str), a.astype(bool),
                              a.reshape(-1), a.reshape(1, -1) if a.size else a, np.array(3.0), np.zeros((0,)),
                              np.zeros((2, 2, 2)), np.array([{"a": 1}], dtype=object),
                              np.zeros(2, dtype=[("a", "<f4"), ("b", "<i4")]), np.array([b"abc"]),
                              a.astype(np.float16), a.astype(np.uint8) if key != "meta" else a.astype(np.float32)])
            members[f"{key}.npy"] = _npy(alt)
            notes.append(f"{key} as {alt.dtype} {alt.shape}")
    elif op == 2:  # value injection
        key = rng.choice(["driver_E", "driver_v0", "driver_rest"] + [k for k in arrays if k.startswith("field.")])
        a = arrays[key].copy()
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            a.flat[rng.randrange(a.size)] = rng.choice([np.nan, np.inf, -np.inf, 0.0, -1.0, 1e300])
        members[f"{key}.npy"] = _npy(a)
        notes.append(f"{key} value")
    elif op == 3:  # huge / bogus declared shape in a .npy header
        key = rng.choice(list(arrays))
        shape = rng.choice(["(10**12,)", "(1000000000000,)", "(2**40, 2**40)", "(4611686018427387904, 4)",
                            "(-1,)", "(3, 3)", "(100000000,)", "()", "('a',)"]).replace("10**12", str(10 ** 12)).replace(
                                "2**40", str(2 ** 40))
        members[f"{key}.npy"] = _npy_with_shape(arrays[key], shape)
        notes.append(f"{key} shape {shape}")
    elif op == 4:  # extra members: odd names, not .npy, a pickle
        name = rng.choice(["field.x.npy", "field..npy", "field.a.b.c.npy", "junk.txt", "meta", "../evil.npy", "field.m.w"])
        members[name] = rng.choice([_npy(np.array([1.0])), b"junk", _npy(np.array([None], dtype=object))])
        notes.append(f"extra member {name}")
    elif op == 5:  # not a zip at all: a bare .npy, a pickle, text, empty
        data = rng.choice([_npy(arrays["driver_E"]), b"\x80\x04K\x01.", b"", b"PK\x03\x04", b"hello", b"PK" + bytes(100)])
        path = work / "m.pdmat"
        path.write_bytes(data)
        return Case(lambda: MaterialFile.load(path), sane_material, path, f"material not a zip {data[:8]!r}")
    elif op == 6:  # meta not JSON / not UTF-8 / not a dict
        members["meta.npy"] = _npy(np.frombuffer(rng.choice([b"\xff\xfe", b"[1, 2]", b"null", b'"x"', b"{",
                                                            deep_json(100000).encode()]), np.uint8))
        notes.append("meta not a dict")
    data = _zip_of(members, compress)
    if op in (7, 8):  # zip-level byte mutation
        data = mutate_bytes(rng, data)
        notes.append("zip bytes")
    path = work / rng.choice(["m.pdmat", "m.npz"])
    path.write_bytes(data)
    return Case(lambda: MaterialFile.load(path), sane_material, path, "material " + ", ".join(notes or ["valid"]))


def make_record(rng: random.Random, work: Path, device: str = "cpu") -> Case:  # noqa: ARG001
    from pd_tool.materials.file import RECORD_PATH, read_record

    scene = work / "scene.ply"
    scene.write_bytes(b"ply\n")
    mat = work / "m.pdmat"
    mat.write_bytes(b"PK")
    rec: Any = {"scene": str(scene), "material": str(mat), "written": "2026-01-01T00:00:00"}
    rec = mutate_tree(rng, rec, JSON_NASTY + [str(work), str(work / "missing.ply"), "a\x00b", "~"])
    path = work / RECORD_PATH
    path.parent.mkdir(parents=True, exist_ok=True)
    if rng.random() < 0.1:
        path.mkdir()
    else:
        path.write_bytes(json_text(rng, rec))
    return Case(lambda: read_record(work), sane_record, path, "record")


# ---------------------------------------------------------------------------- presets
def _toml_value(v: Any) -> str:
    import datetime as dt

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (dt.date, dt.datetime, dt.time)):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}" for k, x in v.items()) + "}"
    return json.dumps(str(v))


def toml_text(tree: dict) -> str:
    """A small TOML writer: top-level scalars first, then one [table] per dict value."""
    lines = [f"{json.dumps(str(k))} = {_toml_value(v)}" for k, v in tree.items() if not isinstance(v, dict)]
    for k, v in tree.items():
        if isinstance(v, dict):
            lines.append(f"[{json.dumps(str(k))}]")
            lines += [f"{json.dumps(str(kk))} = {_toml_value(vv)}" for kk, vv in v.items()]
    return "\n".join(lines) + "\n"


def toml_number(rng: random.Random) -> Any:
    return rng.choice([0, -1, 1, 0.0, -0.0, 1e-320, 1e308, -1e308, float("inf"), float("-inf"), float("nan"),
                       2 ** 63 - 1, -(2 ** 63), 10 ** 30, 1.5, 1e12, 1e13, 0.499, 0.5, 511, 512, 513, 9.5])


def make_preset(rng: random.Random, work: Path, device: str = "cpu") -> Case:  # noqa: ARG001
    import datetime as dt

    from pd_tool.materials.presets import builtin, load_preset

    kind = rng.choice(["materials", "quality", "forces"])
    presets = builtin(kind)
    name = rng.choice(list(presets))
    table = {k: v for k, v in presets[name].items()}
    tree: dict = table if rng.random() < 0.4 else {name: table}
    if rng.random() < 0.15:
        tree[rng.choice(["other", "x"])] = dict(table)
    pool = [None, True, False, 0, -1, 10 ** 30, "", "abc", "1e3", [], [1, 2], {}, {"a": 1}, float("nan"),
            float("inf"), dt.date(2024, 1, 1), 2 ** 63 - 1]
    note = f"{kind} {name}"
    if rng.random() < 0.85:
        # JSON round trip in mutate_tree loses dates, so put dates in afterwards
        tree = mutate_tree(rng, tree, [v for v in pool if not isinstance(v, dt.date)], number=toml_number)
        if rng.random() < 0.1:
            paths = [p for p in _tree_paths(tree) if p]
            if paths:
                p = rng.choice(paths)
                _get(tree, p[:-1])[p[-1]] = dt.date(2024, 1, 1)
        note += " tree edit"
    text = toml_text(tree) if isinstance(tree, dict) else f"x = {_toml_value(tree)}\n"
    if rng.random() < 0.03:
        depth = rng.choice([100, 5000, 100000])
        text = rng.choice(["grid_res = ", "[t]\nE = "]) + rng.choice(["[" * depth + "]" * depth, "{a = " * depth + "1" + "}" * depth])
        note += f" nested {depth} deep"
    data = text.encode()
    if rng.random() < 0.2:
        data = mutate_bytes(rng, data)
        note += " bytes"
    path = work / rng.choice(["p.toml", "my preset.toml"])
    if rng.random() < 0.03:
        path.mkdir()
        note += " folder"
    else:
        path.write_bytes(data)
    arg: Any = path if rng.random() < 0.5 else str(path)
    return Case(lambda: load_preset(kind, arg), sane_preset(kind), path, "preset " + note)


TARGETS: dict[str, Callable[[random.Random, Path, str], Case]] = {
    "ply": make_ply, "splat": make_splat, "cameras": make_cameras, "video": make_video,
    "material": make_material, "record": make_record, "preset": make_preset,
}
WEIGHTS = {"ply": 0.27, "splat": 0.08, "cameras": 0.2, "video": 0.12, "material": 0.15, "record": 0.05, "preset": 0.13}


def check_target(name: str, rng: random.Random, device: str = "cpu", keep: Path | None = None) -> tuple[Outcome, str]:
    """Generate one input for target `name` in a fresh temporary folder, load it, classify.
    Returns (outcome, note). With `keep`, a failing input is copied there."""
    with tempfile.TemporaryDirectory(prefix=f"pdfuzz-{name}-") as d:
        case = TARGETS[name](rng, Path(d), device)
        out = run_checked(case.load, case.sanity)
        if out.kind == "bug" and keep is not None:
            keep.mkdir(parents=True, exist_ok=True)
            dst = keep / f"{name}-{len(list(keep.iterdir())):05d}"
            src = Path(d)
            shutil.copytree(src, dst, symlinks=True, ignore_dangling_symlinks=True)
            (dst / "BUG.txt").write_text(f"{case.note}\n{case.path.relative_to(src)}\n{out.detail}\n")
        return out, case.note


# ============================================================================ CLI
def tiny_scene(path: Path) -> Path:
    """A valid 8-Gaussian .ply for the commands that need a scene beside the fuzzed input."""
    path.write_bytes(_ply_bytes(_ply_records(random.Random(0), 8, 0, normals=False, extra=False), "le"))
    return path


def cli_args(target: str, case: Case, work: Path, scene: Path) -> list[str] | None:
    """The pdtool command line that reads this input, or None when no command reads it as
    a plain file argument (click refuses folders given where a file is expected, with its
    own usage text, before pdtool runs). Only inputs the loader rejects are given to the
    commands other than `info`, so that none of them starts a real fit or bake."""
    p = str(case.path)
    out = work / "cli-out"
    if target in ("ply", "splat"):
        return ["info", p]
    if target == "cameras" and case.path.is_file():
        return ["render", str(scene), "-o", str(out.with_suffix(".png")), "--camera", p, "--width", "16",
                "--height", "16", "--device", "cpu"]
    if target == "video":
        return ["fit", str(scene), p, "-o", str(out.with_suffix(".pdmat")), "--no-preview", "--device", "cpu"]
    if target == "material" and case.path.is_file():
        return ["bake", str(out.with_suffix(".usd")), "--scene", str(scene), "--material", p, "--force", "0,0,1",
                "--device", "cpu"]
    if target == "preset":
        kind = case.note.split()[1]
        opt = {"materials": ["--preset", p], "quality": ["--preset", "jelly", "--quality", p],
               "forces": ["--preset", "jelly", "--interaction", p]}[kind]
        return ["bake", str(out.with_suffix(".usd")), "--scene", str(scene), *opt, "--force", "0,0,1", "--device", "cpu"]
    if target == "record":
        return ["bake", str(out.with_suffix(".usd")), "--force", "0,0,1", "--device", "cpu"]  # run in `work`
    return None


def cli_run(args: list[str], cwd: Path | None = None, runner: Any = None) -> tuple[int, str, str]:
    """`pdtool ARGS` through click's CliRunner: (exit code, stdout, stderr + any traceback)."""
    from click.testing import CliRunner

    from cli import main

    runner = runner or CliRunner()
    old = Path.cwd()
    try:
        if cwd is not None:
            os.chdir(cwd)
        res = runner.invoke(main, args, catch_exceptions=True)
    finally:
        os.chdir(old)
    err = res.stderr
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        err += "".join(traceback.format_exception(res.exception))
    return res.exit_code, res.stdout, err


def cli_property(code: int, out: str, err: str, loaded_ok: bool) -> str | None:
    """None when pdtool behaved: exit 0 for a good file (info), else exit 2 with exactly one
    stderr line starting 'Error: ' and no traceback. Otherwise what went wrong."""
    if "Traceback" in err or "Traceback" in out:
        return f"traceback (exit {code}): {err[-500:]}"
    if loaded_ok:
        return None if code == 0 else f"exit {code} for a file the loader accepts: {err[:300]}"
    lines = err.strip().splitlines()
    if code != 2:
        return f"exit {code} (expected 2): {err[:300]}"
    if len(lines) != 1 or not lines[0].startswith("Error: "):
        return f"stderr is not one 'Error: ' line: {err[:300]!r}"
    return None


CLI_WEIGHTS = {"ply": 0.35, "splat": 0.1, "cameras": 0.15, "video": 0.1, "material": 0.1, "preset": 0.15, "record": 0.05}


def cli_one(target: str, rng: random.Random, runner: Any = None, subprocess_too: bool = False) -> tuple[str | None, str]:
    """Generate one input for `target`, run the command that reads it, check the CLI
    property. Returns (problem or None, note); (None, note) also when no command applies."""
    import subprocess

    with tempfile.TemporaryDirectory(prefix=f"pdfuzz-cli-{target}-") as d:
        work = Path(d)
        case = TARGETS[target](rng, work, "cpu")
        if target == "video":  # the CLI's own settings: working size 256, fps from the files
            from pd_tool.video.folder import load_reference_video

            src = case.path
            case = Case(lambda: load_reference_video(src, working_size=256), sane_video, src, case.note)
        lib = run_checked(case.load, case.sanity)
        ok = lib.kind == "ok"
        if ok and target not in ("ply", "splat"):
            return None, case.note + " (loads: no command run)"
        if lib.signature.startswith(("insane", "warning")) and target not in ("ply", "splat"):
            # the loader returned something: the command would start a real fit or bake
            return f"loader: {lib.detail}", case.note + " (loads: no command run)"
        scene = tiny_scene(work / "tiny_scene.ply")
        args = cli_args(target, case, work, scene)
        if args is None:
            return None, case.note + " (no command reads it)"
        code, out, err = cli_run(args, cwd=work if target == "record" else None, runner=runner)
        bad = cli_property(code, out, err, ok)
        if subprocess_too and bad is None:
            exe = Path(sys.executable).with_name("pdtool")
            cmd = [str(exe)] if exe.exists() else [sys.executable, str(Path(__file__).resolve().parents[1] / "cli.py")]
            proc = subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=300,
                                  cwd=work if target == "record" else None)
            bad = cli_property(proc.returncode, proc.stdout, proc.stderr, ok)
            if bad:
                bad = "subprocess: " + bad
        return bad, f"pdtool {args[0]} on {case.note}"


def run_cli(n: int, seed: int, subprocess_n: int = 10) -> dict[str, Any]:
    """n inputs through the commands that read them (CliRunner); every n // subprocess_n-th
    one also through the installed console script."""
    from click.testing import CliRunner

    rng = random.Random(f"{seed}-cli")
    runner = CliRunner()
    names = list(CLI_WEIGHTS)
    stats: dict[str, Any] = {"tried": 0, "commands_run": 0, "subprocess": 0, "bugs": 0, "per_target": {}, "examples": []}
    every = max(1, n // subprocess_n) if subprocess_n else 0
    for i in range(n):
        target = rng.choices(names, weights=[CLI_WEIGHTS[t] for t in names])[0]
        sub = bool(every) and i % every == 0
        bad, note = cli_one(target, rng, runner, subprocess_too=sub)
        stats["tried"] += 1
        ran = "no command" not in note and "no command run" not in note
        stats["commands_run"] += ran
        stats["subprocess"] += sub and ran
        pt = stats["per_target"].setdefault(target, {"tried": 0, "commands_run": 0, "bugs": 0})
        pt["tried"] += 1
        pt["commands_run"] += ran
        if bad:
            stats["bugs"] += 1
            pt["bugs"] += 1
            if len(stats["examples"]) < 10:
                stats["examples"].append({"note": note, "problem": bad})
    return stats


# ============================================================================ main
def _limit_memory(gb: float) -> None:
    with contextlib.suppress(Exception):
        import resource

        lim = int(gb * 2 ** 30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, lim))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=12000, help="total generated inputs over all targets")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--targets", default=",".join(TARGETS), help="comma-separated subset of " + ", ".join(TARGETS))
    ap.add_argument("--cli", type=int, default=300, help="inputs also run through the pdtool command that reads them (0: none)")
    ap.add_argument("--subprocess", type=int, default=10, help="of those, how many through the real console script")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="where loaded tensors go")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--save-failures", type=Path, help="copy each failing input into this folder")
    ap.add_argument("--mem-limit-gb", type=float, default=16.0,
                    help="address-space limit on CPU (a loader that tries to allocate more fails visibly)")
    args = ap.parse_args(argv)
    if args.device == "cpu" and args.mem_limit_gb > 0:
        _limit_memory(args.mem_limit_gb)
    names = [t.strip() for t in args.targets.split(",") if t.strip()]
    total_w = sum(WEIGHTS[t] for t in names)
    quota = {t: max(1, round(args.n * WEIGHTS[t] / total_w)) for t in names}
    report: dict[str, Any] = {"seed": args.seed, "n": sum(quota.values()), "device": args.device, "targets": {}}
    t_all = time.perf_counter()
    any_bug = False
    for t in names:
        rng = random.Random(f"{args.seed}-{t}")
        counts = {"tried": 0, "ok": 0, "error": 0, "bug": 0}
        sigs: dict[str, dict[str, Any]] = {}
        t0 = time.perf_counter()
        for _ in range(quota[t]):
            out, note = check_target(t, rng, args.device, args.save_failures)
            counts["tried"] += 1
            counts[out.kind] += 1
            if out.kind == "bug":
                s = sigs.setdefault(out.signature, {"count": 0, "example": note, "detail": out.detail[:800]})
                s["count"] += 1
        counts["seconds"] = round(time.perf_counter() - t0, 2)
        counts["bugs"] = sigs
        report["targets"][t] = counts
        any_bug |= bool(sigs)
        print(f"{t:9s} tried {counts['tried']:6d}  loaded {counts['ok']:6d}  rejected {counts['error']:6d}  "
              f"bugs {counts['bug']:5d}  ({counts['seconds']:.1f} s)", flush=True)
        for sig, s in sorted(sigs.items(), key=lambda kv: -kv[1]["count"]):
            print(f"    {s['count']:5d} x {sig}   e.g. {s['example']}", flush=True)
    if args.cli > 0:
        t0 = time.perf_counter()
        report["cli"] = run_cli(args.cli, args.seed, args.subprocess)
        report["cli"]["seconds"] = round(time.perf_counter() - t0, 2)
        c = report["cli"]
        print(f"cli       tried {c['tried']:6d}  commands run {c['commands_run']:6d}  bugs {c['bugs']:5d}  "
              f"(subprocess {c['subprocess']}, {c['seconds']:.1f} s)")
        for t, v in c["per_target"].items():
            print(f"    {t:9s} {v['tried']:5d} inputs, {v['commands_run']:5d} commands run, {v['bugs']} bugs")
        for ex in c["examples"]:
            print(f"    {ex['note']}: {ex['problem'][:200]}")
        any_bug |= c["bugs"] > 0
    report["seconds"] = round(time.perf_counter() - t_all, 1)
    report["total_tried"] = sum(v["tried"] for v in report["targets"].values())
    report["total_bugs"] = sum(v["bug"] for v in report["targets"].values()) + report.get("cli", {}).get("bugs", 0)
    print(f"total     {report['total_tried']} loader inputs, {report['total_bugs']} bugs, {report['seconds']:.0f} s")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2, default=str))
    return 1 if any_bug else 0


if __name__ == "__main__":
    sys.exit(main())
