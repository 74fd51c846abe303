"""K-Means of Gaussian centres into driving particles, memory-bounded and deterministic.

Lloyd iterations whose assignment step is an exact 1-nearest-centre search on a grid
(``knn.knn``), so that 1M points into 50k clusters never holds a 1M x 50k matrix (the
authors' version ran out of memory there). Cluster sums are accumulated in 64-bit fixed
point: integer atomics are associative, so the result is identical from run to run on
CUDA too (float atomics are not).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from pd_tool.drivers.knn import default_chunk, grid_radius, knn
from pd_tool.core.errors import PdToolError

DEFAULT_ITERS = 20  # Lloyd iterations at most
DEFAULT_TOL = 1e-4  # stop once fewer than this fraction of the points change cluster
_MORTON_BITS = 21  # bits per axis of the Morton code (3 x 21 = 63)


class DriverError(PdToolError):
    """Driving-particle options are impossible (more drivers than points, ratio <= 0, ...)."""


def _morton_codes(points: Tensor) -> Tensor:
    """63-bit Morton (Z-order) code of each point in its bounding box: [N] int64."""
    lo = points.min(0).values
    ext = (points.max(0).values - lo).clamp_min(1e-30)
    scale = float((1 << _MORTON_BITS) - 1)
    q = ((points - lo) / ext * scale).round().long().clamp(0, (1 << _MORTON_BITS) - 1)

    def spread(v: Tensor) -> Tensor:  # insert two zero bits between the 21 bits of v
        v = (v | (v << 32)) & 0x1F00000000FFFF
        v = (v | (v << 16)) & 0x1F0000FF0000FF
        v = (v | (v << 8)) & 0x100F00F00F00F00F
        v = (v | (v << 4)) & 0x10C30C30C30C30C3
        v = (v | (v << 2)) & 0x1249249249249249
        return v

    return (spread(q[:, 0]) << 2) | (spread(q[:, 1]) << 1) | spread(q[:, 2])


def _init_morton(points: Tensor, k: int, gen: torch.Generator) -> Tensor:
    """Stratified seeding: split the Z-order curve into k runs of equal count, one random
    member of each run is a centre. O(N log N); spreads centres with the point density.
    """
    n = points.shape[0]
    order = torch.argsort(_morton_codes(points), stable=True)
    bounds = torch.div(torch.arange(k + 1, dtype=torch.long) * n, k, rounding_mode="floor")
    size = bounds[1:] - bounds[:-1]  # >= 1 since k <= n
    u = torch.rand(k, generator=gen, dtype=torch.float64)
    pick = bounds[:-1] + torch.minimum((u * size).long(), size - 1)
    return points[order[pick.to(points.device)]].clone()


def _init_kmeanspp(points: Tensor, k: int, gen: torch.Generator) -> Tensor:
    """Classic k-means++ (D^2 sampling), O(N) memory, k sequential passes over the points.

    Exact but slow for large k (50k passes for 50k drivers); prefer "morton" there.
    """
    n = points.shape[0]
    u = torch.rand(k, generator=gen, dtype=torch.float64)
    first = min(int(u[0] * n), n - 1)
    centres = torch.empty((k, 3), dtype=points.dtype, device=points.device)
    centres[0] = points[first]
    d2 = ((points - centres[0]) ** 2).sum(1).double()
    for j in range(1, k):
        cdf = torch.cumsum(d2, 0)
        total = cdf[-1]
        if float(total) <= 0.0:  # fewer distinct points than k: any point will do
            pick = torch.tensor(min(int(u[j] * n), n - 1), device=points.device)
        else:
            pick = torch.searchsorted(cdf, (u[j].to(points.device) * total).reshape(1)).clamp_max(n - 1)[0]
        centres[j] = points[pick]
        d2 = torch.minimum(d2, ((points - centres[j]) ** 2).sum(1).double())
    return centres


def _assign(points: Tensor, centres: Tensor, chunk: int, radius: float) -> tuple[Tensor, Tensor]:
    """Exact nearest centre of every point: (dist2 [N], label [N] long), by one full
    search each iteration (knn.knn's hash-grid pass, from `radius`). Reusing candidate
    centres between iterations does not pay here (docs/benchmarks.md, "tried for setup")."""
    d2, idx = knn(points, centres, 1, chunk=chunk, radius=radius)
    return d2[:, 0], idx[:, 0]


class _FixedPoint:
    """Exact, order-independent cluster sums: coordinates as 64-bit integers."""

    def __init__(self, points: Tensor):
        n = points.shape[0]
        self.lo = points.min(0).values.double()
        self.ext = (points.max(0).values.double() - self.lo).clamp_min(1e-30)
        # Sums of up to n values below 2^bits must stay below 2^62.
        self.bits = min(40, 62 - max(1, math.ceil(math.log2(max(n, 2)))))
        self.q = ((points.double() - self.lo) / self.ext * float(1 << self.bits)).round().long()

    def means(self, labels: Tensor, k: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """(centres [k, 3] mean of members, counts [k] long)."""
        dev = labels.device
        sums = torch.zeros((k, 3), dtype=torch.long, device=dev).index_add_(0, labels, self.q)
        counts = torch.bincount(labels, minlength=k)
        mean = sums.double() / counts.clamp_min(1)[:, None].double()
        return (self.lo + mean / float(1 << self.bits) * self.ext).to(dtype), counts


def _reseed_empty(labels: Tensor, d2: Tensor, counts: Tensor) -> Tensor:
    """Give each empty cluster one point: the farthest from its own centre among clusters
    that can spare one (keep >= 1 member). Deterministic: stable sorts only.
    """
    empty = torch.nonzero(counts == 0).squeeze(1)
    if empty.numel() == 0:
        return labels
    n = labels.shape[0]
    # Points by decreasing distance (ties by index), then their rank inside their cluster.
    by_dist = torch.argsort(-d2, stable=True)
    lab_sorted = labels[by_dist]
    by_label = torch.argsort(lab_sorted, stable=True)
    lab2 = lab_sorted[by_label]
    pos = torch.arange(n, device=labels.device)
    first = torch.ones_like(lab2, dtype=torch.bool)
    first[1:] = lab2[1:] != lab2[:-1]
    seg_start = torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values
    rank = torch.empty_like(pos)
    rank[by_label] = pos - seg_start  # rank of by_dist[i] in its cluster
    spare = rank < counts[lab_sorted] - 1
    donors = by_dist[spare][: empty.numel()]
    labels = labels.clone()
    labels[donors] = empty[: donors.numel()]
    return labels


def kmeans(
    points: Tensor,
    k: int,
    *,
    seed: int = 0,
    iters: int = DEFAULT_ITERS,
    tol: float = DEFAULT_TOL,
    chunk: int | None = None,
    init: str = "morton",
) -> tuple[Tensor, Tensor]:
    """Cluster points into k clusters (Lloyd), memory-bounded and deterministic for a seed.

    Args:
        points: [N, 3] float (any unit), CPU or CUDA.
        k: clusters, 1 <= k <= N.
        seed: seeds the initialisation; same seed and device -> same result.
        iters: Lloyd iterations at most.
        tol: stop when fewer than tol * N points change cluster in an iteration.
        chunk: (point, candidate) pairs held in memory at once (default:
            pd_tool.drivers.knn.default_chunk); memory is O(N + k + chunk), never N x k.
        init: "morton" (default: Z-order stratified seeding, O(N log N)) or "kmeans++"
            (D^2 sampling, k sequential passes: fine for k up to a few thousand).
    Returns:
        (centres [k, 3] points.dtype, the mean of each cluster's members;
         labels [N] long, the cluster of each point). No cluster is empty: an emptied
        cluster is re-seeded with the point farthest from its own centre.
    """
    if points.ndim != 2 or points.shape[1] != 3:
        raise DriverError(f"kmeans: points must be [N, 3], got {tuple(points.shape)}")
    n = points.shape[0]
    if not 1 <= k <= n:
        raise DriverError(f"kmeans: asked for {k} clusters of {n} points; use 1 <= k <= {n}")
    if not bool(torch.isfinite(points).all()):
        raise DriverError("kmeans: points hold NaN or inf; clean the scene before clustering")
    gen = torch.Generator().manual_seed(int(seed))  # CPU stream: same draws on any device
    if init == "morton":
        centres = _init_morton(points, k, gen)
    elif init == "kmeans++":
        centres = _init_kmeanspp(points, k, gen)
    else:
        raise DriverError(f"kmeans: unknown init {init!r}; use 'morton' or 'kmeans++'")
    fixed = _FixedPoint(points)
    chunk = default_chunk(points.device) if chunk is None else chunk
    # centres keep their spacing from one iteration to the next: size the search once
    radius = grid_radius(points, centres, 1, chunk)
    labels = None
    for _ in range(max(1, iters)):
        d2, new = _assign(points, centres, chunk, radius)
        counts = torch.bincount(new, minlength=k)
        new = _reseed_empty(new, d2, counts)
        changed = n if labels is None else int((new != labels).sum())
        labels = new
        centres, counts = fixed.means(labels, k, points.dtype)
        if changed < tol * n:
            break
    return centres, labels
