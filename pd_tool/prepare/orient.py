"""Which way is up in a capture, and what the object stands on (behind `--up auto`,
`--static-below PCT%` and `--pin auto`).

A splat file carries no up axis: COLMAP captures are usually -y, Blender and synthetic
scenes +z, and nothing in the file says which. Two cues decide it:

* Support. An object in a capture rests on something, so with the true up axis the
  centre of its Gaussians lies above the footprint of its lowest slab (the 2-D convex
  hull of the bottom 5% of its height). For each of the six directions, the signed
  distance of the centre's projection from that footprint's edge (positive inside,
  as a fraction of the object's horizontal size) says how well the object would stand
  that way up. Lying on a branch tip or a leaf edge it would fall over.
* The unseen underside. Cameras orbit above the object, so its underside is seen by
  few views and its Gaussians grow larger (the donut capture's bottom fifth: 2.3 x the
  median size; its top: 0.33 x). This decides the sign where the two ends both carry the
  object (a plant's pot and flower disc are both wide).

The axis is the one whose better end stands best; the sign adds the two cues
(UNSEEN_WEIGHT). The guess is "sure" when both the axis and the sign win by their
margins (AXIS_MARGIN, SIGN_MARGIN). Measured in tests/prepare/test_orient.py: the three
shared captures (udon -y, donut +z, tree -y) and the synthetic plant in 20 variants
(5 seeds, normal and thin leaves, turned about up) in each of the six conventions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pd_tool.prepare.outliers import select_outliers

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
SUPPORT_SLAB = 0.05  # bottom fraction of the height whose footprint carries the object
UNDERSIDE_SLAB = 0.2  # bottom fraction of the height whose Gaussians' sizes are compared
UNSEEN_WEIGHT = 0.1  # support-margin units per e-fold of size ratio between the two ends
AXIS_MARGIN = 0.05  # the best axis stands this much (fraction of the size) better than the next
SIGN_MARGIN = 0.03  # the chosen end wins by this much
HULL_POINTS = 3000  # footprint points kept for the hull (evenly strided, deterministic)


DEFAULT_UP = "+z"  # what --up auto takes when the guess is not sure
MIN_GUESS_POINTS = 20


@dataclass(frozen=True)
class UpGuess:
    """The guessed up axis, whether the guess is sure, and what decided it."""

    axis: str  # one of UP_AXES
    sure: bool
    axis_gap: float  # how much better the axis stands than the next one, fraction of the size
    sign_gap: float  # how much better this end is as the bottom than the other
    scores: dict[str, float]  # direction -> support margin (positive: stands)

    def describe(self) -> str:
        how = "sure" if self.sure else "not sure"
        return (f"{self.axis} ({how}: the object stands on its {self._bottom()} end, axis margin "
                f"{self.axis_gap:.2f}, end margin {self.sign_gap:.2f})")

    def _bottom(self) -> str:
        other = {"+": "-", "-": "+"}[self.axis[0]] + self.axis[1]
        return f"{other[1]}-lowest ({other})"


def direction(up_axis: str) -> np.ndarray:
    """Unit vector [3] of '+x' ... '-z'."""
    v = np.zeros(3)
    v["xyz".index(up_axis[1])] = 1.0 if up_axis[0] == "+" else -1.0
    return v


def _hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise 2-D convex hull (Andrew's monotone chain) of points [N, 2]."""
    pts = np.unique(points, axis=0)
    if len(pts) < 3:
        return pts

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list = []
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _inside_margin(hull: np.ndarray, c: np.ndarray) -> float:
    """Signed distance of c from the edge of a counter-clockwise polygon (positive inside)."""
    if len(hull) < 3:
        return -float(np.min(np.linalg.norm(hull - c, axis=1))) if len(hull) else -np.inf
    e = np.roll(hull, -1, 0) - hull
    n = np.stack([e[:, 1], -e[:, 0]], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-300
    return -float(np.max(np.sum((c - hull) * n, 1)))


def _object(positions: np.ndarray, opacities: np.ndarray | None) -> np.ndarray:
    """Mask of the Gaussians that make the object: visible, not isolated floaters."""
    keep = np.ones(len(positions), bool) if opacities is None else np.asarray(opacities) >= 0.02
    if keep.sum() < 10:
        keep[:] = True
    idx = np.flatnonzero(keep)
    keep[idx[select_outliers(positions[idx])]] = False
    return keep


def guess_up(positions: np.ndarray, scales: np.ndarray | None = None,
             opacities: np.ndarray | None = None) -> UpGuess:
    """Guess the up axis of a scene from its Gaussians: positions [N, 3], scales [N, 3]
    (standard deviations), opacities [N] (0-1). See the module docstring."""
    pos = np.asarray(positions, np.float64)
    keep = _object(pos, opacities) if len(pos) else np.zeros(0, bool)
    p = pos[keep]
    if len(p) < MIN_GUESS_POINTS:  # too few Gaussians to show a base or an underside
        return UpGuess(DEFAULT_UP, False, 0.0, 0.0, {})
    size = None if scales is None else np.asarray(scales, np.float64)[keep].max(axis=1)
    lo, hi = np.quantile(p, 0.005, axis=0), np.quantile(p, 0.995, axis=0)
    ext = np.maximum(hi - lo, 1e-12)
    centre = p.mean(axis=0)
    support: dict[str, float] = {}
    unseen: dict[str, float] = {}
    for up in UP_AXES:
        a = "xyz".index(up[1])
        others = [b for b in range(3) if b != a]
        t = (p[:, a] - lo[a]) / ext[a] if up[0] == "+" else (hi[a] - p[:, a]) / ext[a]
        foot = p[(t < SUPPORT_SLAB) & (t > -0.02)][:, others]
        if len(foot) > HULL_POINTS:
            foot = foot[:: int(np.ceil(len(foot) / HULL_POINTS))]
        scale = float(np.linalg.norm(ext[others]))
        support[up] = _inside_margin(_hull(foot), centre[others]) / scale if len(foot) else -1.0
        if size is not None and (t < UNDERSIDE_SLAB).any():
            unseen[up] = float(np.log(max(np.median(size[t < UNDERSIDE_SLAB]), 1e-30) / max(np.median(size), 1e-30)))
        else:
            unseen[up] = 0.0
    axis_score = {ax: max(support["+" + ax], support["-" + ax]) for ax in "xyz"}
    ranked = sorted(axis_score, key=axis_score.get, reverse=True)
    ax = ranked[0]
    sign = (support["+" + ax] - support["-" + ax]) + UNSEEN_WEIGHT * (unseen["+" + ax] - unseen["-" + ax])
    axis = ("+" if sign >= 0 else "-") + ax
    axis_gap = axis_score[ax] - axis_score[ranked[1]]
    return UpGuess(axis, bool(axis_gap >= AXIS_MARGIN and abs(sign) >= SIGN_MARGIN), float(axis_gap),
                   float(abs(sign)), {k: round(v, 4) for k, v in support.items()})


def object_heights(positions: np.ndarray, up_axis: str, opacities: np.ndarray | None = None) -> tuple[float, float]:
    """(bottom, top): the object's lowest and highest coordinate along `up_axis` (a signed
    coordinate along that direction), floaters and invisible Gaussians left out."""
    h = np.asarray(positions, np.float64) @ direction(up_axis)
    keep = _object(np.asarray(positions, np.float64), opacities) if len(h) else np.zeros(0, bool)
    if not keep.any():  # every Gaussian an outlier (one or two of them): use them all
        keep = np.ones(len(h), bool)
    if not len(h):
        return 0.0, 0.0
    return float(h[keep].min()), float(h[keep].max())


# ----------------------------------------------------------------------------- pinning
BASE_BINS = 40  # height slabs of the width profile
NARROW = 0.6  # the base ends where the width drops below this fraction of the base's widest
BASE_MAX = 0.35  # a base is at most this fraction of the height (the plant's pot is 0.25, the
# tree's flared trunk 0.15; a narrowing higher up is the object's own shape, as on the udon)
CONTACT = 0.05  # without a narrowing, pin the contact slab: this fraction of the height


@dataclass(frozen=True)
class Base:
    """What --pin auto fixes: heights below `top` (a coordinate along up)."""

    top: float
    bottom: float
    kind: str  # "base" (below where the shape narrows) or "contact" (the lowest slab)
    narrow_to: float | None  # width above the cut / the base's widest, for a base


def find_base(heights: np.ndarray, horizontal: np.ndarray) -> Base:
    """The base an object stands on, from heights [N] along up and the other two
    coordinates [N, 2]: the part below where its width first drops under NARROW of the
    widest slab beneath (a pot under a stem, a trunk's flare), within the lower BASE_MAX of
    the height; without such a narrowing (a donut, a bowl), the contact slab, the lowest
    CONTACT of the height. Width: the 90th percentile distance from the slab's median."""
    bottom, top = float(heights.min()), float(heights.max())
    span = max(top - bottom, 1e-12)
    idx = np.minimum(((heights - bottom) / span * BASE_BINS).astype(int), BASE_BINS - 1)
    min_count = max(5, len(heights) // (BASE_BINS * 20))
    widest = 0.0
    for i in range(int(BASE_BINS * BASE_MAX) + 1):
        sel = idx == i
        if sel.sum() < min_count:
            continue  # a slab too sparse to measure says nothing about the width
        q = horizontal[sel]
        w = float(np.quantile(np.linalg.norm(q - np.median(q, axis=0), axis=1), 0.9))
        if widest > 0 and w < NARROW * widest and i >= 2:
            return Base(bottom + span * i / BASE_BINS, bottom, "base", w / widest)
        widest = max(widest, w)
    return Base(bottom + span * CONTACT, bottom, "contact", None)


def resolve_up(positions: np.ndarray, up_axis: str, scales: np.ndarray | None = None,
               opacities: np.ndarray | None = None) -> tuple[str, UpGuess | None]:
    """(the up axis to use, the guess behind it or None): `up_axis` itself unless "auto"."""
    if up_axis != "auto":
        return up_axis, None
    g = guess_up(positions, scales, opacities)
    # an unsure guess is no better than the convention most splat tools write
    return (g.axis if g.sure else DEFAULT_UP), g


def up_line(guess: UpGuess) -> str:
    """One line saying which axis --up auto took, and how to override it."""
    if guess.sure:
        return f"up axis {guess.axis}, guessed from the splats (--up auto; give --up to override)"
    return (f"up axis: took {DEFAULT_UP}, the default, as the guess from the splats ({guess.axis}, margins "
            f"{guess.axis_gap:.2f} axis, {guess.sign_gap:.2f} end) is not sure; if the render shows the object "
            f"on its side or upside down, give --up {guess.axis if guess.axis != DEFAULT_UP else '-y'} or "
            "another axis")
