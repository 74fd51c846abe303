"""Reference videos for fitting: a folder of frames (or one video file) plus its camera.

Folder layout (what `load_reference_video` reads and `write_video_folder` writes)::

    video/
      frame_0000.png ...     PNG or JPG frames, sorted naturally (frame2 before frame10);
                             OR one video file (.mp4; also .mov, .m4v, .webm, .mkv, .avi)
      camera.json            pdtool camera.json (pd_tool.core.cameras): intrinsics, world_to_camera, fps
      masks/                 optional: one PNG per frame, same size as the frames, in the same
                             natural order; white (1) = object, black (0) = ignore. A 1-channel
                             PNG is the mask itself, RGB takes the max of R, G, B, RGBA its alpha.

Frame 0 is the rest state (the frame the video model started from). An alpha channel in
the frames themselves is ignored (use masks/). Instead of camera.json, a camera file
(cameras.json, transforms.json, camera.json) and a view may be passed (`--camera FILE
--view ID`); it takes precedence over the folder's camera.json.
"""
from __future__ import annotations

import dataclasses
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pd_tool.core.atomic import atomic_output, path_kind
from pd_tool.core.cameras import Camera, load_cameras, save_camera_json, select_view
from pd_tool.core.errors import VideoError


FRAME_EXTS = (".png", ".jpg", ".jpeg")
VIDEO_EXTS = (".mp4", ".mov", ".m4v", ".webm", ".mkv", ".avi")  # read with imageio-ffmpeg
CAMERA_FILE = "camera.json"
MASK_DIR = "masks"
DEFAULT_FPS = 30.0  # frames per second when neither the caller nor camera.json nor the video says
DEFAULT_LONG_SIDE = 1024  # px, working resolution's long side (the authors' 576 x 1024)
MIN_FRAMES = 3  # frame 0 (rest) + the two frames stage 1 needs
ASPECT_TOL = 0.01  # relative; frame vs camera aspect ratio (rounding of odd sizes is ~0.2%)


@dataclass
class ReferenceVideo:
    """One reference video at the working resolution.

    frames: [T, H, W, 3] float32, linear 0-1 (the file's values / 255, no gamma change).
    masks: [T, H, W] float32 0-1 (soft at edges after resizing), or None.
    camera: the view, resized to W x H (intrinsics scaled, field of view kept).
    fps: frames per second of the video (time between frames is 1 / fps).
    folder: the video folder; frame_paths: the frame files in order (or [the video file]);
    mask_paths: the mask files in order, or None; camera_path: where the camera came from.
    native_size: (width, height) of the files before resizing.
    """

    frames: Tensor
    masks: Tensor | None
    camera: "Camera"
    fps: float
    folder: Path
    frame_paths: list[Path]
    mask_paths: list[Path] | None
    camera_path: Path
    native_size: tuple[int, int]

    @property
    def num_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def frame_dt(self) -> float:
        """Seconds between frames."""
        return 1.0 / self.fps


def natural_key(name: str) -> tuple:
    """Sort key with digit runs compared as numbers: frame2 < frame10; case-insensitive."""
    parts = re.split(r"(\d+)", name)
    # re.split alternates text (even index) and digits (odd index), so types line up
    return tuple(int(p) if i % 2 else p.lower() for i, p in enumerate(parts))


def _list_files(folder: Path, exts: Sequence[str]) -> list[Path]:
    """The frame (or video) files in `folder`, in natural order. A frame's index is its
    time, so anything that would shift later frames is refused: an entry with a frame's
    name that is not a file, and numbered names with a gap (a constant step is kept)."""
    named = [p for p in folder.iterdir() if p.suffix.lower() in exts and not p.name.startswith(".")]
    odd = [p for p in named if not p.is_file()]
    if odd:
        raise VideoError(f"{odd[0]}: has a frame's name but is {'a folder' if odd[0].is_dir() else 'not a file'}; "
                         f"every later frame would shift in time; remove or rename it")
    files = sorted(named, key=lambda p: natural_key(p.name))
    numbers = [re.findall(r"\d+", p.stem) for p in files]
    if len(files) > 2 and all(numbers):
        idx = [int(n[-1]) for n in numbers]
        steps = {b - a for a, b in zip(idx, idx[1:])}
        if len(steps) > 1:
            step = min(steps)
            at = next(i for i in range(1, len(idx)) if idx[i] - idx[i - 1] != step)
            raise VideoError(f"{folder}: frame numbers jump from {files[at - 1].name} to {files[at].name} (other "
                             f"frames step by {step}); a missing frame shifts every later one in time; "
                             f"export the frames again or renumber them evenly")
    return files


def _to_float_rgb(img: np.ndarray, path: Path) -> np.ndarray:
    """Decoded image -> [H, W, 3] float32 0-1 (gray repeated, alpha dropped)."""
    if img.dtype == np.uint8:
        f = img.astype(np.float32) / 255.0
    elif img.dtype in (np.uint16, np.int32, np.uint32):  # 16-bit PNG (Pillow may say "I")
        f = img.astype(np.float32) / 65535.0
    elif img.dtype == np.bool_:
        f = img.astype(np.float32)
    elif np.issubdtype(img.dtype, np.floating):
        f = np.clip(img.astype(np.float32), 0.0, 1.0)
    else:
        raise VideoError(f"{path}: unsupported pixel type {img.dtype}; save frames as 8- or 16-bit PNG or JPG")
    if f.ndim == 2:
        f = f[..., None]
    if f.ndim != 3 or f.shape[-1] not in (1, 2, 3, 4):
        raise VideoError(f"{path}: image of shape {img.shape} is not a 2D picture; save frames as RGB PNG or JPG")
    if f.shape[-1] in (1, 2):  # gray (+ alpha)
        f = np.repeat(f[..., :1], 3, axis=-1)
    return f[..., :3]


def _to_float_mask(img: np.ndarray, path: Path) -> np.ndarray:
    """Decoded mask -> [H, W] float32 0-1: 1 channel itself, RGB max, RGBA / LA alpha."""
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0, np.dtype(np.int32): 65535.0,
             np.dtype(np.uint32): 65535.0, np.dtype(np.bool_): 1.0}.get(img.dtype)
    if scale is None:
        raise VideoError(f"{path}: unsupported mask pixel type {img.dtype}; save masks as 8-bit grayscale PNG")
    f = img.astype(np.float32) / scale
    if f.ndim == 3:
        c = f.shape[-1]
        f = f[..., 0] if c == 1 else f[..., -1] if c in (2, 4) else f.max(axis=-1)
    if f.ndim != 2:
        raise VideoError(f"{path}: mask of shape {img.shape} is not a 2D picture; save masks as grayscale PNG")
    return f


def _why(e: Exception) -> str:
    """The first line of an exception, short: library messages can span pages."""
    first = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
    return f"{type(e).__name__}: {first[:80]}" if first else type(e).__name__


def _imread(path: Path) -> np.ndarray:
    import imageio.v3 as iio
    from PIL import Image

    try:
        # pillow only: PNG/JPG need nothing else, and a broken file then fails fast
        # instead of being offered to every imageio plugin in turn
        with warnings.catch_warnings():
            # Pillow only warns between 89 and 179 Mpx; a warning would print a second line
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            return np.asarray(iio.imread(path, plugin="pillow"))
    except Exception as e:  # imageio raises many types for broken files
        cause: BaseException | None = e
        for _ in range(8):  # imageio wraps Pillow's exception in an OSError (bounded: no cycles)
            if cause is None:
                break
            if isinstance(cause, (Image.DecompressionBombWarning, Image.DecompressionBombError)):
                raise VideoError(f"{path}: image header declares more than {Image.MAX_IMAGE_PIXELS:,} pixels (a "
                                 f"corrupt file, or far beyond a reference video's size); export frames at most 8K") from None
            cause = cause.__cause__ or cause.__context__
        raise VideoError(f"{path}: cannot read image ({_why(e)}); "
                         f"re-export it as PNG or JPG") from None


def _working_size(native: tuple[int, int], working_size: int | tuple[int, int] | None,
                  folder: Path) -> tuple[int, int]:
    w0, h0 = native
    if working_size is None:
        return native
    if isinstance(working_size, (int, np.integer)) and not isinstance(working_size, bool):
        long_side = int(working_size)
        if long_side < 8:
            raise VideoError(f"working size {long_side} px is too small; give a long side of at least 8 px (default {DEFAULT_LONG_SIDE})")
        s = long_side / max(w0, h0)
        if s >= 1.0:  # never upscale: more pixels, no more information
            return native
        return max(1, round(w0 * s)), max(1, round(h0 * s))
    try:
        w, h = (int(v) for v in working_size)
    except (TypeError, ValueError):
        raise VideoError(f"working size {working_size!r} must be a long side in px or (width, height)") from None
    if w < 8 or h < 8:
        raise VideoError(f"working size {w}x{h} is too small; give at least 8x8 px")
    if abs((w / h) / (w0 / h0) - 1.0) > ASPECT_TOL:
        raise VideoError(f"{folder}: working size {w}x{h} (aspect {w / h:.3f}) would stretch the {w0}x{h0} "
                         f"frames (aspect {w0 / h0:.3f}); give a size with the frames' aspect or a long side")
    return w, h


def _resize(img: Tensor, size: tuple[int, int]) -> Tensor:
    """[..., C, H, W] -> [..., C, h, w] with an antialiased bilinear filter (area-like when shrinking)."""
    w, h = size
    if img.shape[-1] == w and img.shape[-2] == h:
        return img
    lead = img.shape[:-3]
    x = img.reshape(-1, *img.shape[-3:])
    y = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return y.reshape(*lead, *y.shape[-3:]).clamp_(0.0, 1.0)


def _find_source(path: Path) -> tuple[Path, list[Path], Path | None]:
    """(folder, frame files, video file or None) for a folder or a video file."""
    if not path.exists():
        raise VideoError(f"{path}: video folder not found; pass a folder of PNG/JPG frames or one .mp4, with camera.json")
    if path.is_file():
        if path.suffix.lower() in VIDEO_EXTS:
            return path.parent, [], path
        raise VideoError(f"{path}: not a folder or a video file; pass the folder holding the frames and camera.json")
    if not path.is_dir():  # a pipe or a device
        raise VideoError(f"{path}: is not a regular file or a folder (a pipe or device?); pass the folder holding "
                         f"the frames and camera.json, or one .mp4")
    frames = _list_files(path, FRAME_EXTS)
    videos = _list_files(path, VIDEO_EXTS)
    if frames and videos:
        raise VideoError(f"{path}: holds both image frames ({frames[0].name}, ...) and a video ({videos[0].name}); "
                         f"keep one of them in the folder, or pass the video file itself")
    if len(videos) > 1:
        raise VideoError(f"{path}: holds {len(videos)} videos ({', '.join(v.name for v in videos[:3])}); "
                         f"keep one per folder (one folder per view)")
    if not frames and not videos:
        raise VideoError(f"{path}: no frames; put PNG/JPG frames (frame_0000.png, ...) or one .mp4 in the folder")
    return path, frames, (videos[0] if videos else None)


def _read_video_file(path: Path, size_fn) -> tuple[list[Tensor], tuple[int, int], float | None]:
    """Decode every frame of a video file, resizing as it streams (memory stays bounded)."""
    import imageio.v3 as iio

    frames: list[Tensor] = []
    native = None
    try:
        meta = iio.immeta(path, plugin="FFMPEG")
        for img in iio.imiter(path, plugin="FFMPEG"):
            rgb = _to_float_rgb(np.asarray(img), path)
            if native is None:
                native = (rgb.shape[1], rgb.shape[0])
                size = size_fn(native)
            frames.append(_resize(torch.from_numpy(rgb).permute(2, 0, 1), size))
    except VideoError:
        raise
    except Exception as e:
        raise VideoError(f"{path}: cannot decode video ({_why(e)}); "
                         f"re-encode it as H.264 .mp4 or export PNG frames") from None
    fps = meta.get("fps")
    fps = float(fps) if isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0 else None
    return frames, native or (0, 0), fps


def read_mask(path: Path, size: tuple[int, int], frames: str = "the frames are",
              fix: str = "export masks at the frames' size") -> np.ndarray:
    """[H, W] float32 0-1 object mask from an image that must be `size` (width, height) px,
    the size of the frames it masks. Raises VideoError naming `frames` and `fix` otherwise."""
    m = _to_float_mask(_imread(path), path)
    if (m.shape[1], m.shape[0]) != tuple(size):
        raise VideoError(f"{path}: mask is {m.shape[1]}x{m.shape[0]} but {frames} {size[0]}x{size[1]}; {fix}")
    return m


def has_camera(path: str | Path) -> bool:
    """Whether a video folder (or the folder of a video file) holds a camera.json.
    Raises VideoError as load_reference_video does for a missing or unusable source."""
    folder = _find_source(Path(path))[0]
    return (folder / CAMERA_FILE).is_file()


def read_first_frame(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, Path]:
    """The first frame of an image, a video file or a frame folder, with its mask.

    Returns (rgb [H, W, 3] float32 0-1, mask [H, W] float32 0-1 from the folder's masks/ or
    None, the file the frame came from). Raises VideoError as load_reference_video does."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() in FRAME_EXTS:
        return _to_float_rgb(_imread(path), path), None, path
    folder, frame_files, video_file = _find_source(path)
    if video_file is not None:
        import imageio.v3 as iio

        try:
            img = next(iter(iio.imiter(video_file, plugin="FFMPEG")))
        except StopIteration:
            raise VideoError(f"{video_file}: the video holds no frames; export it again") from None
        except Exception as e:
            raise VideoError(f"{video_file}: cannot decode video ({_why(e)}); "
                             f"re-encode it as H.264 .mp4 or export PNG frames") from None
        rgb, src = _to_float_rgb(np.asarray(img), video_file), video_file
    else:
        rgb, src = _to_float_rgb(_imread(frame_files[0]), frame_files[0]), frame_files[0]
    mask = None
    if (folder / MASK_DIR).is_dir():
        masks = _list_files(folder / MASK_DIR, FRAME_EXTS)
        if masks:
            mask = read_mask(masks[0], (rgb.shape[1], rgb.shape[0]), "the frame is")
    return rgb, mask, src


def _load_camera(folder: Path, camera_path: str | Path | None, view: int | str | None) -> tuple["Camera", Path]:
    if camera_path is not None:
        src = Path(camera_path)
    elif (folder / CAMERA_FILE).is_file():
        src = folder / CAMERA_FILE
    else:
        raise VideoError(f"{folder}: no {CAMERA_FILE}; add the camera the first frame was rendered with "
                         f"(pdtool render ... --write-camera {folder}) or pass --camera FILE --view ID")
    return select_view(load_cameras(src), view), src


def load_reference_video(
    folder: str | Path,
    *,
    camera_path: str | Path | None = None,
    view: int | str | None = None,
    fps: float | None = None,
    working_size: int | tuple[int, int] | None = DEFAULT_LONG_SIDE,
    device: str | torch.device = "cpu",
) -> ReferenceVideo:
    """Read a reference video folder (see the module docstring) at the working resolution.

    Args:
        folder: the video folder (or a video file; its folder is searched for camera.json
            and masks/).
        camera_path: camera file to use instead of folder/camera.json; view: its view
            (index or name; None = first).
        fps: frames per second; None -> camera.json's fps, else the video file's, else 30.
        working_size: long side in px (never upscales), or exact (width, height) with the
            frames' aspect ratio, or None for the files' own size. Default 1024.
        device: where the frame and mask tensors go.
    Returns:
        ReferenceVideo with frames [T, H, W, 3] and masks [T, H, W] (float32, 0-1) and the
        camera resized to W x H.
    Raises:
        VideoError: missing folder, no frames, both frames and a video, fewer than 3
            frames, frames of different sizes, an unreadable image, masks not matching the
            frames, no camera, or a camera whose aspect ratio is not the frames'.
        CameraError: a malformed camera file or unknown view (from pd_tool.core.cameras).
    """
    folder, frame_files, video_file = _find_source(Path(folder))
    # Camera first: a missing camera is found before decoding a large video.
    cam, cam_src = _load_camera(folder, camera_path, view)
    if not (0.0 < cam.cx < cam.width and 0.0 < cam.cy < cam.height):
        # intrinsics written for another image size (e.g. cx = 960 in a 512-px-wide camera):
        # the frames would be compared with a view of something else
        raise VideoError(f"{cam_src}: the camera's principal point ({cam.cx:g}, {cam.cy:g}) lies outside its "
                         f"{cam.width}x{cam.height} image, so its intrinsics are for another image size; use the "
                         f"camera the first frame was rendered with")
    if fps is not None and not (np.isfinite(fps) and fps > 0):
        raise VideoError(f"fps must be a positive number, got {fps}; pass e.g. --fps 30")

    state: dict = {}

    def size_fn(native: tuple[int, int]) -> tuple[int, int]:
        # called on the first frame, so a wrong camera is reported before the rest decodes
        w0, h0 = native
        if abs((w0 / h0) / (cam.width / cam.height) - 1.0) > ASPECT_TOL:
            raise VideoError(f"{folder}: frames are {w0}x{h0} (aspect {w0 / h0:.3f}) but the camera from {cam_src} "
                             f"is {cam.width}x{cam.height} (aspect {cam.width / cam.height:.3f}); use the camera "
                             f"the first frame was rendered with, or crop the frames to its aspect")
        state["size"] = _working_size(native, working_size, folder)
        return state["size"]

    video_fps = None
    if video_file is not None:
        frames, native, video_fps = _read_video_file(video_file, size_fn)
        sources = [video_file]
    else:
        frames, native = [], None
        for path in frame_files:
            rgb = _to_float_rgb(_imread(path), path)
            hw = (rgb.shape[1], rgb.shape[0])
            if native is None:
                native, size = hw, size_fn(hw)
            elif hw != native:
                raise VideoError(f"{path}: frame is {hw[0]}x{hw[1]} but {frame_files[0].name} is "
                                 f"{native[0]}x{native[1]}; export all frames at one size")
            frames.append(_resize(torch.from_numpy(rgb).permute(2, 0, 1), size))
        sources = list(frame_files)
    t = len(frames)
    if t < MIN_FRAMES:
        what = video_file if video_file is not None else folder
        raise VideoError(f"{what}: {t} frame(s); fitting needs at least {MIN_FRAMES} "
                         f"(frame 0 = rest state, then the motion); add frames")

    size = state["size"]

    masks, mask_files = None, None
    mask_dir = folder / MASK_DIR
    if mask_dir.is_dir():
        mask_files = _list_files(mask_dir, FRAME_EXTS)
        if len(mask_files) != t:
            raise VideoError(f"{mask_dir}: {len(mask_files)} mask(s) for {t} frames; give one PNG mask per "
                             f"frame (or remove {MASK_DIR}/ to fit on whole frames)")
        ms = []
        for path in mask_files:
            m = read_mask(path, native)
            ms.append(_resize(torch.from_numpy(m)[None], size)[0])
        masks = torch.stack(ms).to(device)

    if fps is None:
        fps = cam.fps if cam.fps is not None else video_fps if video_fps is not None else DEFAULT_FPS
    frames_t = torch.stack(frames).permute(0, 2, 3, 1).contiguous().to(device)
    return ReferenceVideo(
        frames=frames_t, masks=masks, camera=cam.resized(*size), fps=float(fps), folder=folder,
        frame_paths=sources, mask_paths=mask_files, camera_path=cam_src, native_size=native,
    )


def _as_uint8(a, name: str, ndim: int) -> np.ndarray:
    if isinstance(a, Tensor):
        a = a.detach().cpu().numpy()
    a = np.asarray(a)
    if a.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dims, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * 255
    if np.issubdtype(a.dtype, np.floating):
        return np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    raise ValueError(f"{name} must be uint8 (0-255), bool or float (0-1), got {a.dtype}")


def write_video_folder(
    folder: str | Path,
    frames,
    camera: "Camera",
    fps: float,
    *,
    masks=None,
    overwrite: bool = False,
    what: str | None = None,
) -> Path:
    """Write a reference video folder: frame_0000.png ..., camera.json (and masks/).

    The folder is built beside its destination and renamed into place, so a crash leaves
    no half-written video. It carries pdtool's manifest (pd_tool.core.atomic), so a later run
    may replace it; a folder that pdtool did not make is never replaced.

    Args:
        folder: destination folder.
        frames: [T, H, W, 3] uint8 (or float 0-1), numpy or torch; frame 0 = rest state.
        camera: the view the frames were rendered from; resized to W x H if its size
            differs with the same aspect ratio. fps is written into camera.json.
        fps: frames per second.
        masks: optional [T, H, W] uint8 / bool / float 0-1 -> masks/mask_0000.png ...
        overwrite: replace an existing folder that pdtool made, or an empty one
            (otherwise VideoError). A folder holding anything pdtool did not write is
            refused with OutputError either way.
        what: the option that named the folder (e.g. "--frames-out"), for messages.
    Returns:
        the folder path. Raises OutputError when the folder cannot be written.
    """
    import imageio.v3 as iio

    folder = Path(folder)
    if path_kind(folder) is not None and not overwrite:
        raise VideoError(f"{(what + ' ') if what else ''}{folder}: already exists; choose a new folder or delete it "
                         f"first")
    rgb = _as_uint8(frames, "frames", 4)
    if rgb.shape[-1] != 3:
        raise ValueError(f"frames must be [T, H, W, 3], got {rgb.shape}")
    t, h, w, _ = rgb.shape
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    m8 = None
    if masks is not None:
        m8 = _as_uint8(masks, "masks", 3)
        if m8.shape != (t, h, w):
            raise ValueError(f"masks must be [{t}, {h}, {w}] to match the frames, got {list(m8.shape)}")
    if (camera.width, camera.height) != (w, h):
        if abs((w / h) / (camera.width / camera.height) - 1.0) > ASPECT_TOL:
            raise ValueError(f"camera is {camera.width}x{camera.height} but frames are {w}x{h}: aspect ratios differ")
        camera = camera.resized(w, h)
    camera = dataclasses.replace(camera, fps=float(fps))
    digits = max(4, len(str(t - 1)))
    with atomic_output(folder, directory=True, what=what) as tmp:
        for i in range(t):
            iio.imwrite(tmp / f"frame_{i:0{digits}d}.png", rgb[i])
        if m8 is not None:
            (tmp / MASK_DIR).mkdir()
            for i in range(t):
                iio.imwrite(tmp / MASK_DIR / f"mask_{i:0{digits}d}.png", m8[i])
        save_camera_json(tmp / CAMERA_FILE, camera)
    return folder
