"""A fit that cannot learn is refused, with one line that says why and what to change:
before any simulation when its videos or its scene leave the loss nothing to compare
(check_videos_can_teach, check_fit_can_learn), and after the fit, before anything is
written, when no loss history moved (check_learned).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pd_tool.core.errors import PdToolError
from pd_tool.fit.problem import FitProblem
from pd_tool.render import render
from pd_tool.video.folder import VIDEO_EXTS, ReferenceVideo


class FitLearnsNothing(PdToolError):
    """The fit's inputs cannot move its loss: nothing to see, nothing free to move, no motion."""


# Thresholds of the "learns nothing" checks. Frames and masks are read from 8-bit files, so
# half a level (0.5/255) is the finest difference they hold: a rendered change below it is
# not in the data.
_PIXEL_LEVEL = 0.5 / 255
# A reference video "shows no motion" when no pixel of any frame differs from frame 0 by more
# than this. Image frames are each stored on their own, so a still scene repeats frame 0 to
# within 8-bit rounding. A video file's codec adds noise to a still scene: libx264 on a
# still 256-px plant reached 3/255 at crf 18, 9/255 at crf 23 and 22/255 at crf 35. A swaying
# plant changes its edge pixels by far more: 60-200/255 in the tests' 24-32 px videos, over
# 200/255 at 256 px, in PNG frames and in mp4 at every crf tried.
_STILL_FRAMES = 4.0 / 255
_STILL_VIDEO_FILE = 32.0 / 255
# A video whose masks hold less than one whole pixel of weight over every compared frame
# leaves the loss nothing to compare (frame_loss gives 0 for an empty mask).
_MIN_MASK_PIXELS = 1.0
# After the fit: a loss history "did not move" when its spread is within this fraction of its
# size. Adam moves every parameter with a non-zero gradient by about its lr, which changes the
# loss by far more; a loss the parameters cannot reach stays the same bit for bit.
_FLAT_LOSS = 1e-6


def check_videos_can_teach(videos: list[ReferenceVideo]) -> None:
    """Refuse (FitLearnsNothing, one line) a reference video the fit cannot learn from,
    before any simulation: every mask of the compared frames (1 on) black, or no motion
    (no pixel, inside the masks, changes from frame 0 by more than a few 8-bit levels)."""
    for v in videos:
        frames = v.frames[1:]
        weight = None
        if v.masks is not None:
            weight = v.masks[1:]
            total = float(weight.sum())
            if total < _MIN_MASK_PIXELS:
                raise FitLearnsNothing(
                    f"{v.folder / 'masks'}: every mask of frames 1-{v.num_frames - 1} is black (no pixel marks "
                    f"the object), so the fit has nothing to compare; paint the object white in the masks, or "
                    f"remove masks/ to fit on whole frames")
        largest = 0.0
        for k in range(len(frames)):  # a frame at a time: no second copy of the whole video
            change = (frames[k] - v.frames[0]).abs().amax(dim=-1)  # [H, W], the largest channel change
            if weight is not None:
                change = change * (weight[k] > 0)
            largest = max(largest, float(change.max()))
        source = v.frame_paths[0] if len(v.frame_paths) == 1 and v.frame_paths[0].suffix.lower() in VIDEO_EXTS \
            else v.folder
        if largest <= (_STILL_VIDEO_FILE if source != v.folder else _STILL_FRAMES):
            where = " inside the masks" if weight is not None else ""
            raise FitLearnsNothing(
                f"{source}: no frame differs from frame 0 by more than {largest * 255:.1f}/255{where}, so the "
                f"video shows no motion to fit; pass a video of the object moving (frame 0 at rest)")


@torch.no_grad()
def check_fit_can_learn(pb: FitProblem) -> None:
    """Refuse (FitLearnsNothing, one line) a fit whose simulation cannot change what its
    videos compare, before any simulation: every particle static (bake refuses the same
    scene: nothing can move), or, per video, the moving Gaussians out of the camera's view
    (all behind it, or all outside the image) or changing no pixel of the rest frame inside
    the masks (hidden, masked out, transparent)."""
    if not (~pb.static).any():
        o = pb.prep.options
        region = " and ".join(f"--{k.replace('_', '-')} {getattr(o, k)}" for k in ("static_below", "static_box")
                              if getattr(o, k) is not None)
        raise FitLearnsNothing(f"every particle is static ({region or 'the static region'} pins all "
                               f"{len(pb.prep.static):,}), so nothing can move; shrink the static region "
                               f"(--static-below / --static-box)")
    p = pb.prep
    fg = torch.as_tensor(p.foreground, dtype=torch.long, device=pb.scene.positions.device)
    moving = fg[torch.as_tensor(~p.static[: len(p.foreground)], device=fg.device)]
    sc = pb.scene
    for v in pb.videos:
        cam = v.camera
        near = 0.01  # the rasteriser's near plane (pd_tool.render.render), world units
        with np.errstate(divide="ignore", invalid="ignore"):  # a centre on the camera's plane: u, v infinite
            uvz = torch.as_tensor(cam.project(sc.positions[moving].detach().double().cpu().numpy()))
        front = uvz[:, 2] > near
        # a Gaussian reaches 3 sigma past its centre on screen
        reach = 3.0 * sc.scales[moving].detach().double().cpu().amax(dim=1) * max(cam.fx, cam.fy) / uvz[:, 2].clamp_min(near)
        inside = front & (uvz[:, 0] + reach >= 0) & (uvz[:, 0] - reach <= cam.width) \
            & (uvz[:, 1] + reach >= 0) & (uvz[:, 1] - reach <= cam.height)
        what = f"{v.folder}: the moving part of the scene ({len(moving):,} Gaussians)"
        fix = (f"so the fit cannot see it move; use the camera frame 0 was seen with ({v.camera_path}), "
               f"or check the static region")
        if not front.any():
            raise FitLearnsNothing(f"{what} is behind the camera, {fix}")
        if not inside.any():
            raise FitLearnsNothing(f"{what} lies outside the camera's {cam.width}x{cam.height} image, {fix}")
        shown = render(sc.positions, sc.quats, sc.scales, sc.opacities, sc.sh, cam, background=pb.s.background).rgb
        opacity = sc.opacities.clone()
        opacity[moving] = 0.0
        hidden = render(sc.positions, sc.quats, sc.scales, opacity, sc.sh, cam, background=pb.s.background).rgb
        change = (shown - hidden).abs().amax(dim=-1)  # [H, W]
        if v.masks is not None:
            # SSIM compares 11-px windows (pd_tool.fit.losses), so a change up to 5 px outside
            # a mask still reaches the loss
            seen = (v.masks[1:] > 0).any(dim=0).float()[None, None]
            seen = torch.nn.functional.max_pool2d(seen, 11, stride=1, padding=5)[0, 0] > 0
            change = change * seen.to(change.device)
        if float(change.max()) <= _PIXEL_LEVEL:
            masked = " inside the masks" if v.masks is not None else ""
            raise FitLearnsNothing(f"{what} changes no pixel of the rest frame{masked} (hidden, masked out or "
                                   f"transparent), {fix}")


def check_learned(losses: dict[str, list[float]]) -> None:
    """After the fit, before anything is written: refuse (FitLearnsNothing) when every loss
    history of two or more iterations stayed flat, i.e. the videos gave the fit no gradient
    (E may still have moved, under the smoothness terms alone). `losses`: the run's loss
    histories by stage, one loss per iteration."""
    judged = {k: [x for x in losses[k] if math.isfinite(x)] for k in ("velocity", "material", "calibrate")
              if len(losses.get(k, [])) >= 2}
    if not judged:
        return  # one iteration per stage: a loss cannot be seen to move or not
    for h in judged.values():
        if len(h) >= 2 and max(h) - min(h) > _FLAT_LOSS * max(abs(x) for x in h):
            return
    k, h = max(judged.items(), key=lambda kv: len(losses[kv[0]]))
    at = f"stayed at {h[0]:.6g}" if h else "was NaN"
    raise FitLearnsNothing(
        f"the fit learned nothing: its {k} loss {at} over {len(losses[k])} iterations, so the videos do not "
        f"constrain the moving part (out of view, masked out or still); nothing was written; check the camera, "
        f"masks/ and the static region")
