"""UsdBakeWriter: stream an animated splat bake into one USD file, frame by frame.

Memory stays bounded without value clips: time samples go straight into a
crate (.usdc) layer, and the layer is saved whenever `flush_bytes` of new
samples have piled up. A crate save appends the new arrays to the file and
afterwards reads them back lazily from the memory-mapped file, so samples
already saved no longer occupy the heap (measured in docs/usd.md:
peak RSS flat in the number of frames). The result is a single file.

Atomic output: everything is written to a hidden temporary file next to the
destination (same file system) and moved into place with os.replace only by
`close()`, after validation. An exception inside `with UsdBakeWriter(...)`
(or `abort()`) deletes the temporary file, so a failed bake leaves nothing.
A destination that cannot be written (full, read-only, a name too long) raises
pd_tool.core.errors.OutputError, one line naming the destination, never the temporary.
"""
from __future__ import annotations

import os
import queue
import secrets
import threading
import weakref
from pathlib import Path

import numpy as np
from pxr import Kind, Sdf, Usd, UsdGeom

from pd_tool.core import atomic as _atomic
from pd_tool.core.errors import UsdExportError

from ._geom import normalize_quats, rgb_to_sh_dc, sh_dc_to_rgb, srgb_to_linear, unit_xyzw_half
from ._held import same_values
from .instancer import InstancerPart
from .splat_field import SplatFieldPart

FORMATS = ("instancer", "splat", "both")
SUFFIXES = (".usd", ".usdc", ".usda")
DEFAULT_SCALE_FACTOR = 2.0  # instancer sphere radius / sigma: the ~2-sigma ellipsoid
DEFAULT_FLUSH_BYTES = 64 << 20  # bytes of unsaved samples before an incremental save
QUEUE_FRAMES = 2  # threaded mode: frames waiting for the writer thread (bounds memory)
ROOT = "/Root"
# How far an instance marked static may stray from its first frame: float rounding of the
# caller's transforms (a pinned Gaussian goes scene -> simulation -> scene axes each frame,
# a few float32 ulps), not motion. Positions relative to the frame's coordinate magnitude
# plus its size; orientations as |q - q0| (sign-blind); scales relative.
STATIC_POS_TOL = 1e-5
STATIC_QUAT_TOL = 1e-4
STATIC_SCALE_TOL = 1e-5


class UsdBakeWriter:
    """Write an animated Gaussian-splat bake as USD, one frame at a time.

    Args:
        path: destination, ``.usd`` / ``.usdc`` (binary crate, streamed) or
            ``.usda`` (text; converted at close, so not memory bounded: for
            small debugging bakes only).
        n_points: N, the number of Gaussians (fixed for the whole bake).
        fps: frames per second; time codes are frame numbers, so the stage's
            timeCodesPerSecond and framesPerSecond are both `fps`.
        start_frame: first time code (stage startTimeCode).
        up_axis: "Y" or "Z", the stage upAxis.
        meters_per_unit: metres per scene unit (stage metersPerUnit).
        fmt: "instancer" (UsdGeom.PointInstancer of unit spheres + a coloured
            UsdGeom.Points), "splat" (UsdVol.ParticleField3DGaussianSplat) or
            "both".
        colors: [N, 3] float 0-1 display colour per splat, sRGB encoded as 3DGS
            renders it; default: from the DC term of `sh` (0.5 + 0.2821 * dc), else
            mid grey. primvars:displayColor receives them linearised (sRGB EOTF),
            because USD defines displayColor as linear.
        opacities: [N] float 0-1 (activated); default 1.
        sh: [N, K, 3] SH coefficients, K = (d+1)^2, sh[:, 0] the DC term; used by
            the splat schema. Default: degree 0 from `colors`.
        scale_factor: instancer scale = Gaussian sigma * scale_factor; the
            default 2 makes the unit-sphere prototype show the 2-sigma ellipsoid.
        ids: [N] int instance ids (PointInstancer.ids); default 0..N-1.
        static: [N] bool, instances that keep their first frame's pose for the whole
            bake (a pinned pot; the bake passes its static and unsimulated Gaussians).
            They go to /Root/StaticInstancer, /Root/StaticSplatColors and
            /Root/StaticSplats, written once as default values; the others to the
            time-sampled prims. Every frame is checked: a static instance that moves
            further than float rounding (STATIC_*_TOL) raises UsdExportError.
        color_points: also write /Root/SplatColors (UsdGeom.Points with
            displayColor), the only place Blender reads per-splat colour from.
        flush_bytes: save (append to the file) after this many bytes of new
            samples; bounds the writer's memory.
        threaded: write in a background thread so that USD work overlaps the
            caller's simulation (GPU waits release the GIL). `write_frame` then
            copies its inputs, checks them, queues them (at most QUEUE_FRAMES
            waiting, so memory stays bounded) and returns; an error in the thread
            is raised by the next call or by `close()`.

    Example:
        >>> with UsdBakeWriter("out.usd", n_points=n, fps=30, colors=rgb,
        ...                    opacities=alpha, sh=sh, fmt="both") as w:
        ...     for f in range(frames):
        ...         w.write_frame(f, pos[f], quats_wxyz[f], sigmas[f])
        ...     w.hold_frames(59)          # at rest: no new samples up to 59
        >>> # leaving the block calls close(): validated, then moved into place
    """

    def __init__(self, path: str | os.PathLike, *, n_points: int, fps: float,
                 start_frame: float = 0, up_axis: str = "Z", meters_per_unit: float = 1.0,
                 fmt: str = "instancer", colors: np.ndarray | None = None,
                 opacities: np.ndarray | None = None, sh: np.ndarray | None = None,
                 scale_factor: float = DEFAULT_SCALE_FACTOR, ids: np.ndarray | None = None,
                 color_points: bool = True, flush_bytes: int = DEFAULT_FLUSH_BYTES,
                 threaded: bool = False, static: np.ndarray | None = None) -> None:
        self.path = Path(path)
        n = int(n_points)
        self._check_args(n, fps, up_axis, meters_per_unit, fmt, scale_factor)
        colors, opacities, sh, ids = _per_splat_inputs(n, colors, opacities, sh, ids)
        static = _static_mask(n, static)
        self._static_idx = np.flatnonzero(static)
        # None: every instance moves, and frames are written without a subset copy
        self._moving_idx = np.flatnonzero(~static) if len(self._static_idx) else None
        self._static_pose: tuple[np.ndarray, np.ndarray, np.ndarray, float] | None = None
        self._static_q_given: np.ndarray | None = None  # the first frame's, unnormalised
        self.n_points, self.fps, self.fmt = n, float(fps), fmt
        self.start_frame = float(start_frame)
        self.flush_bytes = int(flush_bytes)
        # caller side: what has been accepted (time checks, end time code)
        self.frames_written = 0
        self._last_t: float | None = None
        self._held_until: float | None = None
        self._closed = False
        self.warnings: list[str] = []
        # writer side (the writer thread in threaded mode): what is in the layer
        self.bytes_written = 0  # array bytes of all time samples handed to USD
        self._w_frames = 0
        # per time-sampled attribute: (last authored value, its time); a value equal to the
        # last one is not authored again (a held pose, constant scales)
        self._w_last: dict[Sdf.Path, tuple[object, np.ndarray, float]] = {}
        self._w_covered: float | None = None  # last frame written or held, in the layer
        self._unsaved = 0
        self._thread: threading.Thread | None = None
        self._thread_error: BaseException | None = None
        self._cancel = False

        token = f"{os.getpid()}-{secrets.token_hex(4)}"
        # the output's name, shortened: a temporary must fit NAME_MAX wherever the name does
        stem = _atomic.temp_stem(self.path.name)
        self._tmp = self.path.parent / f".{stem}.tmp-{token}.usdc"
        self._tmp_text = self.path.parent / f".{stem}.tmp-{token}.usda"
        self._layer = None
        # Last line of defence for a writer dropped without close()/abort() (no
        # with-block, an exception in between): its temporaries go at collection
        # or interpreter exit. After close() the file was renamed away already.
        self._finalizer = weakref.finalize(self, _unlink_all, (self._tmp, self._tmp_text))
        if not os.path.isdir(self.path.parent):
            raise UsdExportError(f"{self.path}: folder {self.path.parent} does not exist; "
                                 f"create it or choose another output path")
        problem = _atomic.destination_problem(self.path)  # a name too long, a read-only or full disk
        if problem is not None:
            raise _atomic.output_error(self.path, problem)
        try:
            # A strong reference: a stage hands out only weak layer handles, and the
            # layer must outlive the stage used to set it up.
            self._layer = Sdf.Layer.CreateNew(str(self._tmp))
            stage = Usd.Stage.Open(self._layer)
        except Exception as e:  # pxr raises Tf.ErrorException on unwritable paths
            self._layer = None
            self._remove_temporaries()
            raise _write_error(self.path, e, (self._tmp, self._tmp_text), creating=True) from None
        try:
            self._setup_stage(stage, up_axis, meters_per_unit, colors, opacities, sh, ids,
                              scale_factor, color_points, static)
            self._save()
        except BaseException:
            del stage
            self._layer = None
            self._remove_temporaries()
            raise
        # From here on samples go straight into the layer: no stage, so no change
        # processing per sample.
        del stage
        if threaded:
            self._queue: queue.Queue = queue.Queue(maxsize=QUEUE_FRAMES)
            self._thread = threading.Thread(target=self._worker, name="UsdBakeWriter", daemon=True)
            self._thread.start()

    # ---------------------------------------------------------------- setup
    @staticmethod
    def _check_args(n: int, fps: float, up_axis: str, mpu: float, fmt: str,
                    scale_factor: float) -> None:
        if n <= 0:
            raise UsdExportError(f"n_points={n}: a bake needs at least one splat")
        if not fps > 0:
            raise UsdExportError(f"fps={fps}: must be > 0")
        if up_axis not in ("Y", "Z"):
            raise UsdExportError(f"up_axis={up_axis!r}: must be 'Y' or 'Z'")
        if not mpu > 0:
            raise UsdExportError(f"meters_per_unit={mpu}: must be > 0")
        if fmt not in FORMATS:
            raise UsdExportError(f"format {fmt!r}: choose one of {', '.join(FORMATS)}")
        if not scale_factor > 0:
            raise UsdExportError(f"scale_factor={scale_factor}: must be > 0")

    def _setup_stage(self, stage: Usd.Stage, up_axis: str, mpu: float, colors, opacities,
                     sh, ids, scale_factor: float, color_points: bool, static: np.ndarray) -> None:
        if self.path.suffix.lower() not in SUFFIXES:
            raise UsdExportError(f"{self.path}: output must end in {', '.join(SUFFIXES)}")
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, float(mpu))
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(self.start_frame)
        stage.SetEndTimeCode(self.start_frame)
        root = UsdGeom.Xform.Define(stage, ROOT)
        Usd.ModelAPI(root).SetKind(Kind.Tokens.component)
        stage.SetDefaultPrim(root.GetPrim())
        stage.GetRootLayer().documentation = "pdtool bake: animated 3D Gaussian splats"
        # USD's displayColor is linear; 3DGS colours are sRGB encoded
        colors = srgb_to_linear(colors)
        # Moving and static instances live in separate prims: a PointInstancer's arrays
        # hold every instance at every time, so one prim would repeat the static ones in
        # each frame's sample (docs/usd.md, "Static instances").
        self._parts, self._static_parts = [], []
        for prefix, sel, parts in (("", ~static, self._parts), ("Static", static, self._static_parts)):
            if not sel.any():
                continue
            if self.fmt in ("instancer", "both"):
                parts.append(InstancerPart(
                    stage, f"{ROOT}/{prefix}Instancer", colors=colors[sel], opacities=opacities[sel],
                    ids=ids[sel], scale_factor=scale_factor,
                    color_points_path=f"{ROOT}/{prefix}SplatColors" if color_points else None))
            if self.fmt in ("splat", "both"):
                parts.append(SplatFieldPart(stage, f"{ROOT}/{prefix}Splats", colors=colors[sel],
                                            opacities=opacities[sel], sh=sh[sel]))

    # ---------------------------------------------------------------- frames
    def write_frame(self, time_code: float, positions: np.ndarray, orientations: np.ndarray,
                    scales: np.ndarray) -> None:
        """Author one frame's time samples.

        Args:
            time_code: frame number; strictly greater than any earlier frame or hold.
            positions: [N, 3] scene units (cast to float32).
            orientations: [N, 4] (w, x, y, z), unit (renormalised here).
            scales: [N, 3] linear Gaussian sigmas, scene units (> 0).
        """
        self._check_open()
        t = float(time_code)
        pos, q, sig = self._check_frame(t, positions, orientations, scales, copy=self._thread is not None)
        self._check_static(t, pos, q, sig)
        self._last_t, self._held_until = t, None
        self.frames_written += 1
        self._submit(("frame", t, pos, q, sig))

    def hold_frames(self, until_time_code: float) -> None:
        """Extend the animation to `until_time_code` with the object at rest.

        No samples are written (USD holds the last sample); only the end time
        code moves. A later `write_frame` re-authors the held pose first.
        """
        self._check_open()
        t = float(until_time_code)
        if self._last_t is None:
            raise UsdExportError("hold_frames before any write_frame: write the rest pose first")
        if t <= self.end_time_code:
            raise UsdExportError(f"hold_frames({t:g}): must be after time code {self.end_time_code:g}")
        self._held_until = t
        self._submit(("hold", t))

    def _submit(self, item: tuple) -> None:
        if self._thread is None:
            self._apply(item)
        else:
            self._queue.put(item)  # blocks while QUEUE_FRAMES frames wait: bounded memory

    def _check_static(self, t: float, pos: np.ndarray, q: np.ndarray, sig: np.ndarray) -> None:
        """Static instances must keep their first frame's pose (to float rounding)."""
        si = self._static_idx
        if not len(si):
            return
        if self._static_pose is None:
            p0 = pos[si]
            size = float(np.abs(p0).max(initial=0.0) + np.ptp(pos, axis=0).max(initial=0.0))
            self._static_pose = (p0.copy(), normalize_quats(q[si]), sig[si].copy(),
                                 STATIC_POS_TOL * max(size, 1e-30))
            self._static_q_given = q[si]  # fancy indexing copies
            return
        p0, q0, s0, tol = self._static_pose
        # a bake hands its static instances over unchanged, bit for bit: comparing the bytes
        # is a third of the tolerance test's cost
        pos_s, q_s, sig_s = pos[si], q[si], sig[si]
        if np.array_equal(pos_s, p0) and np.array_equal(q_s, self._static_q_given) and np.array_equal(sig_s, s0):
            return
        moved = float(np.abs(pos_s - p0).max())
        qn = normalize_quats(q_s)
        turned = float(np.minimum(np.abs(qn - q0).max(axis=1), np.abs(qn + q0).max(axis=1)).max())
        grown = float((np.abs(sig_s - s0) / s0).max())
        if moved > tol or turned > STATIC_QUAT_TOL or grown > STATIC_SCALE_TOL:
            raise UsdExportError(
                f"frame {t:g}: instances passed as static changed since the first frame (moved "
                f"{moved:.3g} scene units, rotated {turned:.3g}, scaled {grown:.3g}; float rounding "
                f"allows {tol:.3g}, {STATIC_QUAT_TOL:g}, {STATIC_SCALE_TOL:g}); leave moving "
                f"instances out of `static`")

    def _apply(self, item: tuple) -> None:
        if item[0] == "hold":
            self._w_covered = item[1]
            return
        _, t, positions, quats, sigmas = item
        xyzw16 = unit_xyzw_half(quats)  # normalised once for every part
        layer = self._layer
        if self._w_frames == 0:
            si = self._static_idx
            static = (positions[si], quats[si], sigmas[si], xyzw16[si]) if len(si) else None
            for part in self._static_parts:  # their only values: defaults, no time samples
                for p, v in part.first_frame_defaults(*static) + part.samples(*static):
                    layer.GetAttributeAtPath(p).default = v
        mi = self._moving_idx
        moving = (positions, quats, sigmas, xyzw16) if mi is None else (positions[mi], quats[mi], sigmas[mi], xyzw16[mi])
        if self._w_frames == 0:
            for part in self._parts:
                for p, v in part.first_frame_defaults(*moving):
                    layer.GetAttributeAtPath(p).default = v
        nbytes = 0
        prev = self._w_covered
        for p, v in (s for part in self._parts for s in part.samples(*moving)):
            a = np.asarray(v)  # Vt arrays expose a buffer: no copy
            last = self._w_last.get(p)
            if last is not None and (last[0] is v or same_values(last[1], a)):
                continue  # unchanged since the last sample (a part's Held value: the same object): USD holds it
            if last is not None and last[2] < prev:
                # The value was held (unchanged frames, or hold_frames) up to the previous
                # frame: author it there too, or linear interpolation would blend the new
                # value into the held ones.
                layer.SetTimeSample(p, prev, last[0])
                nbytes += a.nbytes
            layer.SetTimeSample(p, t, v)
            nbytes += a.nbytes
            self._w_last[p] = (v, a, t)
        self._w_covered = t
        self._w_frames += 1
        self.bytes_written += nbytes
        self._unsaved += nbytes
        if self._unsaved >= self.flush_bytes:
            self._save()

    def _worker(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._thread_error is not None or self._cancel:
                continue  # drain: the caller will raise or has given up
            try:
                self._apply(item)
            except BaseException as e:  # handed to the caller thread
                self._thread_error = e

    def _join_thread(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = None

    @property
    def end_time_code(self) -> float:
        """Last time code covered so far (written or held)."""
        ends = [x for x in (self._last_t, self._held_until) if x is not None]
        return max(ends) if ends else self.start_frame

    def _check_frame(self, t: float, positions, orientations, scales, copy: bool = False):
        # Everything is checked here, in the caller's thread, so errors surface at
        # the call that caused them even in threaded mode.
        if self._thread_error is not None:
            raise self._thread_error
        n = self.n_points
        if not np.isfinite(t) or t < self.start_frame:
            raise UsdExportError(f"time code {t:g}: must be finite and >= start_frame {self.start_frame:g}")
        if self._last_t is not None and t <= self.end_time_code:
            raise UsdExportError(f"time code {t:g}: frames must increase "
                                 f"(last covered {self.end_time_code:g})")
        # copy: a queued frame must not change when the caller reuses its buffers. Without
        # it, asarray converts only what needs it (numpy 2 refuses copy=False then).
        as_f32 = np.array if copy else np.asarray
        pos = as_f32(_np(positions), dtype=np.float32, order="C")
        q = as_f32(_np(orientations), dtype=np.float32, order="C")
        s = as_f32(_np(scales), dtype=np.float32, order="C")
        for name, a, cols in (("positions", pos, 3), ("orientations", q, 4), ("scales", s, 3)):
            if a.shape != (n, cols):
                raise UsdExportError(f"frame {t:g}: {name} has shape {tuple(a.shape)}, "
                                     f"expected ({n}, {cols})")
            if not np.isfinite(a).all():
                raise UsdExportError(f"frame {t:g}: {name} holds NaN or inf; the simulation "
                                     f"diverged (try a finer --quality or a smaller force)")
        if not (s > 0).all():
            raise UsdExportError(f"frame {t:g}: scales must be linear sigmas > 0 "
                                 f"(min {s.min():g}); pass exp(log_scales)")
        return pos, q, s

    # ---------------------------------------------------------------- finish
    def _save(self) -> None:
        try:
            ok = self._layer.Save()
        except Exception as e:  # Tf.ErrorException: disk full, folder removed, ...
            raise _write_error(self.path, e, (self._tmp, self._tmp_text)) from None
        if not ok:
            raise _write_error(self.path, None)
        self._unsaved = 0

    def close(self, *, validate: bool = True) -> Path:
        """Finish the file and move it to `path` atomically; returns `path`.

        With `validate`, `validate_usd` (all registered UsdValidation validators,
        our checks at the first and last sample) runs on the finished temporary
        file; an invalid file raises UsdExportError and is deleted, never published.
        Its warnings are kept in `self.warnings`.
        """
        self._check_open()
        if self.frames_written == 0:
            self.abort()
            raise UsdExportError(f"{self.path}: no frames were written; nothing to save")
        try:
            self._join_thread()
            if self._thread_error is not None:
                raise self._thread_error
            self._layer.endTimeCode = self.end_time_code
            self._save()
            src = self._tmp
            if self.path.suffix.lower() == ".usda":
                self._layer.Export(str(self._tmp_text))
                src = self._tmp_text
            self._layer = None
            if validate:
                from .validate import validate_usd
                self.warnings = validate_usd(src, every_sample=False)
            try:
                os.replace(src, self.path)
            except OSError as e:
                raise _atomic.output_error(self.path, e) from None
        except BaseException:
            self.abort()
            raise
        self._remove_temporaries()
        self._closed = True
        _reload_if_open(self.path)
        return self.path

    def abort(self) -> None:
        """Drop the bake: delete the temporary files; `path` is left untouched."""
        self._cancel = True
        self._join_thread()
        self._layer = None
        self._closed = True
        self._remove_temporaries()

    def _remove_temporaries(self) -> None:
        _unlink_all((self._tmp, self._tmp_text))

    def _check_open(self) -> None:
        if self._closed:
            raise UsdExportError(f"{self.path}: writer is already closed")

    def __enter__(self) -> "UsdBakeWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self._closed:
            return
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _pxr_message(e: Exception) -> str:
    """The human part of a Tf error: "Error in 'Func' at line .. : 'msg'" -> "msg"."""
    text = " ".join(str(e).split())
    if " : " in text:
        text = text.rsplit(" : ", 1)[1]
    return text.strip("'\" ")


def _write_error(path: Path, e: Exception | None, temporaries: tuple[Path, ...] = (),
                 creating: bool = False) -> Exception:
    """The error for a failed USD write: OutputError when the destination shows why
    (full, read-only, ...) or pxr names an OS error, else UsdExportError with pxr's words
    (the hidden temporary's name replaced by the user's path)."""
    text = _pxr_message(e) if e is not None else ""
    for tmp in temporaries:
        text = text.replace(str(tmp), str(path))
    everything = " ".join(str(e).split()) if e is not None else ""  # pxr's chain: the OS error may come first
    quoted = _atomic.output_error_in_text(path, everything)
    if quoted is not None:
        return quoted
    problem = _atomic.destination_problem(path)
    if problem is not None:
        return _atomic.output_error(path, problem)
    if creating:
        return UsdExportError(f"{path}: cannot create a USD file there{f' ({text})' if text else ''}; check the "
                              f"folder is writable")
    return UsdExportError(f"{path}: writing the USD file failed{f' ({text})' if text else ''}; check free "
                          f"disk space and that {path.parent} still exists")


def _unlink_all(paths) -> None:
    # runs from a finalizer too, where an exception would print a traceback at exit
    for p in paths:
        try:
            p.unlink()
        except OSError:
            pass


def _np(a) -> np.ndarray:
    """numpy view of a numpy array or a (CPU or CUDA) torch tensor."""
    if hasattr(a, "detach"):
        a = a.detach().cpu().numpy()
    return np.asarray(a)


def _static_mask(n: int, static) -> np.ndarray:
    if static is None:
        return np.zeros(n, bool)
    m = np.asarray(_np(static))
    if m.shape != (n,) or m.dtype != bool:
        raise UsdExportError(f"static must be {n} booleans, got {m.dtype} {tuple(m.shape)}")
    return m.copy()


def _per_splat_inputs(n: int, colors, opacities, sh, ids):
    """Validate and fill in the constant per-splat arrays (see UsdBakeWriter)."""
    if sh is not None:
        sh = np.asarray(_np(sh), dtype=np.float32)
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise UsdExportError(f"sh has shape {tuple(sh.shape)}, expected ({n}, K, 3)")
        k = sh.shape[1]
        if k < 1 or round(k ** 0.5) ** 2 != k:
            raise UsdExportError(f"sh has {k} coefficients per splat; expected (degree+1)^2 "
                                 f"(1, 4, 9 or 16)")
    if colors is None:
        colors = sh_dc_to_rgb(sh[:, 0]) if sh is not None else np.full((n, 3), 0.5, np.float32)
    colors = np.ascontiguousarray(_np(colors), dtype=np.float32)
    if colors.shape != (n, 3):
        raise UsdExportError(f"colors has shape {tuple(colors.shape)}, expected ({n}, 3)")
    if sh is None:
        sh = rgb_to_sh_dc(colors)[:, None, :]
    opacities = np.ones(n, np.float32) if opacities is None else _np(opacities)
    opacities = np.ascontiguousarray(opacities, dtype=np.float32).reshape(-1)
    if opacities.shape != (n,):
        raise UsdExportError(f"opacities has {opacities.shape[0]} values, expected {n}")
    for name, a in (("colors", colors), ("opacities", opacities)):
        if not np.isfinite(a).all() or a.min() < 0 or a.max() > 1:
            raise UsdExportError(f"{name} must lie in 0-1 (found {a.min():g}..{a.max():g}); "
                                 f"pass activated values, not logits")
    if ids is None:
        return colors, opacities, sh, np.arange(n, dtype=np.int64)
    ids = np.asarray(_np(ids), dtype=np.int64)
    if ids.shape != (n,) or np.unique(ids).size != n:
        raise UsdExportError(f"ids must be {n} distinct integers")
    return colors, opacities, sh, ids


def _reload_if_open(path: Path) -> None:
    # Sdf caches layers by path: a layer for `path` still held elsewhere in this
    # process (an earlier bake opened for checking) would show the old file.
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)
