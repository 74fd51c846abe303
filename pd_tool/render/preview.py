"""Preview videos and images: atomic .mp4 / .gif / .png writers and an animation renderer.

Writers: the ffmpeg binary that the imageio-ffmpeg wheel ships (H.264 .mp4, no system
ffmpeg needed), driven through a pipe whose exit status and error output pdtool reads
itself (so an encoder failure is one line, never a half-written file or ffmpeg's own
lines on the terminal), and Pillow for .gif / .png. Every file is written to a temporary
name beside the target and renamed (pd_tool.core.atomic), so a failed or interrupted write
leaves no half-written preview, and every file carries pdtool's mark (mp4/gif comment,
PNG Software text) so that pdtool knows later which files it may replace.
"""
from __future__ import annotations

import os
import subprocess
import threading
from fractions import Fraction
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from pd_tool.core.atomic import MARK_TEXT, as_output_error, atomic_output, output_error_in_text, png_info
from pd_tool.core.errors import PdToolError
from pd_tool.render import render

PREVIEW_SUFFIXES = (".mp4", ".gif")
MP4_QUALITY = 8  # 0-10 (10 = best), imageio-ffmpeg's scale: crf = (1 - q / 10) * 51; 8 keeps splat edges crisp
_STDERR_KEEP = 8192  # bytes of the encoder's error output kept for the message


class PreviewError(PdToolError):
    """A preview path has an unsupported extension, or frames are unusable."""


class PreviewEncoderMissing(PreviewError):
    """An .mp4 was asked for, but the ffmpeg binary of imageio-ffmpeg is not there."""


def ffmpeg_exe() -> str:
    """The ffmpeg binary of the imageio-ffmpeg wheel (ImportError / RuntimeError when absent)."""
    import imageio_ffmpeg

    return imageio_ffmpeg.get_ffmpeg_exe()


class _EncoderFailed(Exception):
    """ffmpeg stopped with an error (its message, one line)."""


class _Mp4Encoder:
    """H.264 .mp4 through a pipe to ffmpeg: frames [H, W, 3] uint8 (even sizes) go in one
    at a time; close() checks that ffmpeg finished cleanly."""

    def __init__(self, path: Path, width: int, height: int, fps: float, shown: Path) -> None:
        try:
            exe = ffmpeg_exe()
        except (ImportError, RuntimeError) as e:
            raise PreviewEncoderMissing(
                f"{shown}: .mp4 previews need the imageio-ffmpeg package (pip install imageio-ffmpeg); "
                "or write a .gif preview") from e
        rate = Fraction(float(fps)).limit_denominator(1001)
        cmd = [exe, "-nostdin", "-y", "-v", "error", "-f", "rawvideo", "-vcodec", "rawvideo", "-s",
               f"{width}x{height}", "-pix_fmt", "rgb24", "-r", str(rate), "-i", "pipe:0", "-an",
               "-vcodec", "libx264", "-pix_fmt", "yuv420p", "-crf", str(int((1 - MP4_QUALITY / 10) * 51)),
               "-metadata", f"comment={MARK_TEXT}", "-f", "mp4", str(path)]
        # -nostdin is for ffmpeg's keyboard commands; the frames come through pipe:0.
        # A session of its own: Ctrl-C reaches pdtool, which stops ffmpeg itself (abort()).
        self._p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.PIPE, start_new_session=True)
        self._err = bytearray()
        self._reader = threading.Thread(target=self._drain, daemon=True)
        self._reader.start()

    def _drain(self) -> None:
        for chunk in iter(lambda: self._p.stderr.read(4096), b""):
            self._err += chunk
            del self._err[:-_STDERR_KEEP]

    def _reap(self) -> None:
        """ffmpeg has exited: collect its error output and close the pipe."""
        self._reader.join(timeout=5)
        self._p.stderr.close()

    def _failure(self) -> _EncoderFailed:
        self._reap()
        lines = [ln.strip() for ln in self._err.decode("utf-8", "replace").splitlines() if ln.strip()]
        return _EncoderFailed(lines[-1][:200] if lines else f"ffmpeg exited with status {self._p.returncode}")

    def write(self, frame: np.ndarray) -> None:
        try:
            self._p.stdin.write(np.ascontiguousarray(frame).tobytes())
        except (BrokenPipeError, ValueError):  # ffmpeg is gone: its error output says why
            self._p.stdin = None
            self._p.wait()
            raise self._failure() from None

    def _end_input(self) -> None:
        # a pipe whose reader is gone cannot be flushed; the exit status says what happened
        try:
            if self._p.stdin is not None:
                self._p.stdin.close()
        except OSError:
            pass
        self._p.stdin = None
        self._p.wait()

    def close(self) -> None:
        self._end_input()
        if self._p.returncode != 0:
            raise self._failure()
        self._reap()

    def abort(self) -> None:
        if self._p.poll() is None:
            self._p.kill()
        self._end_input()
        self._reap()


def _as_frame(frame: np.ndarray, index: int, shape: tuple[int, ...] | None) -> np.ndarray:
    a = np.asarray(frame)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3:
        raise PreviewError(f"preview frame {index}: expected uint8 [H, W, 3], got {a.dtype} {list(a.shape)}; convert with (rgb.clamp(0, 1) * 255).round().byte()")
    if shape is not None and a.shape != shape:
        raise PreviewError(f"preview frame {index}: size {a.shape[1]}x{a.shape[0]} differs from frame 0 ({shape[1]}x{shape[0]}); render every frame with the same camera")
    return a


def _even(a: np.ndarray) -> np.ndarray:
    """Pad to even width and height (H.264 with yuv420p needs them) by repeating the edge."""
    ph, pw = a.shape[0] % 2, a.shape[1] % 2
    return np.pad(a, ((0, ph), (0, pw), (0, 0)), mode="edge") if ph or pw else a


def _encoder_error(path: Path, e: _EncoderFailed) -> PdToolError:
    """What an ffmpeg failure means: the destination's trouble when its message or the
    destination shows one (full, read-only...), else an encoder error."""

    text = str(e)
    mapped = output_error_in_text(path, text) or as_output_error(path, e)
    return mapped if mapped is not None else PreviewError(
        f"{path}: the mp4 encoder failed ({text}); write a .gif preview instead")


def write_preview(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 30.0, *,
                  own_only: bool = False) -> Path:
    """Write uint8 RGB frames [H, W, 3] as an .mp4 (H.264) or .gif at ``fps`` frames per second.

    Either plays len(frames) / fps seconds: the mp4 at a constant frame rate, the gif with
    per-frame delays that keep the total exact to its 10 ms unit (`gif_delays`), repeated
    frames (a held pose) included.

    Frames are consumed one at a time (mp4 streams; gif keeps them, as Pillow needs all).
    Odd sizes are padded by one pixel for mp4. Returns the path. Raises PreviewError for a
    wrong extension, an empty sequence, inconsistent frames or an encoder failure, and
    OutputError when the file cannot be written (full, read-only...). own_only: replace
    an existing file only when pdtool wrote it (a side output nobody named).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in PREVIEW_SUFFIXES:
        raise PreviewError(f"{path}: preview must end in .mp4 or .gif, not '{path.suffix}'")
    if not (np.isfinite(fps) and fps > 0):
        raise PreviewError(f"{path}: fps must be positive, got {fps}")

    shape = None
    n = 0
    with atomic_output(path, own_only=own_only, what="a preview video") as tmp:
        if suffix == ".mp4":
            enc = None
            try:
                for i, f in enumerate(frames):
                    a = _even(_as_frame(f, i, shape))
                    shape = np.asarray(f).shape
                    if enc is None:
                        enc = _Mp4Encoder(tmp, a.shape[1], a.shape[0], fps, path)
                    enc.write(a)
                    n += 1
                if enc is not None:
                    enc.close()
            except _EncoderFailed as e:
                raise _encoder_error(path, e) from None
            except BaseException:
                if enc is not None:
                    enc.abort()
                raise
        else:
            images = []
            for i, f in enumerate(frames):
                a = _as_frame(f, i, shape)
                shape = a.shape
                images.append(a)
            n = len(images)
            if n:
                from PIL import Image

                shown, delays = gif_delays(n, fps)
                pil = [Image.fromarray(images[i]) for i in shown]
                pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:],
                            duration=[10 * d for d in delays], loop=0, comment=MARK_TEXT.encode())
        if n == 0:
            raise PreviewError(f"{path}: no frames to write")
    return path


def gif_delays(n: int, fps: float) -> tuple[list[int], list[int]]:
    """Which of n frames a GIF shows and for how long, so that it plays n / fps seconds.

    GIF delays are whole hundredths of a second, and viewers stretch delays under 2 cs to
    10 cs. Frame i starts at round(100 i / fps) cs and the GIF ends at round(100 n / fps)
    cs, so the rounding never accumulates: the total is exact to 10 ms. Frames that would
    show for under 2 cs (fps over 50) are skipped; the frame before covers their time.
    Pillow sums the delays of identical consecutive frames (a held pose) when it merges
    them, which keeps the total, as the delays are whole centiseconds (Pillow truncates
    milliseconds to centiseconds per frame). Returns (frame indices, delays in cs).
    """
    end = round(100 * n / fps)
    shown: list[int] = []
    starts: list[int] = []
    for i in range(n):
        s = round(100 * i / fps)
        if not starts or s - starts[-1] >= 2:
            shown.append(i)
            starts.append(s)
    if len(starts) > 1 and end - starts[-1] < 2:  # a last sliver: the frame before holds on
        shown.pop()
        starts.pop()
    delays = [b - a for a, b in zip(starts, starts[1:] + [end])]
    delays[-1] = max(delays[-1], 2)  # a single frame shorter than 20 ms still shows for 20 ms
    return shown, delays


def write_preview_any(frames: list[np.ndarray], path: str | os.PathLike, fps: float = 30.0, *,
                      own_only: bool = False) -> Path:
    """write_preview to path (.mp4), or beside it as .gif when no mp4 encoder is installed:
    for previews that come with a longer job (a fit), which should not fail at its last
    step over a missing video codec. Returns the path written."""
    try:
        return write_preview(frames, path, fps, own_only=own_only)
    except PreviewEncoderMissing:
        return write_preview(frames, Path(path).with_suffix(".gif"), fps, own_only=own_only)


def save_png(path: str | os.PathLike, image: np.ndarray, *, own_only: bool = False,
             what: str = "an image") -> Path:
    """Write a uint8 [H, W, 3] (or [H, W, 4]) image as PNG, atomically, marked as pdtool's.
    Returns the path. own_only: replace an existing file only when pdtool wrote it;
    `what` names the image in that refusal."""
    from PIL import Image

    path = Path(path)
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] not in (3, 4):
        raise PreviewError(f"{path}: expected a uint8 [H, W, 3|4] image, got {a.dtype} {list(a.shape)}")
    with atomic_output(path, own_only=own_only, what=what) as tmp:
        Image.fromarray(a).save(tmp, format="PNG", pnginfo=png_info())
    return path


def to_uint8(rgb) -> np.ndarray:
    """float RGB in 0-1 (torch or numpy, [H, W, 3]) -> uint8 numpy [H, W, 3], rounded."""
    if hasattr(rgb, "detach"):
        rgb = rgb.detach().float().cpu().numpy()
    return (np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def render_animation_preview(
    frames: Iterable[Sequence],
    scales,
    opacities,
    sh,
    camera,
    path: str | os.PathLike,
    fps: float = 30.0,
    *,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    device: str | None = None,
) -> Path:
    """Render an animation of one scene and write it as a preview (.mp4 / .gif).

    frames: iterable of (means [N, 3], quats [N, 4] wxyz) per frame, or
        (means, quats, scales) when scales change; numpy or torch.
    scales [N, 3], opacities [N], sh [N, K, 3]: the scene's other activated values.
    camera: pd_tool.core.cameras.Camera (e.g. auto_camera(means of frame 0, 480, 270)).
    device: torch device to render on; None = the device of ``sh`` (cpu for numpy).
    Frames are rendered and encoded one at a time, so memory stays bounded for mp4.
    """
    import torch

    def t(x):
        return torch.as_tensor(x, dtype=torch.float32, device=dev)

    dev = torch.device(device) if device is not None else (sh.device if isinstance(sh, torch.Tensor) else torch.device("cpu"))
    sc, op, coeffs = t(scales), t(opacities), t(sh)

    def images():
        for fr in frames:
            frame_scales = t(fr[2]) if len(fr) > 2 else sc
            with torch.no_grad():
                out = render(t(fr[0]), t(fr[1]), frame_scales, op, coeffs, camera, background=background)
            yield to_uint8(out.rgb)

    return write_preview(images(), path, fps)
