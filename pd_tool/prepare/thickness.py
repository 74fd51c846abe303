"""How thick the moving parts of a prepared scene are, against the simulation's cell.

MPM has no degrees of freedom below a grid cell, so a leaf, petal or brim thinner than a
cell bends as if it were much thicker and moves too little (docs/simulator.md, "Thin
parts"). This module measures each particle's local thickness from the particles around it
and turns it into the one line that bake, fit and select print.

Thickness at a window of w cells: the particles within w cells around a particle (3x3x3
bins of w/3 cells, the particle's bin in the middle), their covariance, and
sqrt(12 * smallest eigenvalue). That is a slab's exact thickness, a filled window's edge,
and 0.87 of a rod's diameter.

A part is thin where it reads under RESOLVED_CELLS of a cell through two windows: one cell,
and a wide one of three cells but at most WIDE_SHARE of the object's size. The cell window
sees the part at the grid's scale. The wide one tells a sheet from the surface of a bulk
part, which a scan samples only on its outside and which reads as a sheet within one cell
but not within three; capped, it does not take in the other parts of the object (the stem
beside a leaf) on a coarse grid, where a cell is already a large share of the object.
Particles are weighted by their simulated volume. A coarse cell's window can still take in
more than the part, so the reading is an upper bound. The surface of a bulk part whose
radius of curvature exceeds about two cells reads as a sheet, filled or not (a known false
report: a ball ten cells wide).

Against bench/convergence.py (docs/benchmarks.md): at 16 cells every scene is reported,
and every one moves 36-84% too little; from 32 cells up udon, the donut and the tree are
not reported, and they move within 10% of the reference from 32 cells (udon and the tree)
or 48 (the donut); the plant with 3 mm leaves is reported at 16-96 cells (3-47% short) and
not at 128, where it moves within 2% of a 192-cell reference. A bake raises its grid to
ThinParts.grid_needed (pd_tool.prepare.preparation.refine_for_thin).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pd_tool.core.arrays import extent
from pd_tool.materials.presets import builtin
from pd_tool.prepare.cells import Device, neighbours, unique_rows

WINDOW_BINS = 3  # bins along a window's edge
WIDE_WINDOW = 3.0  # cells: the second window, which a bulk part's surface does not pass...
WIDE_SHARE = 0.15  # ...and at most this share of the object's longest side (never under a cell)
MIN_POINTS = 30  # fewer particles in a window: no estimate (the smallest eigenvalue of a
# covariance of a few points reads low: windows of about 10 in a solid stem read a third of a cell)
# A part is resolved when it is at least this many cells thick. The convergence benchmark's
# plant with 3 mm leaves moves within 2% of a converged simulation at 128 cells (0.29 of a
# cell) and 3-7% too little at 96 and 64 (0.2, 0.13); in a 2D MLS-MPM a strip of two
# particle layers was about 20% too stiff at a quarter cell (../shared/docs/thin-parts.md).
# The figure comes from that plant; the benchmark's 1.2 cm strip, 0.46 of a cell thick at
# default and not raised, reads 0.96 of its reference's peak and 0.95 of beam theory's
# first swing. Recheck it as more thin scenes are measured.
RESOLVED_CELLS = 0.25
THIN_SHARE = 0.05  # a notice when at least this share of the moving particles is thin
MAX_GRID = 256  # the largest grid the CLI accepts
SAMPLE = 100_000  # particles the estimate looks at (a random subset beyond; 0.2 s on one CPU core)


# Moments a window sums, packed per bin: count, weight, weighted sums of the 3 coordinates
# and of their 6 distinct products (xx, yy, zz, xy, xz, yz), about the bin's own corner.
_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _shifted(m: Tensor, o: tuple[int, int, int]) -> Tensor:
    """Packed moments m [K, 11] (int64, fixed point) about a corner moved by -o (positions
    y = x + o): s' = s + W o, q'_ab = q_ab + s_a o_b + o_a s_b + W o_a o_b."""
    out = m.clone()
    w = m[:, 1]
    for a in range(3):
        out[:, 2 + a] += w * o[a]
    for k, (a, b) in enumerate(_PAIRS):
        out[:, 5 + k] += m[:, 2 + a] * o[b] + o[a] * m[:, 2 + b] + w * (o[a] * o[b])
    return out


def _window_moments(x: Tensor, w: Tensor, h: float) -> tuple[Tensor, Tensor]:
    """Per occupied bin of edge h: the packed moments [M, 11] (_PAIRS) of the particles in
    the 3x3x3 bins around it, positions in units of h about its own corner (so that the
    covariance does not cancel at large coordinates), as float64; and each particle's bin
    [N]. Every particle of a bin sees the same window. x [N, 3], w [N] (> 0): positions and
    weights, float64 on one device.

    The sums are 64-bit fixed point (weights scaled to at most 1, coordinates within a bin
    in [0, 1)), so they are exact and the same in any order: on every device, every run."""
    n = len(x)
    bits = min(40, 58 - math.ceil(math.log2(max(n, 2))))  # a window's sums stay below 2^62
    scale = float(1 << bits)
    keys = torch.floor(x / h)
    local = x / h - keys
    cells, inverse, _, _ = unique_rows(keys.long())
    wn = w / w.max()
    cols = [wn] + [wn * local[:, a] for a in range(3)] + [wn * local[:, a] * local[:, b] for a, b in _PAIRS]
    fixed = torch.cat([torch.ones(n, 1, dtype=torch.int64, device=x.device),
                       torch.round(torch.stack(cols, 1) * scale).long()], 1)
    own = torch.zeros((len(cells), 11), dtype=torch.int64, device=x.device).index_add_(0, inverse, fixed)
    win = torch.zeros_like(own)
    half = WINDOW_BINS // 2
    offsets = [(a - half, b - half, c - half) for a in range(WINDOW_BINS) for b in range(WINDOW_BINS)
               for c in range(WINDOW_BINS)]
    for o, (i, j) in zip(offsets, neighbours(cells, offsets)):
        win[i] += _shifted(own[j], o)
    return win.double(), inverse


def smallest_eigenvalue(cov: Tensor) -> Tensor:
    """The smallest eigenvalue [K] of symmetric 3x3 matrices cov [K, 3, 3], in closed form
    (the trigonometric solution of the characteristic cubic). torch.linalg.eigvalsh on a
    GPU takes 13 GB of workspace for a 300k scene's windows; this takes a few [K]
    temporaries.
    Its error is about machine epsilon times the largest eigenvalue, and up to its square
    root (1e-8) times it where the two smallest nearly coincide (a needle): under 1e-3 of a
    window's bin in thickness, far below what RESOLVED_CELLS tells apart."""
    a00, a11, a22 = cov[:, 0, 0], cov[:, 1, 1], cov[:, 2, 2]
    a01, a02, a12 = cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 2]
    q = (a00 + a11 + a22) / 3.0
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p = torch.sqrt((b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * p1) / 6.0)
    safe = torch.where(p > 0, p, torch.ones_like(p))
    # det(B) / 2 of B = (A - q I) / p, whose eigenvalues are 2 cos(phi + 2 pi k / 3)
    det = (b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02) + a02 * (a01 * a12 - b11 * a02))
    r = (det / (2.0 * safe ** 3)).clamp(-1.0, 1.0)
    phi = torch.acos(r) / 3.0
    return torch.where(p > 0, q + 2.0 * p * torch.cos(phi + 2.0 * math.pi / 3.0), q)


def local_thickness(positions: np.ndarray, window: float, weights: np.ndarray | None = None, *,
                    device: Device = "cpu") -> np.ndarray:
    """Local thickness [N] in metres of the part each particle lies in, seen through a window
    `window` metres wide; NaN where it holds fewer than MIN_POINTS particles.
    positions [N, 3] metres; weights [N] (> 0; default 1): the simulation's particle volumes,
    so that a filled inside, a few particles each holding a cell, counts for its volume
    against the many on the surface. Computed on `device`."""
    x = np.asarray(positions, np.float64)
    out = np.full(len(x), np.nan)
    if len(x) == 0 or not window > 0.0:
        return out
    xt = torch.as_tensor(np.ascontiguousarray(x), device=device)
    w = torch.ones(len(x), dtype=torch.float64, device=xt.device) if weights is None else \
        torch.as_tensor(np.asarray(weights, np.float64), device=xt.device)
    h = window / WINDOW_BINS
    win, inverse = _window_moments(xt, w, h)
    ok = win[:, 0] >= MIN_POINTS
    m = win[ok]
    n = m[:, 1]
    mean = m[:, 2:5] / n[:, None]
    cov = torch.empty((len(m), 3, 3), dtype=torch.float64, device=xt.device)
    for k, (a, b) in enumerate(_PAIRS):
        cov[:, a, b] = cov[:, b, a] = m[:, 5 + k] / n - mean[:, a] * mean[:, b]
    per_bin = torch.full((len(win),), math.nan, dtype=torch.float64, device=xt.device)
    per_bin[ok] = torch.sqrt(12.0 * smallest_eigenvalue(cov).clamp_min(0.0)) * h
    return per_bin[inverse].cpu().numpy()


def local_thickness_ref(positions: np.ndarray, window: float, weights: np.ndarray | None = None) -> np.ndarray:
    """Brute-force twin of local_thickness: each particle's window gathered explicitly."""
    x = np.asarray(positions, np.float64)
    w = np.ones(len(x)) if weights is None else np.asarray(weights, np.float64)
    keys = np.floor(x / (window / WINDOW_BINS)).astype(np.int64)
    out = np.full(len(x), np.nan)
    half = WINDOW_BINS // 2
    for i in range(len(x)):
        sel = np.all(np.abs(keys - keys[i]) <= half, axis=1)
        if sel.sum() < MIN_POINTS:
            continue
        cov = np.cov(x[sel].T, aweights=w[sel], bias=True)
        out[i] = math.sqrt(12.0 * max(float(np.linalg.eigvalsh(cov)[0]), 0.0))
    return out


@dataclass(frozen=True)
class ThinParts:
    """What local_thickness says about a scene's moving particles at one cell size.

    share: fraction of the moving particles that are thin (thinner than RESOLVED_CELLS
    cells through both windows); thickness_m: their median thickness through one cell;
    dx_m: the cell; grid_needed: cells along the longest side that would resolve that median.
    """

    share: float
    thickness_m: float
    dx_m: float
    grid_needed: int

    @property
    def thin(self) -> bool:
        return self.share >= THIN_SHARE

    def found(self, grid_res: int, article: str) -> str:
        """What is thin, against `article` ("this", "the") `grid_res`-cell grid's cell:
        the start of every thin-parts line."""
        return (f"thin parts: {self.share:.0%} of the moving particles lie in parts {_length(self.thickness_m)} "
                f"thick or thinner, under a quarter of {article} {grid_res}-cell grid's {_length(self.dx_m)} cell")

    def line(self, grid_res: int) -> str:
        """The notice bake, fit and select print: what is thin, and the shipped quality (or
        the grid_res of a quality file) to try. A coarse cell's window can take in more than
        the part (the stem beside a leaf), so the thickness is an upper bound and the grid a
        lower one: a finer grid may report a thinner part again."""
        head = (self.found(grid_res, "this")
                + "; MPM bends them as if they were thicker, so they move too little")

        shipped = sorted((int(q["grid_res"]), name) for name, q in builtin("quality").items())
        if self.grid_needed > MAX_GRID:
            finest, name = shipped[-1]
            return head + (f"; resolving them needs {self.grid_needed} cells or more along the longest side, "
                           f"beyond the {MAX_GRID} pdtool allows (--quality {name}, {finest} cells, comes closest)")
        fits = [name for grid, name in shipped if grid >= self.grid_needed]
        if fits:
            return head + f"; try --quality {fits[0]} or finer"
        return head + f"; try a --quality file with grid_res = {self.grid_needed} or more"


def describe_refinement(coarse: ThinParts, grid_res: int, still: ThinParts | None, new_grid: int,
                        new_dx: float) -> str:
    """The line a bake prints when it raised its grid for thin parts: what was thin at
    `grid_res` (`coarse`), the grid it simulates on instead, and, when the parts are
    still thin there (`still`, the quality's ceiling), what would resolve them."""
    head = coarse.found(grid_res, "the") + f"; simulating on {new_grid} cells ({_length(new_dx)})"
    keep = f"--no-refine-thin keeps {grid_res}"
    if still is None:
        return head + f", which resolves them ({keep})"
    return (head + f", the most this quality allows; they are still thinner than that resolves and move too "
            f"little ({still.grid_needed} cells would: a finer --quality or a quality file; {keep})")


def _length(m: float) -> str:
    return f"{m * 1000:.2g} mm" if m < 0.01 else f"{m * 100:.2g} cm"


def thin_parts(positions: np.ndarray, moving: np.ndarray, dx: float, grid_res: int,
               volumes: np.ndarray | None = None, *, device: Device = "cpu") -> ThinParts | None:
    """ThinParts of the moving particles, or None when too few have an estimate.

    positions [N, 3] metres, moving [N] bool, dx metres, grid_res cells along the longest
    side of the simulation box (grid_res * dx is that side), volumes [N] m^3 (the weights);
    the windows are summed on `device`.
    """
    x = np.asarray(positions, np.float64)
    moving = np.asarray(moving, bool)
    vol = np.ones(len(x)) if volumes is None else np.asarray(volumes, np.float64)
    if len(x) > SAMPLE:
        # a fixed subset: the covariance of a window is unbiased under uniform thinning
        keep = np.random.default_rng(0).choice(len(x), SAMPLE, replace=False)
        x, moving, vol = x[keep], moving[keep], vol[keep]
    t, thin = _readings(x, moving, dx, vol, device)
    if np.isfinite(t).sum() < MIN_POINTS:
        return None
    thick = float(np.median(t[thin])) if thin.any() else float(np.nanmedian(t))
    needed = math.ceil(grid_res * dx / (max(thick, 1e-9) / RESOLVED_CELLS))
    return ThinParts(share=float(thin.mean()), thickness_m=thick, dx_m=dx, grid_needed=int(needed))


def _readings(x: np.ndarray, moving: np.ndarray, dx: float, vol: np.ndarray, device: Device) -> tuple[np.ndarray, np.ndarray]:
    """The moving particles' thickness through one cell's window [M] (NaN: too sparse) and
    whether each is thin [M]: under RESOLVED_CELLS of a cell through that window and the
    wide one (none where fewer than MIN_POINTS have a thickness). x [N, 3] metres, moving
    [N] bool (M of them), vol [N] weights."""
    t = local_thickness(x, dx, vol, device=device)[moving]
    if np.isfinite(t).sum() < MIN_POINTS:  # too few estimates to judge: the wide window is not read
        return t, np.zeros(len(t), bool)
    size = float(extent(x[moving]).max())
    wide = local_thickness(x, min(WIDE_WINDOW * dx, max(dx, WIDE_SHARE * size)), vol, device=device)[moving]
    # a particle whose window is too sparse to judge counts as not thin
    with np.errstate(invalid="ignore"):
        thin = (t < RESOLVED_CELLS * dx) & (wide < RESOLVED_CELLS * dx)
    return t, thin


def thin_mask(positions: np.ndarray, moving: np.ndarray, dx: float, volumes: np.ndarray | None = None, *,
              device: Device = "cpu") -> np.ndarray:
    """[N] bool: the moving particles that lie in thin parts, as ThinParts counts them
    (under RESOLVED_CELLS of a cell `dx` metres through both windows), every particle
    judged (thin_parts judges a sample of SAMPLE); False for static particles and where a
    window is too sparse. positions [N, 3] metres, moving [N] bool, volumes [N] m^3."""
    x = np.asarray(positions, np.float64)
    moving = np.asarray(moving, bool)
    vol = np.ones(len(x)) if volumes is None else np.asarray(volumes, np.float64)
    out = np.zeros(len(x), bool)
    out[moving] = _readings(x, moving, dx, vol, device)[1]
    return out
