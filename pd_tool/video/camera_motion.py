"""How far the camera moved in a generated video: a global image alignment done in torch.

`pdtool fit` renders every frame from one fixed camera, so a reference video whose camera
drifts (a slow pan or zoom, which image-to-video models like to add) makes the fit explain
camera motion with object motion. This module measures that drift.

Each frame is aligned to the reference image (the render the video started from) with a
similarity transform (shift, zoom, roll) of the whole frame:

1. phase correlation (FFT) gives candidate shifts without a starting guess: one peak per
   coherently moving part (the static background, the moving object);
2. from each candidate and from "no motion", a few L-BFGS steps on a robust (Cauchy)
   photometric loss fit shift, zoom and roll; the Cauchy loss gives pixels that do not
   follow the fitted motion (the moving object) little weight, and the candidate with the
   lowest loss, the motion that explains most of the image, is the camera's.

The camera motion of a frame is how far the fitted similarity moves the image's corners,
in pixels of the frames (the largest of the four). Uniform regions (a white background)
carry no signal and cannot fool it; a textured static region (a pot, a table, a room)
anchors it.
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Iterator

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

ALIGN_LONG_SIDE = 256  # px; frames are aligned at this long side (fast, still sub-pixel after scaling back)
CAUCHY_SCALE = 0.05  # grey-level residual (0-1) where the robust loss starts to flatten
BLUR_SIGMA = 1.0  # px at the alignment size; widens the refinement's basin of convergence
REFINE_ITERS = 20  # L-BFGS iterations per starting guess
HYPOTHESES = 3  # correlation peaks tried per frame (plus "no motion")
MARGIN = 0.1  # fraction of each side left out of the alignment loss (room for the motion)
TAPER = 0.2  # fraction of each side under the cosine taper of the correlation window


@dataclass
class CameraMotion:
    """A video's camera motion relative to its reference image.

    shifts: [T, 2] float64 (dx, dy) px at the frames' size: the image content moved by
        this much (x right, y down). zooms: [T] scale factor (1 = none). rolls: [T] rad.
    displacement: [T] float64 px at the frames' size: the largest distance that one of
        the image's corners moved under the fitted similarity.
    long_side: the frames' long side, px.
    """

    shifts: np.ndarray
    zooms: np.ndarray
    rolls: np.ndarray
    displacement: np.ndarray
    long_side: int

    @property
    def max_px(self) -> float:
        """The largest corner displacement over the frames, px."""
        return float(self.displacement.max()) if len(self.displacement) else 0.0

    @property
    def max_percent(self) -> float:
        """max_px as a percentage of the frames' long side."""
        return 100.0 * self.max_px / self.long_side


def to_gray(images) -> Tensor:
    """uint8 / float 0-1 images [..., H, W, 3] (numpy or torch) -> float32 grey [..., H, W] in 0-1."""
    t = torch.as_tensor(np.asarray(images) if not isinstance(images, Tensor) else images)
    t = t.float() / 255.0 if t.dtype == torch.uint8 else t.float()
    if t.shape[-1] != 3:
        raise ValueError(f"expected RGB images [..., H, W, 3], got shape {list(t.shape)}")
    return t @ torch.tensor([0.299, 0.587, 0.114])


def _tukey2d(h: int, w: int, taper: float = TAPER) -> Tensor:
    # flat in the middle, cosine taper at the borders: the borders stop correlating as a
    # strong edge, and the image centre (where the moving object usually is) gets no more
    # weight than the static surroundings (a Hann window would favour the object)
    def tukey(n: int) -> Tensor:
        x = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
        a = taper / 2.0
        ramp = lambda t: 0.5 * (1 - torch.cos(math.pi * t / a))  # noqa: E731
        return torch.where(x < a, ramp(x), torch.where(x > 1 - a, ramp(1 - x), torch.ones_like(x)))

    return torch.outer(tukey(h), tukey(w))


def _parabola_peak(left: float, mid: float, right: float) -> float:
    # vertex of the parabola through (-1, left), (0, mid), (1, right): sub-pixel peak offset
    den = left - 2.0 * mid + right
    return 0.0 if abs(den) < 1e-12 else float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


def phase_correlation(reference: Tensor, image: Tensor, peaks: int = 1) -> list[tuple[float, float, float]]:
    """Global shifts between two grey images [H, W] by phase correlation.

    Returns the `peaks` strongest correlation peaks, strongest first, as (dx, dy, height):
    `image` is (a part of) `reference` moved by (dx, dy) px (x right, y down), sub-pixel by
    a parabola through the peak; height is the normalised correlation (about 1 for a pure
    shift of the whole image; a moving object and a static background give one peak each,
    in proportion to their area and texture). Shifts are found up to half the image size.
    """
    if reference.shape != image.shape or reference.ndim != 2:
        raise ValueError(f"expected two grey images of one size [H, W], got {list(reference.shape)} and "
                         f"{list(image.shape)}")
    h, w = reference.shape
    win = _tukey2d(h, w)
    a = (reference.double() - reference.double().mean()) * win
    b = (image.double() - image.double().mean()) * win
    cross = torch.fft.fft2(b) * torch.fft.fft2(a).conj()
    cross = cross / cross.abs().clamp_min(1e-12)
    corr = torch.fft.ifft2(cross).real
    # local maxima (3x3, wrapping) are the candidate shifts
    padded = torch.cat([corr[-1:], corr, corr[:1]], 0)
    padded = torch.cat([padded[:, -1:], padded, padded[:, :1]], 1)
    is_max = corr >= F.max_pool2d(padded[None, None], 3, stride=1)[0, 0]
    order = torch.argsort(torch.where(is_max, corr, torch.full_like(corr, -math.inf)).flatten(), descending=True)

    def at(y: int, x: int) -> float:
        return float(corr[y % h, x % w])

    out = []
    for flat in order[:peaks].tolist():
        iy, ix = divmod(flat, w)
        fx = _parabola_peak(at(iy, ix - 1), at(iy, ix), at(iy, ix + 1))
        fy = _parabola_peak(at(iy - 1, ix), at(iy, ix), at(iy + 1, ix))
        out.append(((ix if ix <= w // 2 else ix - w) + fx, (iy if iy <= h // 2 else iy - h) + fy, at(iy, ix)))
    return out


def _blur(img: Tensor, sigma: float) -> Tensor:
    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    t = img[None, None]
    t = F.conv2d(F.pad(t, (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
    t = F.conv2d(F.pad(t, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))
    return t[0, 0]


def _similarity_grid(q: Tensor, h: int, w: int) -> tuple[Tensor, Tensor]:
    """Where each reference pixel lands in the moved image, for parameters q.

    q = (tx, ty, zoom, roll), all in px at the image's corner radius r (zoom = r * log s,
    roll = r * angle), so that the four unknowns are equally scaled for the optimiser.
    Returns the sampling grid [1, H, W, 2] for grid_sample (align_corners=False) and the
    corner displacements [4] px.
    """
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    r = math.hypot(cx, cy)
    s = torch.exp(q[2] / r)
    ang = q[3] / r
    cos, sin = torch.cos(ang), torch.sin(ang)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=q.dtype), torch.arange(w, dtype=q.dtype), indexing="ij")
    px, py = xs - cx, ys - cy
    u = s * (cos * px - sin * py) + cx + q[0]
    v = s * (sin * px + cos * py) + cy + q[1]
    grid = torch.stack([(2 * u + 1) / w - 1, (2 * v + 1) / h - 1], -1)[None]
    corners = torch.tensor([[-cx, -cy], [cx, -cy], [-cx, cy], [cx, cy]], dtype=q.dtype)
    moved = torch.stack([s * (cos * corners[:, 0] - sin * corners[:, 1]) + q[0],
                         s * (sin * corners[:, 0] + cos * corners[:, 1]) + q[1]], -1)
    return grid, (moved - corners).norm(dim=-1)


def align_similarity(reference: Tensor, image: Tensor, shift: tuple[float, float] = (0.0, 0.0),
                     weight: Tensor | None = None, iters: int = REFINE_ITERS) -> tuple[Tensor, float, float]:
    """Refine the similarity that maps `reference` onto `image` (grey [H, W], 0-1).

    Minimises a Cauchy loss of image(A(y)) - reference(y) over the reference pixels y away
    from the border (MARGIN), weighted by `weight` [H, W] (1 = use, 0 = ignore; None = all),
    from the starting shift (dx, dy) px. Returns q = (dx, dy, zoom, roll) (see
    `_similarity_grid`; zoom and roll in px at the corner radius), the largest corner
    displacement, px, and the final loss (lower = more of the image explained).
    """
    h, w = reference.shape
    ref = _blur(reference.double(), BLUR_SIGMA)
    img = _blur(image.double(), BLUR_SIGMA)[None, None]
    # A fixed set of reference pixels: the central part, which stays inside the image for
    # motions up to MARGIN of its size (beyond, samples repeat the border). A mask of "pixels
    # still inside" would shrink as the motion grows and reward moving everything out.
    m = torch.ones_like(ref) if weight is None else weight.double().clone()
    my, mx = round(MARGIN * h), round(MARGIN * w)
    m[:my] = 0.0
    m[h - my:] = 0.0
    m[:, :mx] = 0.0
    m[:, w - mx:] = 0.0
    # q = bound * tanh(p / bound): each of shift, zoom and roll stays within half the corner
    # radius, so frames that match nothing (noise, a cut) cannot send the fit off to infinity
    bound = 0.5 * math.hypot((w - 1) / 2.0, (h - 1) / 2.0)
    q0 = torch.tensor([shift[0], shift[1], 0.0, 0.0], dtype=torch.float64).clamp(-0.95 * bound, 0.95 * bound)
    p = (bound * torch.atanh(q0 / bound)).requires_grad_(True)
    opt = torch.optim.LBFGS([p], lr=1.0, max_iter=iters, line_search_fn="strong_wolfe")

    def params(p: Tensor) -> Tensor:
        return bound * torch.tanh(p / bound)

    def loss_of(q: Tensor) -> Tensor:
        grid, _ = _similarity_grid(q, h, w)
        warped = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0]
        rho = torch.log1p(((warped - ref) / CAUCHY_SCALE) ** 2)
        return (m * rho).sum() / m.sum().clamp_min(1e-9)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = loss_of(params(p))
        loss.backward()
        return loss

    opt.step(closure)
    with torch.no_grad():
        q = params(p)
        loss = float(loss_of(q))
    _, disp = _similarity_grid(q, h, w)
    return q, float(disp.max()), loss


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    # The alignment is thousands of small ops on images of ~256 px. Several OpenMP threads
    # gain nothing there and, on a busy machine, spin at every op's barrier: one test ran
    # 2.5 s on one thread and 200 s on two threads of a loaded 2-core box.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def align_size(h: int, w: int, long_side: int = ALIGN_LONG_SIDE) -> tuple[int, int]:
    """(height, width) px at which frames of h x w are aligned: the long side at most
    `long_side` (never upscaled), at least 8 px each."""
    f = min(1.0, long_side / max(h, w))
    return max(8, round(h * f)), max(8, round(w * f))


def estimate_camera_motion(reference, frames, weight=None, long_side: int = ALIGN_LONG_SIDE) -> CameraMotion:
    """How far the camera moved in `frames` relative to `reference`.

    Args:
        reference: the image the video started from, [H, W, 3] uint8 (or float 0-1).
        frames: the video, [T, H, W, 3] uint8 (or float 0-1), numpy or torch.
        weight: optional [H, W] float, 1 where the scene is static (a pot, the table),
            0 to ignore; None uses the whole frame (robustly).
        long_side: alignment resolution's long side, px (frames are downscaled to it).
    Returns:
        CameraMotion with per-frame shift, zoom, roll and corner displacement in px of
        the frames' own size.
    """
    with _one_thread():
        return _estimate(reference, frames, weight, long_side)


def _estimate(reference, frames, weight, long_side: int) -> CameraMotion:
    ref = to_gray(reference)
    vid = to_gray(frames)
    if vid.ndim != 3 or ref.shape != vid.shape[1:]:
        raise ValueError(f"frames [T, H, W, 3] must match the reference [H, W, 3]: got {list(vid.shape)} "
                         f"and {list(ref.shape)}")
    h, w = ref.shape
    size = align_size(h, w, long_side)
    px = max(h, w) / max(size)  # frame px per alignment px

    def small(t: Tensor) -> Tensor:
        return t if size == (h, w) else F.interpolate(t[:, None], size=size, mode="area")[:, 0]

    ref_s, vid_s = small(ref[None])[0], small(vid)
    wgt = None if weight is None else small(torch.as_tensor(np.asarray(weight), dtype=torch.float32)[None])[0]
    shifts, zooms, rolls, disp = [], [], [], []
    r = math.hypot((size[1] - 1) / 2.0, (size[0] - 1) / 2.0)
    for frame in vid_s:
        # Candidate motions: none, and the strongest correlation peaks (the background's
        # and the object's). Each is refined; the one whose alignment explains the most
        # (weighted) pixels is the camera's.
        starts = [(0.0, 0.0)]
        for dx, dy, _ in phase_correlation(ref_s, frame, HYPOTHESES):
            if all(math.hypot(dx - x0, dy - y0) > 0.5 for x0, y0 in starts):
                starts.append((dx, dy))
        best = min((align_similarity(ref_s, frame, st, wgt) for st in starts), key=lambda res: res[2])
        q, d, _ = best
        shifts.append((float(q[0]) * px, float(q[1]) * px))
        zooms.append(math.exp(float(q[2]) / r))
        rolls.append(float(q[3]) / r)
        disp.append(d * px)
    return CameraMotion(np.array(shifts, np.float64).reshape(-1, 2), np.array(zooms), np.array(rolls),
                        np.array(disp, np.float64), max(h, w))


def undo_motion(frames: Tensor, motion: CameraMotion) -> tuple[Tensor, Tensor]:
    """Warp each frame back onto the reference's geometry: the inverse of its fitted motion.

    frames: [T, H, W, C] float, the frames `motion` was measured on (at any size with the
    same aspect: shifts scale with the long side). Returns (frames [T, H, W, C] with the
    motion undone, where each output pixel is the frame sampled where the reference pixel
    moved to; valid [T, H, W] float32, 1 where that sample lies inside the frame, 0 where
    the shaken frame did not see it).
    """
    t, h, w, _ = frames.shape
    scale = max(h, w) / motion.long_side
    r = math.hypot((w - 1) / 2.0, (h - 1) / 2.0)
    out, valid = [], []
    ones = torch.ones(1, 1, h, w, dtype=torch.float64)
    for k in range(t):
        q = torch.tensor([motion.shifts[k, 0] * scale, motion.shifts[k, 1] * scale,
                          r * math.log(motion.zooms[k]), r * motion.rolls[k]], dtype=torch.float64)
        grid, _ = _similarity_grid(q, h, w)
        img = frames[k].permute(2, 0, 1)[None].double()
        out.append(F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
                   .permute(1, 2, 0).to(frames.dtype))
        seen = F.grid_sample(ones, grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, 0]
        valid.append((seen > 0.999).float())
    return torch.stack(out), torch.stack(valid)
