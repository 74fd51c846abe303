"""Find the camera of a frame in the splat's frame: a photometric pose and focal-length solve.

A handheld clip of the object shows it near the image centre, upright or nearly so.

1. Search: the object's centre seen from a ring of directions (azimuth x elevation about
   the scene's up axis), at a few distances (how much of the frame the object spans),
   rendered small from a subset of the Gaussians, each slid over the frame to its best
   place by FFT. No gradients.
2. Refine the best few by Adam on a blur pyramid: a turn about the object's centre, a
   move, the focal length and a dolly zoom. Gradients come through the rasteriser (the
   Gaussians are moved into the camera's frame in torch; the focal length through their
   camera-frame x, y and scales).

The loss (`_loss`) is a mean absolute difference per covered pixel after one gain per
colour channel (an exposure or white-balance change between the capture and the clip).
On a plain background, read from the frame's border (a render, a generated video), the
render composited over that colour is compared with the whole frame. Over clutter the
render is compared with the frame seen through its alpha, so the clutter around the
object costs nothing, and a mask of the object (given, or from its colours) makes the
object's pixels the render leaves uncovered count. Its value at the end, on the finest
level, is the residual a caller bounds.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from pd_tool.core.cameras import Camera, _UP
from pd_tool.core.quaternion import matrix_to_quat, quat_multiply
from pd_tool.core.scene import GaussianScene

SEARCH_GAUSSIANS = 20000  # the search renders at most this many (the most opaque, largest)
MAX_RESIDUAL = 0.06  # a registration whose residual is over this is refused (see docs/register.md)
GAIN_RANGE = (0.5, 2.0)  # per-channel exposure change allowed between the capture and the clip
MASK_BINS = 16  # colour histogram bins per channel for the colour mask
MASK_SHARE = 0.2  # share of the frame the object is taken to cover, for the colour mask
MASK_WEIGHT = 0.5  # the footprint's mismatch with the mask, against the colour error
SEARCH_REACH = 0.3  # the search slides each candidate this share of the frame each way
SEARCH_BLUR = 1.0  # px at the search's size: more lets a small render of the object match as well as the right one
BORDER = 0.03  # share of the shorter side: the frame's edge read for a plain background
PLAIN_TOLERANCE = 0.04  # colour 0-1: a plain background's pixels are this close to its median
PLAIN_SHARE = 0.9  # the share of the border that must be that close
MIN_COVER = 0.02  # share of the frame the render must cover for a candidate to count


@dataclass
class RegisterSettings:
    """How hard the solve looks.

    work_side: long side (px) the frame is refined at (a smaller frame keeps its size);
    blurs: the refinement levels, coarse to fine, as the sigma (px) of the blur both images
    get, for a frame of work_side (scaled with a smaller one); iterations: Adam steps
    per level; rates: Adam's first step size per level (radians, distance fractions, log
    focal). search_side: long side (px) of the search renders. azimuths: directions per
    ring; elevations (degrees above the horizon); fills: the share of the frame's shorter
    side the object's bounding sphere spans at a candidate's distance. fov_y_deg: the
    vertical field of view the search assumes. keep: candidates refined at the first level.
    dolly_rate: Adam's step along the dolly zoom at every level (log focal): the perspective
    that tells the focal length from the distance shows only on the sharp levels, whose
    own rates are too small to travel far along it. supersample: the sharp levels render
    at up to this many times the working size (no more than the frame's own) and shrink
    the render as the frame was shrunk.
    """

    work_side: int = 320
    blurs: tuple[float, ...] = (16.0, 8.0, 4.0, 2.0, 1.0)
    iterations: tuple[int, ...] = (50, 40, 30, 25, 20)
    rates: tuple[float, ...] = (0.01, 0.005, 0.002, 0.001, 0.0005)
    search_side: int = 96
    azimuths: int = 18
    elevations: tuple[float, ...] = (-20.0, 0.0, 20.0, 40.0, 60.0, 80.0)
    fills: tuple[float, ...] = (0.5, 0.75, 1.05)
    fov_y_deg: float = 45.0
    keep: int = 8
    dolly_rate: float = 0.01
    supersample: float = 2.0
    up_axis: str = "z"


@dataclass
class Registration:
    """The found camera (at the frame's own size), the residual (mean absolute difference
    per covered pixel, 0-1 colour units, on the finest level), the share of the frame the
    render covers, the candidates searched and refined, seconds, and
    the loss after each refinement step."""

    camera: Camera
    residual: float
    coverage: float
    searched: int
    refined: int
    seconds: float
    losses: list[float] = field(default_factory=list)


def _resize_hw(img: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """[H, W, C] -> [h, w, C], antialiased bilinear."""
    x = img.permute(2, 0, 1)[None]
    y = F.interpolate(x, size=(h, w), mode="bilinear", align_corners=False, antialias=True)
    return y[0].permute(1, 2, 0).contiguous()


def _level_size(width: int, height: int, long_side: int) -> tuple[int, int]:
    s = min(1.0, long_side / max(width, height))
    return max(8, round(width * s)), max(8, round(height * s))


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """[H, W, C] blurred by a Gaussian of `sigma` px (separable, edges replicated)."""
    if sigma <= 0:
        return img
    r = max(1, int(math.ceil(3.0 * sigma)))
    k = torch.exp(-0.5 * (torch.arange(-r, r + 1, dtype=img.dtype, device=img.device) / sigma) ** 2)
    k = k / k.sum()
    c = img.shape[-1]
    x = img.permute(2, 0, 1)[None]
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    return x[0].permute(1, 2, 0)


def _pool2(img: torch.Tensor) -> torch.Tensor:
    """[2H, 2W, C] -> [H, W, C], the mean of each 2 x 2 block."""
    return F.avg_pool2d(img.permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0)


def _moved(w2c: np.ndarray, w: torch.Tensor, t: torch.Tensor, pivot: torch.Tensor | None = None) -> np.ndarray:
    """[4, 4] world-to-camera: `w2c` turned by the rotation vector `w` about `pivot` (a point
    in w2c's camera frame, default its origin), then moved by `t` (camera frame)."""
    r = _rodrigues(w.detach().double().cpu()).numpy()
    p = np.zeros(3) if pivot is None else pivot.detach().double().cpu().numpy()
    delta = np.eye(4)
    delta[:3, :3] = r
    delta[:3, 3] = p - r @ p + t.detach().double().cpu().numpy()
    return delta @ w2c


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    """Rotation vector [3] -> [3, 3] rotation matrix (differentiable at 0)."""
    theta2 = (w * w).sum()
    k = torch.zeros(3, 3, dtype=w.dtype, device=w.device)
    k[0, 1], k[0, 2], k[1, 2] = -w[2], w[1], -w[0]
    k = k - k.T
    # sin(t)/t and (1 - cos(t))/t^2 by their series near 0
    small = theta2 < 1e-8
    t = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(t)) / (t * t))
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * k + b * (k @ k)


class _Splats:
    """The Gaussians as the rasteriser takes them, with a camera-frame move applied in torch."""

    def __init__(self, scene: GaussianScene, idx: torch.Tensor | None = None) -> None:
        take = (lambda t: t) if idx is None else (lambda t: t[idx])
        self.means = take(scene.positions).float()
        self.quats = F.normalize(take(scene.quats).float(), dim=-1)
        self.scales = take(scene.scales).float()
        self.opacities = take(scene.opacities).float()
        self.sh = take(scene.sh).float()

    def render(self, w2c: np.ndarray, w: torch.Tensor, t: torch.Tensor, cam: Camera,
               log_focal: torch.Tensor | None = None, pivot: torch.Tensor | None = None):
        """Render with camera `cam` whose pose is w2c's turned by Rodrigues(w) about `pivot`
        (a point in w2c's camera frame; None: the camera itself), then moved by t (camera
        frame): `_moved(w2c, w, t, pivot)`.

        log_focal: a [1] tensor whose gradient is wanted; `cam` already holds its focal
        length. The rasteriser does not differentiate the focal length, so the camera-frame
        x and y of the means and the scales are multiplied by exp(log_focal - its value), 1
        in value: a focal k times longer moves each mean's image and grows its footprint k
        times, as this does (to first order in the Gaussian's size over its depth)."""
        from pd_tool.render.api import render

        dev = self.means.device
        r0 = torch.as_tensor(w2c[:3, :3], dtype=torch.float32, device=dev)
        t0 = torch.as_tensor(w2c[:3, 3], dtype=torch.float32, device=dev)
        r = _rodrigues(w) @ r0
        p = torch.zeros(3, device=dev) if pivot is None else pivot
        means = self.means @ r.T + (_rodrigues(w) @ (t0 - p) + p + t)
        scales = self.scales
        if log_focal is not None:
            k = torch.exp(log_focal - log_focal.detach())
            means = means * torch.cat([k, k, torch.ones_like(k)])
            scales = scales * k
        q = matrix_to_quat(r[None])[0]
        quats = quat_multiply(q.expand_as(self.quats), self.quats)
        ident = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, np.eye(4))
        out = render(means, quats, scales, self.opacities, self.sh, ident)
        return out.rgb, out.alpha


def _loss(rgb: torch.Tensor, alpha: torch.Tensor, frame: torch.Tensor, sigma: float, mask: torch.Tensor | None,
          backdrop: torch.Tensor | None = None):
    """(loss, residual, coverage) of a render (premultiplied rgb [H, W, 3], alpha [H, W, 1])
    against `frame`, both blurred by `sigma` px, as the mean absolute difference per covered
    pixel after a gain per colour channel (an exposure or white-balance change).

    Over clutter (`backdrop` None) the render is compared with the frame seen through its
    alpha, so the frame outside its footprint does not count; with a mask, the footprint's
    mismatch with it is added. Over a plain `backdrop` colour [3] (a render's or a generated
    video's background) the render composited over that colour is compared with the whole
    frame, so an object pixel the render leaves uncovered costs as much as a covered one
    that is wrong: at the true camera the difference is only noise."""
    r = _blur(rgb, sigma)
    a = _blur(alpha, sigma)
    if backdrop is not None:
        f = _blur(frame, sigma)
        fo = f - (1.0 - a) * backdrop  # the object's share of the frame
        gain = ((fo * r).sum(dim=(0, 1)) / (r * r).sum(dim=(0, 1)).clamp_min(1e-8)).clamp(*GAIN_RANGE).detach()
        residual = (r * gain - fo).abs().sum() / (3.0 * a.detach().sum().clamp_min(1.0))
        return residual, residual, alpha.mean()
    af = _blur(alpha * frame, sigma)
    gain = ((af * r).sum(dim=(0, 1)) / (af * af).sum(dim=(0, 1)).clamp_min(1e-8)).clamp(*GAIN_RANGE).detach()
    residual = (r - af * gain).abs().sum() / (3.0 * a.sum().clamp_min(1.0))
    loss = residual
    if mask is not None:
        m = _blur(mask[..., None], sigma)
        loss = loss + MASK_WEIGHT * (a - m).abs().sum() / m.sum().clamp_min(1.0)
    return loss, residual, alpha.mean()


def plain_backdrop(frame: torch.Tensor) -> torch.Tensor | None:
    """The frame's background colour [3] when it is plain (a render's or a generated video's
    white or black), else None: the median of a border BORDER wide, when PLAIN_SHARE of the
    border lies within PLAIN_TOLERANCE of it in every channel."""
    h, w = frame.shape[:2]
    b = max(2, round(BORDER * min(h, w)))
    ring = torch.cat([frame[:b].reshape(-1, 3), frame[-b:].reshape(-1, 3),
                      frame[b:-b, :b].reshape(-1, 3), frame[b:-b, -b:].reshape(-1, 3)])
    colour = ring.median(dim=0).values
    near = ((ring - colour).abs().amax(dim=1) <= PLAIN_TOLERANCE).float().mean()
    return colour if float(near) >= PLAIN_SHARE else None


def backdrop_mask(frame: torch.Tensor, colour: torch.Tensor) -> torch.Tensor:
    """[H, W] 0-1: where `frame` differs from the plain background `colour`, ramping over
    one to three times PLAIN_TOLERANCE (the largest channel's difference)."""
    d = (frame - colour).abs().amax(dim=-1)
    return ((d - PLAIN_TOLERANCE) / (2.0 * PLAIN_TOLERANCE)).clamp(0.0, 1.0)


def colour_mask(object_rgb: torch.Tensor, object_alpha: torch.Tensor, frame: torch.Tensor,
                share: float = MASK_SHARE) -> torch.Tensor:
    """[H, W] the chance that each frame pixel shows the object, from colour alone: the
    object's colour histogram (renders of it, `object_rgb` [V, h, w, 3] premultiplied with
    `object_alpha` [V, h, w, 1]) against the frame's, by Bayes' rule with the object
    covering `share` of the frame. Background that shares the object's colours reads as
    object; the rest of the clutter reads as not."""
    bins = MASK_BINS

    def hist(rgb: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        q = (rgb.clamp(0.0, 1.0) * (bins - 1) + 0.5).long().reshape(-1, 3)
        idx = (q[:, 0] * bins + q[:, 1]) * bins + q[:, 2]
        h = torch.bincount(idx, weights=weight.reshape(-1).to(torch.float64), minlength=bins ** 3).float()
        h = h.reshape(1, 1, bins, bins, bins)
        h = F.avg_pool3d(F.pad(h, (1, 1, 1, 1, 1, 1), mode="replicate"), 3, stride=1)[0, 0]
        return h.reshape(-1) / h.sum().clamp_min(1e-12)

    solid = (object_alpha > 0.5).float()
    h_obj = hist(object_rgb / object_alpha.clamp_min(1e-3), solid)
    h_frame = hist(frame, torch.ones(frame.shape[:2], device=frame.device))
    q = (frame.clamp(0.0, 1.0) * (bins - 1) + 0.5).long()
    idx = (q[..., 0] * bins + q[..., 1]) * bins + q[..., 2]
    return (share * h_obj[idx] / h_frame[idx].clamp_min(1e-12)).clamp(0.0, 1.0)


def _shift_search(rgb: torch.Tensor, alpha: torch.Tensor, frame: torch.Tensor, mask: torch.Tensor, sigma: float,
                  reach: float) -> tuple[float, int, int]:
    """(best loss, dx, dy): the render slid over the frame by whole pixels (at most `reach` of
    the frame's size each way), scored as `_loss` scores it but squared: the blurred render
    against the blurred frame seen through the blurred alpha, per covered pixel, with the
    gain per channel that fits best at each shift. Sums over the shifts by FFT."""
    h, w = frame.shape[:2]
    ph, pw = 2 * h, 2 * w
    r = _blur(rgb, sigma)
    a = _blur(alpha, sigma)[..., 0]
    f = _blur(frame, sigma)
    cover = a.sum().clamp_min(1e-6)

    def corr(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        # out[s] = sum_p x[p] y[p + s] for shifts s, over zero padding
        return torch.fft.irfft2(torch.conj(torch.fft.rfft2(x, s=(ph, pw))) * torch.fft.rfft2(y, s=(ph, pw)), s=(ph, pw))

    sse = torch.zeros(ph, pw, dtype=frame.dtype, device=frame.device)
    for c in range(3):
        ra = corr(r[..., c] * a, f[..., c])  # sum r a f_s
        aa = corr(a * a, f[..., c] * f[..., c]).clamp_min(1e-9)  # sum a^2 f_s^2
        gain = (ra / aa).clamp(*GAIN_RANGE)
        sse = sse + (r[..., c] * r[..., c]).sum() - 2.0 * gain * ra + gain * gain * aa
    # the footprint against the mask: sum (a - m_s)^2 = sum a^2 + sum m^2 - 2 sum a m_s
    m = _blur(mask[..., None], sigma)[..., 0]
    mis = ((a * a).sum() + (m * m).sum() - 2.0 * corr(a, m)).clamp_min(0.0) / m.sum().clamp_min(1.0)
    score = (sse / (3.0 * cover)).clamp_min(0.0).sqrt() + MASK_WEIGHT * mis
    ry, rx = max(1, int(reach * h)), max(1, int(reach * w))
    ys = torch.cat([torch.arange(0, ry + 1), torch.arange(ph - ry, ph)]).to(score.device)
    xs = torch.cat([torch.arange(0, rx + 1), torch.arange(pw - rx, pw)]).to(score.device)
    sub = score[ys][:, xs]
    k = int(torch.argmin(sub))
    iy, ix = divmod(k, sub.shape[1])
    dy, dx = int(ys[iy]), int(xs[ix])
    dy = dy - ph if dy > ph // 2 else dy
    dx = dx - pw if dx > pw // 2 else dx
    return float(sub.reshape(-1)[k]), dx, dy


def _turn(dx: float, dy: float, f: float) -> np.ndarray:
    """[4, 4] camera-frame rotation that moves the image of the view's centre by (dx, dy) px."""
    w = torch.tensor([-math.atan(dy / f), math.atan(dx / f), 0.0], dtype=torch.float64)
    d = np.eye(4)
    d[:3, :3] = _rodrigues(w).numpy()
    return d


def _ring(center: np.ndarray, radius: float, up: np.ndarray, width: int, height: int,
          s: RegisterSettings, focal: float | None = None) -> list[tuple[np.ndarray, float]]:
    """Search candidates: (world_to_camera, focal in px at `height`) around the object, with
    the focal length `focal` or, when None, the one of s.fov_y_deg."""
    from pd_tool.core.cameras import look_at

    h1 = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(up, h1)
    f = focal if focal is not None else 0.5 * height / math.tan(0.5 * math.radians(s.fov_y_deg))
    out = []
    for el in s.elevations:
        for k in range(s.azimuths):
            az = 2.0 * math.pi * k / s.azimuths
            e = math.radians(el)
            d = math.cos(e) * (math.cos(az) * h1 + math.sin(az) * h2) + math.sin(e) * up
            # a view straight along up has no upright roll: tilt it a little off the axis
            if abs(float(d @ up)) > 0.999:
                d = d + 0.05 * h1
                d /= np.linalg.norm(d)
            for fill in s.fills:
                dist = 2.0 * radius * f / (fill * min(width, height))
                out.append((look_at(center + dist * d, center, up), f))
    return out


FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)


def focal_from_35mm(mm: float, width: int, height: int) -> float:
    """The focal length in px of a `width` x `height` frame from its 35 mm-equivalent focal
    length (mm), which phones report: the same diagonal field of view as that lens on a
    36 x 24 mm frame. A phone's main camera is about 24-28 mm."""
    return mm * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM


def object_bounds(positions: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre [3], radius) of the 1st-99th percentile box of the Gaussians' centres."""
    pts = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    return 0.5 * (lo + hi), max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)


def _object_colour_mask(splats: "_Splats", center: np.ndarray, radius: float, up: np.ndarray,
                        frame: torch.Tensor, s: RegisterSettings) -> torch.Tensor:
    """`colour_mask` of `frame` [h, w, 3] from six renders of the object around its up axis."""
    h, w = frame.shape[:2]
    ring = RegisterSettings(azimuths=6, elevations=(20.0,), fills=(0.75,), fov_y_deg=s.fov_y_deg)
    zero3 = torch.zeros(3, device=frame.device)
    rgbs, alphas = [], []
    with torch.no_grad():
        for w2c, f in _ring(center, radius, up, w, h, ring):
            rgb, alpha = splats.render(w2c, zero3, zero3, Camera(w, h, f, f, w / 2.0, h / 2.0))
            rgbs.append(rgb)
            alphas.append(alpha)
    return colour_mask(torch.stack(rgbs), torch.stack(alphas), frame)


def _search_subset(scene: GaussianScene, n: int) -> torch.Tensor | None:
    if scene.positions.shape[0] <= n:
        return None
    area = scene.scales.float().pow(2).sum(-1)
    return torch.topk(scene.opacities.float() * area, n).indices


def register_frame(scene: GaussianScene, frame: torch.Tensor, mask: torch.Tensor | None = None, *,
                   settings: RegisterSettings | None = None, start: Camera | None = None,
                   focal: float | None = None, progress: Callable[[str, int, int], None] | None = None) -> Registration:
    """Find the camera that sees `scene` as `frame` shows it.

    Args:
        scene: the splats (scene units); rendered on their device.
        frame: [H, W, 3] float32 0-1, the frame (any device; moved to the scene's).
        mask: [H, W] float 0-1 where the object is in the frame, or None (on a plain
            background what differs from it, else the object's colours).
        settings: RegisterSettings; up_axis names the scene's up ("z", "-y", ...).
        start: a camera near the answer to refine from instead of searching (any image
            size of the frame's aspect; its principal point is taken as the centre).
        focal: the focal length (px at the frame's size) when it is known (a phone's
            35 mm-equivalent focal length); it is then held, and only the pose is solved.
            None: searched from settings.fov_y_deg and refined.
        progress: called as (stage, done, total) with stage "search" or "refine".
    Returns:
        Registration with the camera at W x H (principal point at the image centre, square
        pixels) and the residual; the caller decides whether the residual is good enough.
    """
    s = settings or RegisterSettings()
    t_start = time.perf_counter()
    dev = scene.positions.device
    frame = frame.to(dev, torch.float32)
    height, width = int(frame.shape[0]), int(frame.shape[1])
    if mask is not None:
        mask = mask.to(dev, torch.float32)
    up = np.asarray(_UP[s.up_axis.lstrip("+") if s.up_axis.startswith("+") else s.up_axis], dtype=np.float64)
    center, radius = object_bounds(scene.positions.detach().cpu().numpy())

    # the working size: frames larger than the finest level are shrunk to it
    ww, wh = _level_size(width, height, s.work_side)
    wframe = _resize_hw(frame, wh, ww)
    full = _Splats(scene)
    backdrop = plain_backdrop(wframe)
    if mask is not None:
        wmask = _resize_hw(mask[..., None], wh, ww)[..., 0]
    elif backdrop is not None:  # a render's plain background: what differs from it is the object
        wmask = backdrop_mask(wframe, backdrop)
    else:  # no mask given: the object's colours tell where it may be
        wmask = _object_colour_mask(full, center, radius, up, wframe, s)

    known = focal is not None
    # 1. search: each candidate slid over the frame to its best place
    cands: list = []
    if start is not None:
        starts = [(start.world_to_camera.copy(), focal if known else start.fx * width / start.width)]
    else:
        sw, sh = _level_size(width, height, s.search_side)
        sframe = _resize_hw(frame, sh, sw)
        smask = _resize_hw(wmask[..., None], sh, sw)[..., 0]
        sub = _Splats(scene, _search_subset(scene, SEARCH_GAUSSIANS))
        cands = _ring(center, radius, up, width, height, s, focal)
        zero3 = torch.zeros(3, device=dev)
        scored = []
        with torch.no_grad():
            for i, (w2c, f) in enumerate(cands):
                # rendered at twice the size and pooled: a splat's small Gaussians alias at 96 px
                cam = Camera(2 * sw, 2 * sh, 2 * f * sw / width, 2 * f * sh / height, sw, sh)
                rgb, alpha = sub.render(w2c, zero3, zero3, cam)
                rgb, alpha = _pool2(rgb), _pool2(alpha)
                if float(alpha.mean()) >= MIN_COVER:
                    score, dx, dy = _shift_search(rgb, alpha, sframe, smask, SEARCH_BLUR, SEARCH_REACH)
                    # the shift in full-size pixels, as a turn of the camera
                    turned = _turn(dx * width / sw, dy * height / sh, f) @ w2c
                    scored.append((score, i, turned, f))
                if progress is not None:
                    progress("search", i + 1, len(cands))
        if not scored:
            scored = [(0.0, i, w2c, f) for i, (w2c, f) in enumerate(cands)]
        scored.sort(key=lambda c: c[0])
        starts = [(w2c, f) for _, _, w2c, f in scored[: s.keep]]

    # 2. refine: the best few on the most blurred level, the best of those on the others
    total = int(s.iterations[0]) * len(starts) + sum(int(n) for n in s.iterations[1:])
    done = [0]

    def _pivot(w2c: np.ndarray) -> torch.Tensor:
        # turning about the object's centre keeps its image in place, so that the view's
        # direction, which the image shows only through the object's own relief, is a
        # parameter of its own rather than the small difference of a turn and a move
        return torch.as_tensor(w2c[:3, :3] @ center + w2c[:3, 3], dtype=torch.float32, device=dev)

    def refine(w2c: np.ndarray, f0: float, lv: int, state=None):
        sigma = s.blurs[lv] * max(ww, wh) / s.work_side  # the blurs are set for a frame of work_side
        dist = float(np.linalg.norm(Camera(width, height, f0, f0, 0, 0, w2c).center - center))
        pivot = _pivot(w2c)
        if state is None:
            state = (torch.zeros(3, device=dev), torch.zeros(3, device=dev), 0.0)
        rot = state[0].clone().requires_grad_(True)
        tr_n = (state[1] / dist).clone().requires_grad_(True)  # translation in object distances
        logf = torch.tensor([state[2]], device=dev, requires_grad=True)
        # a dolly-zoom: the focal length and the distance scaled together, which changes only
        # the perspective; as its own parameter Adam steps along it as fast as along the rest
        dolly = torch.zeros(1, device=dev, requires_grad=True)
        groups = [{"params": [rot, tr_n]}]
        if not known:
            groups += [{"params": [logf]}, {"params": [dolly], "lr": max(s.rates[lv], s.dolly_rate)}]
        opt = torch.optim.Adam(groups, lr=s.rates[lv])
        n = int(s.iterations[lv])
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, n, eta_min=0.1 * s.rates[lv])
        hist = []
        z = torch.tensor([0.0, 0.0, 1.0], device=dev)

        # The frame was shrunk to the working size with an antialiasing filter; a render made
        # at that size instead draws each Gaussian at least a pixel wide, which makes the
        # object look nearer and blurs it (on udon at 320x240 the truth's residual is 0.039
        # rendered small, 0.014 rendered at 640x480 and shrunk, and only then is the truth
        # the best focal length along the dolly zoom). So the sharp levels render at up to
        # `supersample` times the size and shrink the render as the frame was shrunk.
        k = min(s.supersample, max(width / ww, 1.0)) if lv > 0 else 1.0
        rw, rh = round(ww * k), round(wh * k)

        def cam_at(lf: float) -> Camera:
            fk = f0 * math.exp(lf)
            return Camera(rw, rh, fk * rw / width, fk * rh / height, rw / 2.0, rh / 2.0)

        def pose():
            t = tr_n * dist + z * (torch.exp(dolly) - 1.0) * dist
            return rot, t, logf + dolly

        def loss_at(r, t, lf_t):
            rgb, alpha = full.render(w2c, r, t, cam_at(float(lf_t.detach())), lf_t, pivot)
            if (rw, rh) != (ww, wh):
                rgb, alpha = _resize_hw(rgb, wh, ww), _resize_hw(alpha, wh, ww)
            return _loss(rgb, alpha, wframe, sigma, wmask, backdrop)

        for _ in range(n):
            opt.zero_grad()
            loss = loss_at(*pose())[0]
            loss.backward()
            opt.step()
            sched.step()
            hist.append(float(loss.detach()))
            done[0] += 1
            if progress is not None:
                progress("refine", done[0], total)
        with torch.no_grad():
            final = tuple(v.detach().clone() for v in pose())
            end = loss_at(*final)
        return (final[0], final[1], float(final[2])), end, hist

    best = None
    for w2c, f in starts:
        state, end, hist = refine(w2c, f, 0)
        if best is None or float(end[0]) < float(best[2][0]):
            best = (w2c, f, end, state, hist)
    w2c, f, end, state, losses = best
    for lv in range(1, len(s.blurs)):
        state, end, h = refine(w2c, f, lv, state)
        losses += h

    rot, tr, lf = state
    fk = f * math.exp(float(lf))
    cam = Camera(width, height, fk, fk, width / 2.0, height / 2.0, _moved(w2c, rot, tr, _pivot(w2c)), name="registered")
    _, residual, cover = end
    return Registration(cam, float(residual), float(cover), len(cands),
                        len(starts), time.perf_counter() - t_start, losses)


def render_over(scene: GaussianScene, camera: Camera, frame: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(render of `scene` from `camera` composited over `frame`, alpha): [H, W, 3], [H, W, 1]."""
    splats = _Splats(scene)
    dev = scene.positions.device
    zero3 = torch.zeros(3, device=dev)
    with torch.no_grad():
        rgb, alpha = splats.render(camera.world_to_camera, zero3, zero3, camera)
    frame = frame.to(dev, torch.float32)
    return rgb + (1.0 - alpha) * frame, alpha


def side_by_side(scene: GaussianScene, camera: Camera, frame: torch.Tensor, long_side: int = 640) -> np.ndarray:
    """uint8 [h, 3 w, 3]: the frame, the render over it and their difference (x4), each at
    most `long_side` px: what a registration shows the user."""
    from pd_tool.render.preview import to_uint8

    w, h = _level_size(camera.width, camera.height, long_side)
    small = _resize_hw(frame.to(scene.positions.device, torch.float32), h, w)
    over, _ = render_over(scene, camera.resized(w, h), small)
    diff = ((over - small).abs() * 4.0).clamp(0.0, 1.0)
    return np.concatenate([to_uint8(small), to_uint8(over), to_uint8(diff)], axis=1)
