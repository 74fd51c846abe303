"""Preview videos and images: atomic .mp4 / .gif / .png writers and an animation renderer.

Writers: imageio (already a dependency) with the ffmpeg binary that the imageio-ffmpeg
wheel ships (H.264 .mp4, no system ffmpeg needed) and Pillow for .gif / .png. Every file
is written to a temporary name beside the target and renamed, so a failed or interrupted
write leaves no half-written preview.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from pd_tool.errors import PdToolError

PREVIEW_SUFFIXES = (".mp4", ".gif")
MP4_QUALITY = 8  # imageio-ffmpeg quality 0-10 (10 = best); 8 keeps splat edges crisp


class PreviewError(PdToolError):
    """A preview path has an unsupported extension, or frames are unusable."""


class PreviewEncoderMissing(PreviewError):
    """An .mp4 was asked for, but imageio has no ffmpeg plugin (imageio-ffmpeg)."""


def _atomic(path: Path):
    """Write beside `path`, then rename into place (pd_tool.atomic)."""
    from pd_tool.atomic import atomic_output

    return atomic_output(path)


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


def write_preview(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 30.0) -> Path:
    """Write uint8 RGB frames [H, W, 3] as an .mp4 (H.264) or .gif at ``fps`` frames per second.

    Frames are consumed one at a time (mp4 streams; gif keeps them, as Pillow needs all).
    Odd sizes are padded by one pixel for mp4. Returns the path. Raises PreviewError for a
    wrong extension, an empty sequence or inconsistent frames.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in PREVIEW_SUFFIXES:
        raise PreviewError(f"{path}: preview must end in .mp4 or .gif, not '{path.suffix}'")
    if not fps > 0:
        raise PreviewError(f"{path}: fps must be positive, got {fps}")
    import imageio.v2 as iio2

    shape = None
    n = 0
    with _atomic(path) as tmp:
        if suffix == ".mp4":
            writer = None
            try:
                for i, f in enumerate(frames):
                    a = _as_frame(f, i, shape)
                    shape = a.shape
                    if writer is None:
                        try:
                            writer = iio2.get_writer(
                                tmp, format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
                                quality=MP4_QUALITY, pixelformat="yuv420p", macro_block_size=1,
                                ffmpeg_log_level="error",
                            )
                        except ImportError as e:  # imageio without its ffmpeg plugin
                            raise PreviewEncoderMissing(
                                f"{path}: .mp4 previews need the imageio-ffmpeg package "
                                "(pip install imageio-ffmpeg); or write a .gif preview") from e
                    writer.append_data(_even(a))
                    n += 1
            finally:
                if writer is not None:
                    writer.close()
        else:
            images = []
            for i, f in enumerate(frames):
                a = _as_frame(f, i, shape)
                shape = a.shape
                images.append(a)
            n = len(images)
            if n:
                from PIL import Image

                pil = [Image.fromarray(a) for a in images]
                # GIF delays are in 1/100 s units; Pillow takes milliseconds.
                pil[0].save(tmp, format="GIF", save_all=True, append_images=pil[1:],
                            duration=max(20, round(1000.0 / fps)), loop=0)
        if n == 0:
            raise PreviewError(f"{path}: no frames to write")
    return path


def write_preview_any(frames: list[np.ndarray], path: str | os.PathLike, fps: float = 30.0) -> Path:
    """write_preview to path (.mp4), or beside it as .gif when no mp4 encoder is installed:
    for previews that come with a longer job (a fit), which should not fail at its last
    step over a missing video codec. Returns the path written."""
    try:
        return write_preview(frames, path, fps)
    except PreviewEncoderMissing:
        return write_preview(frames, Path(path).with_suffix(".gif"), fps)


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write a uint8 [H, W, 3] (or [H, W, 4]) image as PNG, atomically. Returns the path."""
    from PIL import Image

    path = Path(path)
    a = np.asarray(image)
    if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] not in (3, 4):
        raise PreviewError(f"{path}: expected a uint8 [H, W, 3|4] image, got {a.dtype} {list(a.shape)}")
    with _atomic(path) as tmp:
        Image.fromarray(a).save(tmp, format="PNG")
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
    camera: pd_tool.cameras.Camera (e.g. auto_camera(means of frame 0, 480, 270)).
    device: torch device to render on; None = the device of ``sh`` (cpu for numpy).
    Frames are rendered and encoded one at a time, so memory stays bounded for mp4.
    """
    import torch

    from pd_tool.render import render

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
