"""Interior filling: extra simulation particles inside solid objects.

A 3D Gaussian scan is a shell. Simulated as it is, a solid object (a hat, a fruit, a thick
stem) moves like a hollow balloon: too light and too soft. `fill_interior` finds the
inside of the shell and places particles there on a regular lattice. Those particles are
simulated, never rendered.

Pipeline (all on a voxel grid in torch on the scan's device: voxels.py; memory and time
bounded):
1. density: opacity-weighted, unnormalised Gaussians alpha * exp(-d^T Sigma^-1 d / 2), cut
   at 3 sigma; scales clamped to [SIGMA_MIN_VOXELS voxels, SIGMA_MAX_CELLS cells] so that
   near-singular and absurd covariances neither vanish between voxels nor cost O(N * grid).
2. shell: density >= SHELL_THRESHOLD, then a morphological closing (one voxel) that seals
   pinholes.
3. inside: a 13-line sandwich vote: the fraction of the 13 lines through a voxel (axes,
   face and body diagonals) on which the shell lies on both sides. It is 0 outside a convex
   object, partial in concavities (a bowl, a torus hole), 1 inside a closed shell, and it
   survives holes that a flood fill would leak through. A shell band thicker than twice a
   typical Gaussian's 3-sigma half-width has a solid core (captures with Gaussians all
   through the volume); the core counts as enclosed too. Interior = voxels with vote >=
   VOTE_INTERIOR, in 6-connected components that do not touch the grid border.
4. surface: the shell band is split at its middle (fronts grown at once from the interior
   and from the outside), so the filled region is the solid enclosed by the surface, not
   the solid minus the band.
5. auto: `closedness` is the mean vote over the enclosed voxels (vote >= VOTE_CANDIDATE,
   border-free). Auto fills when it is >= AUTO_CLOSEDNESS and the interior holds at least
   MIN_INTERIOR_CELLS simulation cells.
6. sources: the nearest original Gaussian of each new particle, by jump flooding on a
   coarse grid followed by a local refinement (no O(N * M) search).

Volumes and masses are not set here: the preparation step moves the points onto its grid's
lattice with `resample_fill`, which gives each its share of `interior_volume`, and gives
each a mass density * volume.
Filled particles take part in K-Means driver selection like the Gaussians' centres.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from pd_tool.core.arrays import rows_all, rows_max, rows_min
from pd_tool.core.errors import PreparationError
from pd_tool.core.quaternion import quat_to_matrix_np
from pd_tool.prepare import voxels as vx
from pd_tool.prepare.cells import unique_cells

SHELL_THRESHOLD = 0.3  # summed alpha * Gaussian value (0-1 per Gaussian) that makes a voxel shell
SIGMA_MIN_VOXELS = 0.5  # smallest std-dev, in analysis voxels: a flat Gaussian still marks its voxel
SIGMA_MAX_CELLS = 1.0  # largest std-dev, in simulation cells or two voxels if larger (3-sigma support: 3 cells)
VOTE_CANDIDATE = 0.5  # line vote over which a voxel counts as enclosed at all (for closedness)
VOTE_INTERIOR = 11 / 13  # line vote over which a voxel is filled (2 of 13 lines may be open)
AUTO_CLOSEDNESS = 0.9  # auto fills when the mean vote over the enclosed voxels reaches this
PARTICLES_PER_CELL_AXIS = 2  # filled particles per cell along each axis: 8 per cell
MIN_INTERIOR_CELLS = 1.0  # auto skips interiors smaller than this many simulation cells
VOXEL_MIN_SCALES = 1.0  # analysis voxel at least this many median largest Gaussian std-devs
MAX_VOXELS = 1 << 22  # analysis grid cap (about 160^3); coarser voxels beyond it
MAX_SPLAT_WORK = 60_000_000  # Gaussian-voxel evaluations cap (~1 s compiled); coarser voxels beyond it
SPLAT_CHUNK = 2_000_000  # Gaussian-voxel evaluations per launch (deadline checks between) or torch batch
JFA_MAX_VOXELS = 1 << 15  # nearest-Gaussian search grid cap (32^3); points refine locally
BBOX_QUANTILE = 0.001  # robust bounding box: ignore this fraction of outliers per side


class FillError(PreparationError):
    """Interior filling was asked for (--fill on) but could not finish."""


class _OverBudget(Exception):
    """Internal: the time budget ran out in `stage`."""

    def __init__(self, stage: str) -> None:
        super().__init__(stage)
        self.stage = stage


class _Deadline:
    def __init__(self, budget_s: float) -> None:
        self.budget_s = budget_s
        self.t_end = time.perf_counter() + budget_s

    def check(self, stage: str) -> None:
        if time.perf_counter() > self.t_end:
            raise _OverBudget(stage)


@dataclass
class FillResult:
    """What `fill_interior` found and placed.

    Attributes:
        points: [M, 3] new interior particle positions, metres, same kind (numpy or torch,
            dtype, device) as the `positions` argument; M = 0 when not filled.
        source: [M] int64 index of the nearest original Gaussian of each new particle (copy
            its material and static flag).
        decision: True when particles were placed.
        closedness: 0-1 share of directions, seen from inside, that the shell covers
            (mean ray vote over the enclosed voxels); 0 for a flat sheet; nan for mode "off".
        reason: one line for the user.
        interior_volume: m^3 enclosed by the shell surface (the region the points fill).
        voxel: analysis voxel edge, metres (cell / particles_per_cell_axis unless coarsened).
    """

    points: np.ndarray | torch.Tensor
    source: np.ndarray | torch.Tensor
    decision: bool
    closedness: float
    reason: str
    interior_volume: float
    voxel: float = float("nan")


def fill_interior(
    positions: np.ndarray | torch.Tensor,
    quats: np.ndarray | torch.Tensor,
    scales: np.ndarray | torch.Tensor,
    opacities: np.ndarray | torch.Tensor,
    *,
    cell: float,
    mode: str = "auto",
    particles_per_cell_axis: int = PARTICLES_PER_CELL_AXIS,
    time_budget_s: float = 30.0,
    grid_origin: Sequence[float] | np.ndarray | None = None,
    device: str = "cpu",
) -> FillResult:
    """Find the inside of a Gaussian shell and place particles in it.

    Args:
        positions: [N, 3] Gaussian centres, metres (simulation coordinates).
        quats: [N, 4] rotations, (w, x, y, z), need not be unit.
        scales: [N, 3] linear standard deviations, metres.
        opacities: [N] in 0-1.
        cell: simulation grid spacing, metres.
        mode: "auto" (fill when the shell is closed enough), "on" (fill whatever interior is
            found), "off" (do nothing).
        particles_per_cell_axis: p; interior cells get p^3 particles on a regular lattice
            of spacing cell / p.
        time_budget_s: wall-clock bound, seconds. Past it, "auto" gives up (not filled) and
            "on" raises FillError.
        grid_origin: [3] a corner of the simulation grid, metres; pass it so that the
            lattice aligns with the grid and each interior cell holds exactly p^3 particles.
            Default: the lattice is aligned to multiples of `cell`.
        device: where the density splat and the grid passes run (warp's "cpu" or "cuda:N").
    Returns:
        FillResult; `points` are in the kind of `positions` (numpy, or torch on its device).
    Raises:
        PreparationError: bad arguments (shapes, cell, mode).
        FillError: mode "on" and the time budget ran out.
    """
    if mode not in ("auto", "on", "off"):
        raise PreparationError(f"fill mode {mode!r} is unknown; use auto, on or off")
    if not (isinstance(cell, (int, float)) and math.isfinite(cell) and cell > 0):
        raise PreparationError(f"fill cell size {cell!r} must be a positive number of metres")
    if int(particles_per_cell_axis) != particles_per_cell_axis or particles_per_cell_axis < 1:
        raise PreparationError(
            f"particles_per_cell_axis {particles_per_cell_axis!r} must be a whole number >= 1"
        )
    ppc = int(particles_per_cell_axis)
    pos, quat, scl, opa = _as_numpy(positions, quats, scales, opacities)
    if mode == "off":
        return _empty(positions, float("nan"), "not filled: interior filling is off (--fill off)", 0.0)
    deadline = _Deadline(float(time_budget_s))
    try:
        return _fill(pos, quat, scl, opa, positions, float(cell), mode, ppc, grid_origin, deadline, device)
    except _OverBudget as e:
        msg = (
            f"interior filling ran past its {time_budget_s:g} s time budget while {e.stage}; "
            "use a coarser grid or --fill off"
        )
        if mode == "on":
            raise FillError(msg) from None
        return _empty(positions, float("nan"), f"not filled: {msg}", 0.0)


def resample_fill(points: np.ndarray, source: np.ndarray, volume: float, spacing: float,
                  lattice: float, device: str | torch.device = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The filled particles `points` [M, 3] m (sources [M]; on a lattice of `spacing` m,
    filling `volume` m^3 in equal shares) moved onto a lattice of spacing `lattice` m, so
    that the interior is found once and sampled at any simulation grid's density. Onto a
    coarser lattice, the points in each of its cells merge into one at their centroid that
    carries their volume and the first one's source; onto a finer one, each point splits
    into k^3 (k = the ratio, rounded up) spread over its own lattice cell. Returns points [Q, 3], sources [Q] and
    volumes [Q] m^3, which sum to `volume`. Cells are grouped on `device`."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    source = np.asarray(source, np.int64)
    m = len(points)
    if m == 0:
        return points, source, np.zeros(0)
    share = volume / m
    if lattice >= spacing * (1 - 1e-9):
        _, inverse, counts, first = unique_cells(np.floor(points / lattice), index=True, device=device)
        centroid = np.stack([np.bincount(inverse, points[:, a]) for a in range(3)], 1) / counts[:, None]
        return centroid, source[first], counts * share
    k = int(math.ceil(spacing / lattice - 1e-9))
    offsets = (np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / k - 0.5
    split = (points[:, None, :] + offsets[None] * spacing).reshape(-1, 3)
    return split, np.repeat(source, k ** 3), np.full(m * k ** 3, share / k ** 3)


# ----------------------------------------------------------------------------- pipeline


def _fill(pos, quat, scl, opa, like, cell, mode, ppc, grid_origin, deadline, device="cpu") -> FillResult:
    keep = rows_all(np.isfinite(pos)) & np.isfinite(opa) & (opa > 0)
    if keep.sum() < 4:
        return _empty(like, 0.0, "not filled: fewer than 4 usable Gaussians", 0.0)
    lattice = cell / ppc
    origin = np.zeros(3) if grid_origin is None else np.asarray(grid_origin, np.float64).reshape(3)

    # Robust box: a few floaters far away must not blow up the grid.
    q = BBOX_QUANTILE if keep.sum() > 1000 else 0.0
    lo, hi = np.quantile(pos[keep], [q, 1 - q], axis=0)  # one partition for both
    span = np.maximum(hi - lo, cell)
    lo, hi = lo - 0.02 * span, hi + 0.02 * span
    keep &= rows_all((pos >= lo) & (pos <= hi))
    idx = np.nonzero(keep)[0]
    pos, quat, scl, opa = pos[idx], quat[idx], scl[idx], np.clip(opa[idx], 0.0, 1.0)

    scl = np.where(np.isfinite(scl), scl, 0.0)
    rot = quat_to_matrix_np(quat)
    grid = None
    # Voxels finer than a typical Gaussian see the gaps between a closed scan's Gaussians
    # as holes, and the decision would flip with the grid (the donut: 99% closed at 64
    # cells, 85% at 192). From there on, finer grids analyse the same voxels.
    finite = scl[rows_all(np.isfinite(scl))]
    floor = VOXEL_MIN_SCALES * float(np.median(rows_max(finite))) if len(finite) else 0.0
    k_min = max(1, int(math.ceil(floor / lattice - 1e-9)))
    # the voxel search and the grid passes run on the scan's device: at 300k Gaussians a
    # dozen passes over [N, 3, 3] or over millions of voxels each, which a GPU host's numpy
    # took seconds over
    tdev = torch.device(device)
    rot_t = torch.as_tensor(rot, device=tdev)
    rot2 = rot_t * rot_t
    scl_t = torch.as_tensor(scl, device=tdev)

    def sigmas(h: float) -> torch.Tensor:
        # the cap follows the voxel too, so that large Gaussians (a scan's underside) keep
        # closing the shell on a fine grid
        return scl_t.clamp(SIGMA_MIN_VOXELS * h, SIGMA_MAX_CELLS * max(cell, 2.0 * h))

    def sig_radius(h: float) -> tuple[torch.Tensor, torch.Tensor]:
        sig = sigmas(h)
        s2 = sig * sig
        # the diagonal of R S^2 R^T, summed in numpy's order
        cov_diag = (rot2[:, :, 0] * s2[:, None, 0] + rot2[:, :, 1] * s2[:, None, 1]) + rot2[:, :, 2] * s2[:, None, 2]
        # a sigma clipped to SIGMA_MIN_VOXELS lands on a whole number of voxels here, which float
        # rounding must not push up by one: the work would then rise with the voxel
        return sig, torch.ceil(3.0 * torch.sqrt(cov_diag) / h + 0.5 - 1e-9).long()  # [N, 3] voxels

    def light(k: int) -> bool:  # the splat's work is within MAX_SPLAT_WORK
        radius = sig_radius(lattice * k)[1]
        return float((2 * radius + 1).prod(1).sum()) <= MAX_SPLAT_WORK

    # Coarsen the analysis voxel until memory and work are bounded: the least k in
    # [k_min, k_min + 64) that passes both. Each sigma in voxels only shrinks as the voxel
    # grows, so the work does too, and its least passing k is found by bisection (a
    # million-Gaussian scan can need 60 coarser voxels, each an O(N) pass to check); the
    # voxel count costs nothing to check, so it is checked in order from there.
    first, stop = k_min, k_min + 64
    while first < stop:
        mid = (first + stop) // 2
        if light(mid):
            stop = mid
        else:
            first = mid + 1
    for k in range(first, k_min + 64):
        h = lattice * k
        pad = 3.0 * float(sigmas(h).max()) + 2.0 * h
        i0 = np.floor((lo - pad - origin) / h).astype(np.int64)
        i1 = np.ceil((hi + pad - origin) / h).astype(np.int64)
        shape = tuple(int(v) for v in (i1 - i0))
        if math.prod(shape) > MAX_VOXELS:
            continue
        sig, radius = sig_radius(h)
        grid = (k, h, i0, shape, sig, radius.cpu().numpy())
        break
    if grid is None:
        msg = (f"the object spans more than {MAX_VOXELS:,} fill voxels even at 64x the "
               f"{lattice:g} m lattice; remove far floaters (foreground selection) or use a coarser cell")
        if mode == "on":
            raise FillError(msg)
        return _empty(like, 0.0, f"not filled: {msg}", 0.0)
    k, h, i0, shape, sig, radius = grid
    corner = origin + i0 * h  # metres, low corner of voxel (0, 0, 0)

    dens = _splat_density((pos - corner) / h, rot_t, sig / h, opa, radius, shape, deadline, device)
    shell = vx.close(dens >= SHELL_THRESHOLD)
    deadline.check("closing the shell")

    votes = vx.ray_votes(shell, deadline.check)
    free = ~shell
    # A shell band thicker than two Gaussian half-widths has a solid core (a capture with
    # Gaussians all through its volume, like the donut): count that core as enclosed too.
    half_band = max(1, int(math.ceil(np.median(3.0 * rows_min(sig.cpu().numpy())) / h)))
    core = vx.deep(shell, 2 * half_band, deadline.check)
    open_ = free | core
    enclosed = vx.drop_border_components(open_ & (votes >= _lines(VOTE_CANDIDATE)), deadline.check)
    interior = vx.drop_border_components(open_ & (votes >= _lines(VOTE_INTERIOR)), deadline.check)
    any_enclosed = bool(enclosed.any())
    closedness = float(votes[enclosed].double().mean()) / vx.LINES if any_enclosed else 0.0
    # A flat sheet has no enclosed voxels at all (closedness 0); show its best vote instead
    # so that the user sees how far off it was.
    shown = closedness if any_enclosed else (float(votes[free].max()) / vx.LINES if bool(free.any()) else 0.0)
    solid = vx.grow_into_shell(interior, shell, deadline.check)
    n_solid = int(solid.sum())
    volume = float(n_solid) * h**3
    pct = f"shell {100 * shown:.0f}% closed"

    if mode == "auto" and closedness < AUTO_CLOSEDNESS:
        return _empty(like, closedness, f"not filled: open surface ({pct}; auto fills at "
                      f"{100 * AUTO_CLOSEDNESS:.0f}%)", volume, h)
    if n_solid == 0 or (mode == "auto" and volume < MIN_INTERIOR_CELLS * cell**3):
        return _empty(like, closedness, f"not filled: no enclosed interior found ({pct})",
                      0.0, h)

    vox = torch.nonzero(solid).cpu().numpy()  # [V, 3] analysis voxel indices
    sub = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)
    lat = (vox[:, None, :] * k + sub[None]).reshape(-1, 3)  # lattice indices from `corner`
    points = corner + (lat + 0.5) * lattice
    deadline.check("placing particles")
    source = idx[_nearest_source(points, pos, corner, h, shape, deadline, device)]
    reason = (f"filled {len(points):,} interior particles ({volume:.3g} m^3): {pct}")
    return FillResult(_like(points, like), _like_index(source, like), True, closedness, reason,
                      volume, h)


# ----------------------------------------------------------------------------- pieces


def _lines(share: float) -> int:
    """The least number of the 13 lines whose vote reaches `share`."""
    return math.ceil(share * vx.LINES - 1e-9)


def _splat_density(u, rot, sig_v, opa, radius, shape, deadline, device: str = "cpu") -> torch.Tensor:
    """Sum of alpha * exp(-m / 2) over Gaussians with Mahalanobis m <= 9, per voxel centre.

    u: [N, 3] centres in voxel units (voxel i spans [i, i + 1)); rot: [N, 3, 3]; sig_v: [N,
    3] std-devs in voxels (rot and sig_v float64, numpy or torch); radius: [N, 3] half box
    per axis in voxels (ints). Returns the
    float32 grid of `shape` (torch, on `device`). Launches `fill_kernels.splat_density` (one thread per
    Gaussian) in batches of about SPLAT_CHUNK evaluations, checking the deadline between.
    """
    import warp as wp

    from pd_tool.prepare import fill_kernels as K

    wp.config.quiet = True
    wp.init()
    tdev = torch.device(device)
    rot_t = torch.as_tensor(rot, device=tdev)
    sig_t = torch.as_tensor(sig_v, device=tdev)
    radius = (np.asarray(radius).reshape(len(u), -1) * np.ones((1, 3), np.int64)).astype(np.int32)
    work = np.cumsum(np.prod(2 * radius.astype(np.int64) + 1, axis=1))
    dens_t = torch.zeros(shape, dtype=torch.float32, device=tdev)
    dens = wp.from_torch(dens_t)
    # on CUDA the launches go on torch's stream, so that they run after the torch work that
    # made their inputs, and the grid passes after them
    stream = wp.stream_from_torch(tdev) if tdev.type == "cuda" else None
    # uploaded once; the launches take views of them
    u_w = wp.from_torch(torch.as_tensor(u, device=tdev).float().contiguous(), dtype=wp.vec3)
    opa_w = wp.from_torch(torch.as_tensor(opa, device=tdev).float().contiguous())
    radius_w = wp.from_torch(torch.as_tensor(radius, device=tdev), dtype=wp.vec3i)
    start = 0
    while start < len(u):
        deadline.check("splatting the density")
        done = work[start - 1] if start > 0 else 0
        stop = max(start + 1, int(np.searchsorted(work, done + SPLAT_CHUNK, side="right")))
        # R S^-2 R^T per launch: float64 [n, 3, 3] of all of a 10M-Gaussian scan at once
        # would hold gigabytes of the GPU
        r, sg = rot_t[start:stop], sig_t[start:stop]
        prec = ((r / (sg * sg)[:, None, :]) @ r.transpose(1, 2)).float().contiguous()
        wp.launch(K.splat_density, dim=stop - start, device=device, stream=stream, inputs=[
            u_w[start:stop], wp.from_torch(prec, dtype=wp.mat33), opa_w[start:stop], radius_w[start:stop], dens])
        start = stop
    return dens_t


def splat_density_ref(u, rot, sig_v, opa, radius, shape, deadline=None) -> np.ndarray:
    """Torch twin of `_splat_density` (batched over Gaussians with the same box)."""
    deadline = deadline or _Deadline(math.inf)
    n_vox = math.prod(shape)
    dens = torch.zeros(n_vox, dtype=torch.float32)
    prec = np.einsum("nij,nj,nkj->nik", rot, 1.0 / sig_v**2, rot)  # R S^-2 R^T, per voxel^2
    # m = d^T P d written out: six products beat a batched einsum over 3-vectors.
    pcoef = torch.from_numpy(np.stack([prec[:, 0, 0], prec[:, 1, 1], prec[:, 2, 2],
                                       2 * prec[:, 0, 1], 2 * prec[:, 0, 2],
                                       2 * prec[:, 1, 2]], 1).astype(np.float32))
    base_all = np.round(u - 0.5).astype(np.int64)  # nearest voxel centre (centres at i+0.5)
    frac = torch.from_numpy((base_all + 0.5 - u).astype(np.float32))  # centre - mean, voxels
    base_t = torch.from_numpy(base_all)
    opa_t = torch.from_numpy(opa.astype(np.float32))
    dims = torch.tensor(shape)
    strides = torch.tensor([shape[1] * shape[2], shape[2], 1])
    radius = np.asarray(radius).reshape(len(u), -1) * np.ones((1, 3), np.int64)
    keys, group, _ = unique_cells(radius)
    for gk, r in enumerate(keys):
        sel = torch.from_numpy(np.nonzero(group == gk)[0])
        axes = [torch.arange(-int(v), int(v) + 1) for v in r]
        off = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        offf = off.float()
        step = max(1, SPLAT_CHUNK // off.shape[0])
        for s in range(0, len(sel), step):
            deadline.check("splatting the density")
            g = sel[s:s + step]
            d = frac[g][:, None, :] + offf[None]  # [n, K, 3] voxel centre - mean
            c = pcoef[g][:, None, :]
            m = (c[..., 0] * d[..., 0] ** 2 + c[..., 1] * d[..., 1] ** 2
                 + c[..., 2] * d[..., 2] ** 2 + c[..., 3] * d[..., 0] * d[..., 1]
                 + c[..., 4] * d[..., 0] * d[..., 2] + c[..., 5] * d[..., 1] * d[..., 2])
            vox = base_t[g][:, None, :] + off[None]
            ok = (m <= 9.0) & ((vox >= 0) & (vox < dims)).all(-1)
            w = opa_t[g][:, None] * torch.exp(-0.5 * m)
            dens.index_add_(0, (vox[ok] * strides).sum(-1), w[ok])
    return dens.reshape(shape).numpy()


def _nearest_source(points, pos, corner, h, shape, deadline, device: str = "cpu") -> np.ndarray:
    """Index into `pos` of an approximately nearest Gaussian of each point.

    Jump flooding on a grid of at most JFA_MAX_VOXELS voxels (each voxel seeded with one
    Gaussian it contains: voxels.jump_flood), then each point takes the nearest of the
    seeds found in its voxel's 27 neighbours. The answer is at most about one coarse voxel
    diagonal farther than the true nearest; cost O(grid log grid + M), never O(N * M). Both
    run in torch on `device`.
    """
    c = 1
    while math.prod(-(-np.asarray(shape) // c)) > JFA_MAX_VOXELS:
        c += 1
    g = h * c
    dims = -(-np.asarray(shape) // c)
    gshape = tuple(int(v) for v in dims)
    gi = np.clip(np.floor((pos - corner) / g).astype(np.int64), 0, dims - 1)
    tdev = torch.device(device)
    seeds = torch.as_tensor(pos.astype(np.float32), device=tdev)
    lab = vx.jump_flood(seeds, torch.as_tensor(gi, device=tdev), gshape,
                        torch.as_tensor(corner, dtype=torch.float64), g, deadline.check)
    pts = points.astype(np.float32)
    pv = np.clip(np.floor((points - corner) / g).astype(np.int64), 0, dims - 1)
    return _refine_nearest_torch(pts, seeds, lab, pv, tdev, deadline)


def _refine_nearest_ref(pts, pos32, lab, pv) -> np.ndarray:
    """Each point's nearest of the seeds `lab` holds in its search voxel's 27 neighbours
    (the numpy reference of _refine_nearest_torch).

    pts [M, 3] float32 points, pos32 [N, 3] float32 Gaussians, lab [X, Y, Z] int64 seed
    (index into pos32, -1 none) of each search voxel, pv [M, 3] int64 each point's search
    voxel. Returns [M] int64 indices into pos32 (-1 where all 27 voxels are empty, which
    a jump-flooded grid never has); of equally near seeds, the first in the order centre,
    then voxels.DIRS."""
    dims = np.asarray(lab.shape)
    best_i = lab[tuple(pv.T)]
    best_d = np.where(best_i >= 0, ((pos32[np.maximum(best_i, 0)] - pts) ** 2).sum(-1), np.float32(np.inf))
    for off in vx.DIRS:
        q = pv + np.asarray(off)
        ok = ((q >= 0) & (q < dims)).all(-1)
        ci = np.where(ok, lab[tuple(np.clip(q, 0, dims - 1).T)], -1)
        dc = ((pos32[np.maximum(ci, 0)] - pts) ** 2).sum(-1)
        better = (ci >= 0) & (dc < best_d)
        best_i[better] = ci[better]
        best_d[better] = dc[better]
    return best_i


def _refine_nearest_torch(pts, pos32, lab, pv, device: torch.device, deadline: _Deadline | None = None) -> np.ndarray:
    """_refine_nearest_ref in torch on `device` (its arrays numpy or torch): the same
    candidates, distances and ties.

    A filled closed scan has up to millions of lattice points (the donut: 784k), each with
    27 gathers: on the 2-core development CPU this takes 0.5 s for the donut against the
    numpy reference's 1.7 s, and on an H100 the donut's whole nearest search (jump flooding
    included) about 0.1 s. `deadline` is checked before each of the 27 passes."""
    dims = torch.tensor(lab.shape, device=device)
    labt = torch.as_tensor(lab, device=device)
    post = torch.as_tensor(pos32, device=device)
    ptst = torch.as_tensor(pts, device=device)
    pvt = torch.as_tensor(pv, device=device)

    def sqdist(i: torch.Tensor) -> torch.Tensor:
        # index_select: faster than advanced indexing on a CPU
        return vx.sq_dist(post.index_select(0, i.clamp(min=0)), ptst)

    if deadline is not None:
        deadline.check("finding nearest Gaussians")
    best_i = labt[pvt[:, 0], pvt[:, 1], pvt[:, 2]]
    best_d = torch.where(best_i >= 0, sqdist(best_i), torch.inf)
    for off in vx.DIRS:
        if deadline is not None:
            deadline.check("finding nearest Gaussians")
        q = pvt + torch.tensor(off, device=device)
        ok = ((q >= 0) & (q < dims)).all(-1)
        qc = torch.minimum(q.clamp(min=0), dims - 1)
        ci = torch.where(ok, labt.view(-1).index_select(0, (qc[:, 0] * dims[1] + qc[:, 1]) * dims[2] + qc[:, 2]), -1)
        dc = sqdist(ci)
        better = (ci >= 0) & (dc < best_d)
        best_i = torch.where(better, ci, best_i)
        best_d = torch.where(better, dc, best_d)
    return best_i.cpu().numpy()


# ----------------------------------------------------------------------------- helpers


def _as_numpy(positions, quats, scales, opacities):
    arrs = []
    for name, a, tail in (("positions", positions, (3,)), ("quats", quats, (4,)),
                          ("scales", scales, (3,)), ("opacities", opacities, ())):
        a = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)
        arrs.append(a.astype(np.float64))
        n = arrs[0].shape[0] if arrs[0].ndim >= 1 else -1
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail or a.shape[0] != n:
            raise PreparationError(
                f"fill_interior: {name} has shape {tuple(a.shape)}, expected {(n, *tail)} "
                "(N Gaussians)"
            )
    return arrs


def _like(points: np.ndarray, ref) -> np.ndarray | torch.Tensor:
    if isinstance(ref, torch.Tensor):
        return torch.from_numpy(points).to(device=ref.device, dtype=ref.dtype)
    dtype = ref.dtype if isinstance(ref, np.ndarray) and ref.dtype.kind == "f" else np.float64
    return points.astype(dtype)


def _like_index(source: np.ndarray, ref) -> np.ndarray | torch.Tensor:
    source = source.astype(np.int64)
    if isinstance(ref, torch.Tensor):
        return torch.from_numpy(source).to(ref.device)
    return source


def _empty(like, closedness: float, reason: str, volume: float, h: float = float("nan")) -> FillResult:
    return FillResult(_like(np.zeros((0, 3)), like), _like_index(np.zeros(0, np.int64), like),
                      False, closedness, reason, volume, h)
