"""A reference clip made ready for the fit: the frames it uses, and a still camera.

The fit simulates every frame of a clip from one fixed camera, frame 0 being the rest
state at the moment of the push. A phone video is longer, faster and shakier than that:

- **Which frames.** `choose_frames` starts at `start` (the last still frame before the
  motion), keeps every k-th frame so that the rate is at most `max_fps`, and stops after
  `max_frames`. The fit's time grows with the frames it simulates and compares.
- **A still camera.** `stabilise` measures each frame's camera motion against frame 0
  (pd_tool.video.camera_motion: a robust similarity fit of the whole frame, or of the
  static part where one is known) and, where it exceeds `STILL_PERCENT` of the long side,
  warps the frames back onto frame 0's view. The pixels a shaken frame did not see get a
  mask weight of 0, so the fit compares only what every kept frame shows. A similarity
  undoes a hand's small turns and shifts; the parallax of a camera that walks is beyond it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from pd_tool.core.errors import VideoError
from pd_tool.video.camera_motion import CameraMotion, align_size, estimate_camera_motion, to_gray, undo_motion
from pd_tool.video.folder import MIN_FRAMES, ReferenceVideo

if TYPE_CHECKING:
    from pd_tool.core.cameras import Camera
    from pd_tool.core.scene import GaussianScene

MAX_FRAMES = 30  # frames the fit uses by default: 1 s at 30 fps (the paper's clips: 14 frames)
MAX_FPS = 30.0  # frames per second above which frames are skipped
STILL_PERCENT = 0.5  # camera motion (% of the long side) under which a clip counts as still,
STILL_PX = 1.0  # or (px of the frames as the fit reads them) below which the fit could not see it
# Only the static scene shows the camera's motion. Where the part of frame 0 that the
# measurement weighs (outside the object) is nearly uniform (a rendered video's plain
# background), the camera's motion cannot be seen and the object's own motion would be
# taken for it: mean grey gradient there under TEXTURE_LEVEL a pixel, the clip is left as it is.
TEXTURE_LEVEL = 0.003
OBJECT_MARGIN = 0.05  # share of the long side the object's footprint is widened by (its motion)


@dataclass
class ClipChoice:
    """What was made of a clip: it had `source_frames` at `source_fps`; the fit uses
    `frames` of them from `start`, every `step`-th, at `fps`. camera_motion: the largest
    camera motion measured against frame 0, % of the long side (None: not measured, or the
    static scene too plain to show it); stabilised: the frames were warped back onto frame
    0's view."""

    source_frames: int
    source_fps: float
    start: int
    step: int
    frames: int
    fps: float
    camera_motion: float | None = None
    stabilised: bool = False

    @property
    def changed_frames(self) -> bool:
        return self.start != 0 or self.step != 1 or self.frames != self.source_frames

    def line(self, name: str) -> str | None:
        """One line for the user saying what was done, or None when the clip is used as it is."""
        parts = []
        if self.changed_frames:
            last = self.start + (self.frames - 1) * self.step
            every = "" if self.step == 1 else f", every {_ordinal(self.step)}"
            parts.append(f"{self.source_frames} frames at {self.source_fps:g} fps; the fit uses frames "
                         f"{self.start}-{last}{every}: {self.frames} frames at {self.fps:g} fps "
                         f"({(self.frames - 1) / self.fps:.2f} s; --start, --max-frames, --max-fps choose others)")
        if self.stabilised:
            parts.append(f"the camera moved up to {self.camera_motion:.1f}% of the frame; frames warped back onto "
                         f"frame 0's view, the one the camera file describes, the edges they did not see left out "
                         f"(--no-stabilise keeps them as they are)")
        return f"{name}: " + "; ".join(parts) if parts else None


def _ordinal(k: int) -> str:
    return {2: "2nd", 3: "3rd"}.get(k, f"{k}th")


def choose_frames(count: int, fps: float, *, start: int = 0, max_frames: int | None = MAX_FRAMES,
                  max_fps: float | None = MAX_FPS) -> tuple[list[int], float]:
    """The frames the fit uses of a clip of `count` frames at `fps`: from `start`, every
    k-th frame (k the smallest step that brings the rate to at most `max_fps`; None: every
    frame), at most `max_frames` of them (None: all). Returns (indices, the rate of the
    kept frames, frames/s). Raises VideoError when fewer than MIN_FRAMES remain."""
    if not 0 <= start < count:
        raise VideoError(f"--start {start}: the clip has frames 0-{count - 1}; give the frame where the object is "
                         f"still at rest just before the push")
    step = 1 if max_fps is None or fps <= max_fps else math.ceil(fps / max_fps - 1e-9)
    idx = list(range(start, count, step))
    if max_frames is not None:
        idx = idx[:max_frames]
    if len(idx) < MIN_FRAMES:
        raise VideoError(f"from frame {start}{f', every {_ordinal(step)}' if step > 1 else ''}, the clip leaves "
                         f"{len(idx)} frame(s); the fit needs at least {MIN_FRAMES}: give an earlier --start or a "
                         f"higher --max-fps")
    return idx, fps / step


def texture(frame: torch.Tensor, weight: np.ndarray | None = None) -> float:
    """Mean grey gradient magnitude (0-1 units a pixel) of frame [H, W, 3] at the alignment's
    resolution (`align_size`, where the camera motion is measured) after a 3 x 3 box blur
    (which takes pixel noise of 2/255 to about 0.002), weighted by `weight` [H, W] (None:
    everywhere): how much a shift of the camera would change the frame."""
    g = to_gray(frame.detach().cpu())[None, None]
    size = align_size(*g.shape[-2:])
    if size != tuple(g.shape[-2:]):
        g = F.interpolate(g, size=size, mode="area")
    g = F.avg_pool2d(g, 3, stride=1, padding=1, count_include_pad=False)[0, 0]
    gx = torch.zeros_like(g)
    gy = torch.zeros_like(g)
    gx[:, 1:-1] = 0.5 * (g[:, 2:] - g[:, :-2])
    gy[1:-1] = 0.5 * (g[2:] - g[:-2])
    mag = torch.sqrt(gx * gx + gy * gy)
    wt = torch.ones_like(g) if weight is None else torch.as_tensor(np.asarray(weight), dtype=torch.float32)
    if wt.shape != g.shape:
        wt = F.interpolate(wt[None, None], size=g.shape, mode="area")[0, 0]
    return float((mag * wt).sum() / wt.sum().clamp_min(1e-9))


def footprint(scene: GaussianScene, camera: Camera) -> np.ndarray:
    """alpha [H, W] (0-1) of `scene` rendered at rest from `camera`."""
    from pd_tool.render import render

    with torch.no_grad():
        out = render(scene.positions, scene.quats, scene.scales, scene.opacities, scene.sh, camera)
    return out.alpha[..., 0].clamp(0, 1).cpu().numpy()


def outside_object(alpha: np.ndarray, margin: float = OBJECT_MARGIN) -> np.ndarray:
    """The weight [H, W] of the static scene for the measurement: 1 outside the object's
    footprint (alpha [H, W] of a render of it at rest), widened by `margin` of the long side
    so that the object's own motion stays inside it."""
    a = torch.as_tensor(np.asarray(alpha), dtype=torch.float32)[None, None]
    r = max(1, round(margin * max(a.shape[-2:])))
    grown = F.max_pool2d((a > 0.05).float(), 2 * r + 1, stride=1, padding=r)[0, 0]
    return (1.0 - grown).numpy()


def stabilise(frames: torch.Tensor, masks: torch.Tensor | None, weight: np.ndarray | None = None,
              still_percent: float = STILL_PERCENT) -> tuple[torch.Tensor, torch.Tensor | None, CameraMotion | None, bool]:
    """Measure the camera motion of frames [T, H, W, 3] (0-1) against frame 0 and, where it
    exceeds `still_percent` of the long side and STILL_PX, warp them back onto frame 0's view.

    masks: [T, H, W] object masks or None. weight: [H, W] where the scene is static (1) or
    to be ignored (0) in the measurement; None: the whole frame, robustly. With masks, the
    part any of them marks is left out too. Returns (frames, masks, the measured motion (None where
    the weighed part of frame 0 is too plain to show it, `texture`), whether the frames
    were warped); warped masks are the given masks (or 1) times where the shaken frame saw
    the view.
    """
    cpu = frames.detach().to("cpu", torch.float32)
    if masks is not None:  # the object, wherever a mask marks it, is no part of the static scene
        outside = (1.0 - masks.detach().to("cpu", torch.float32).amax(0)).clamp(0, 1).numpy()
        weight = outside if weight is None else weight * outside
    if texture(cpu[0], weight) < TEXTURE_LEVEL:
        return frames, masks, None, False
    motion = estimate_camera_motion(cpu[0], cpu, weight)
    if motion.max_percent <= still_percent or motion.max_px <= STILL_PX:
        return frames, masks, motion, False
    if masks is not None:  # warped with the frames, as a fourth channel
        cpu = torch.cat([cpu, masks.detach().to("cpu", torch.float32)[..., None]], -1)
    warped, valid = undo_motion(cpu, motion)
    m = valid if masks is None else valid * warped[..., 3]
    return warped[..., :3].to(frames.device), m.to(frames.device), motion, True


def prepare_clip(video: ReferenceVideo, *, start: int = 0, max_frames: int | None = MAX_FRAMES,
                 max_fps: float | None = MAX_FPS, still: bool = True,
                 scene: GaussianScene | None = None) -> tuple[ReferenceVideo, ClipChoice]:
    """The video as the fit uses it: `choose_frames`, then (with `still`) `stabilise` onto
    frame 0's view (the one the video's camera describes, whatever `start` is), measured
    outside the object: outside its masks, or outside the footprint of `scene` (the
    GaussianScene the clip films, rendered at rest from the video's camera; None: the whole
    frame, robustly). Returns the new ReferenceVideo (same camera, the kept frames' rate)
    and what was done."""
    idx, fps = choose_frames(video.num_frames, video.fps, start=start, max_frames=max_frames, max_fps=max_fps)
    choice = ClipChoice(video.num_frames, video.fps, start, idx[1] - idx[0], len(idx), fps)
    frames = video.frames[idx]
    masks = None if video.masks is None else video.masks[idx]
    if still:
        weight = None if scene is None else outside_object(footprint(scene, video.camera))
        # onto frame 0's view, the one the clip's camera describes, whichever frame the fit starts at
        lead = 0 if start == 0 else 1
        if lead:
            frames = torch.cat([video.frames[:1], frames])
            masks = None if masks is None else torch.cat([video.masks[:1], masks])
        frames, masks, motion, warped = stabilise(frames, masks, weight)
        frames, masks = frames[lead:], None if masks is None else masks[lead:]
        choice.camera_motion, choice.stabilised = (None if motion is None else motion.max_percent), warped
    paths = video.frame_paths if len(video.frame_paths) != video.num_frames else [video.frame_paths[i] for i in idx]
    mask_paths = None if video.mask_paths is None else [video.mask_paths[i] for i in idx]
    out = dataclasses.replace(video, frames=frames, masks=masks, fps=float(fps), frame_paths=paths,
                              mask_paths=mask_paths)
    return out, choice
