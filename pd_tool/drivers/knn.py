"""Exact k nearest neighbours of many query points among a set of reference points.

Used twice: the 8 nearest drivers of each Gaussian at rest, and the assignment step of
K-Means (k = 1). A full N x Q distance matrix is never built.

1. For float32 points and k <= 16, one warp thread per query scans a hash grid of the
   references within a radius that most queries' k-th neighbour lies within
   (kernels.grid_knn): one launch, no host round trip.
2. The queries it cannot settle (their k-th candidate lies beyond the radius), and every
   query for float64 or larger k, go to torch: the references sorted into a uniform grid,
   each query looks at the 3 x 3 x 3 block of cells around its own, and only queries whose
   k-th candidate is farther than the block's wall retry with cells twice as large, then
   fall back to a brute-force search (chunked over the reference points).

The result is exact either way; equal distances go to the lower index in the first pass.

Memory: at most ``chunk`` (query, candidate) pairs are held at once, plus O(N k + Q) and
the hash grid's buckets (at most 2^22, 32 MB).
"""
from __future__ import annotations

import contextlib
import math

import torch
from torch import Tensor

from pd_tool.drivers.kernels import KNN_MAX_K

DEFAULT_CHUNK = 1 << 22  # (query, candidate) pairs held in memory at once, on the CPU
# ... and on a GPU, where each chunk costs a host round trip and a few launches. K-Means and
# the nearest drivers of 1M / 3M points (388k / 494k centres) on an H200 took 1.09 / 1.51 s
# at 2^22 pairs, 0.34 / 0.88 s at 2^24 and 0.36 / 0.94 s at 2^25, holding 0.5 / 1.3 / 2.1 GB
# at 1M (pd_tool.prepare.memory counts it).
CUDA_CHUNK = 1 << 24


def default_chunk(device: torch.device | str) -> int:
    """(query, candidate) pairs a search on `device` holds at once."""
    return CUDA_CHUNK if torch.device(device).type == "cuda" else DEFAULT_CHUNK
_SAMPLE = 256  # queries whose k-th neighbour distance sets the cell size
_SAMPLE_QUANTILE = 0.8  # of those distances: most queries finish in the first pass
# The hash-grid kernel's search radius: this quantile of the sample's k-th neighbour
# distances, times _GRID_SLACK. A query whose k-th neighbour lies farther is searched again
# in torch; a larger radius costs candidates as its cube.
_GRID_QUANTILE = 0.95
_GRID_SLACK = 1.1
_GRID_MAX_CELLS = 1 << 22  # hash grid buckets at most (two int32 each)
_MIN_CELL = 1e-4  # cell size floor relative to the refs' extent (duplicate points)
_SAFE_SPAN = 1e15  # coordinates spanning more (or less than its inverse) are rescaled first
_OFFSETS = torch.tensor(
    [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], dtype=torch.long
)  # [27, 3] neighbour cell offsets


class _Grid:
    """Reference points sorted by the key of the uniform grid cell they fall in."""

    def __init__(self, refs: Tensor, cell: float):
        self.cell = float(cell)
        self.origin = refs.min(0).values
        ijk = torch.floor((refs - self.origin) / self.cell).long()
        self.dims = ijk.max(0).values + 1  # [3] cells per axis
        key = self._key(ijk)
        self.order = torch.argsort(key, stable=True)  # refs index by cell
        sorted_key = key[self.order]
        self.cell_keys, counts = torch.unique_consecutive(sorted_key, return_counts=True)
        self.cell_start = torch.cumsum(counts, 0) - counts
        self.cell_count = counts
        self.refs = refs

    def _key(self, ijk: Tensor) -> Tensor:
        d = self.dims
        return (ijk[..., 0] * d[1] + ijk[..., 1]) * d[2] + ijk[..., 2]

    def query_cells(self, q: Tensor) -> Tensor:
        """Cell of each query, clamped into the grid: [c, 3] long."""
        ijk = torch.floor((q - self.origin) / self.cell).long()
        return torch.minimum(ijk.clamp_min(0), self.dims - 1)

    def block_ranges(self, ijk: Tensor) -> tuple[Tensor, Tensor]:
        """Start (in sorted order) and count of the refs in the 27 cells around ijk: [c, 27]."""
        nb = ijk[:, None, :] + _OFFSETS.to(ijk.device)[None]
        inside = ((nb >= 0) & (nb < self.dims)).all(-1)
        key = self._key(nb.clamp_min(0))
        pos = torch.searchsorted(self.cell_keys, key).clamp_max(self.cell_keys.numel() - 1)
        found = inside & (self.cell_keys[pos] == key)
        start = torch.where(found, self.cell_start[pos], torch.zeros_like(pos))
        count = torch.where(found, self.cell_count[pos], torch.zeros_like(pos))
        return start, count

    def safe_radius(self, q: Tensor, ijk: Tensor) -> Tensor:
        """Distance from each query to the nearest wall of its 3x3x3 block: [c].

        Every reference point outside the block is at least this far away. A wall on the
        grid's own boundary does not count: nothing lies beyond it.
        """
        lo = self.origin + (ijk - 1).to(q.dtype) * self.cell
        hi = self.origin + (ijk + 2).to(q.dtype) * self.cell
        inf = torch.full_like(lo, math.inf)
        lo_gap = torch.where(ijk - 1 <= 0, inf, q - lo)
        hi_gap = torch.where(ijk + 1 >= self.dims - 1, inf, hi - q)
        return torch.minimum(lo_gap, hi_gap).min(-1).values


def _pick_cell(queries: Tensor, refs: Tensor, k: int, chunk: int, quantile: float = _SAMPLE_QUANTILE) -> float:
    """Cell size from the k-th neighbour distance of a few sample queries.

    The search is exact for a query whose k-th neighbour is within its block's wall, at
    least one cell away: a cell of about the typical k-th neighbour distance keeps the
    block small (3-6 k candidates) while most queries succeed on the first pass.
    """
    ext = float((refs.max(0).values - refs.min(0).values).max())
    if ext <= 0.0:
        return 1.0  # all refs on one point: one cell
    m = min(queries.shape[0], _SAMPLE)
    sample = queries[torch.linspace(0, queries.shape[0] - 1, m, device=queries.device).long()]
    d2, _ = knn_brute(sample, refs, k, chunk)
    r = torch.quantile(d2[:, -1].double().sqrt(), quantile)
    return max(float(r) * 1.05, ext * _MIN_CELL)


def _topk_block(
    q: Tensor, grid: _Grid, k: int, chunk: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Top-k among the block candidates for queries q [c, 3].

    Returns (dist2 [c, k], idx [c, k], exact [c] bool); missing entries are inf / 0.
    """
    c = q.shape[0]
    dev = q.device
    ijk = grid.query_cells(q)
    start, count = grid.block_ranges(ijk)  # [c, 27]
    total = count.sum(1)
    out_d = torch.full((c, k), math.inf, dtype=q.dtype, device=dev)
    out_i = torch.zeros((c, k), dtype=torch.long, device=dev)
    if c > 0 and int(total.max()) > 0:
        ends = torch.cumsum(count, 1)  # [c, 27] inclusive offsets
        begins = ends - count
        # Queries by candidate count, so that each sub-chunk pads little; sub-chunks hold
        # at most `chunk` (query, candidate) pairs (x4: three coordinates and a distance).
        perm = torch.argsort(total, stable=True)
        totals = total[perm].cpu().tolist()
        s = 0
        while s < c:
            e = min(c, s + max(1, chunk // (4 * max(1, totals[s]))))
            while e - s > 1 and (e - s) * 4 * totals[e - 1] > chunk:
                e = s + max(1, chunk // (4 * totals[e - 1]))
            tm = totals[e - 1]
            if tm == 0:
                s = e
                continue
            rows = perm[s:e]
            t = torch.arange(tm, device=dev).expand(e - s, tm).contiguous()
            cell = torch.searchsorted(ends[rows], t, right=True).clamp_max(26)
            sorted_pos = torch.gather(start[rows], 1, cell) + t - torch.gather(begins[rows], 1, cell)
            valid = t < total[rows, None]
            sorted_pos = torch.where(valid, sorted_pos, torch.zeros_like(sorted_pos))
            idx = grid.order[sorted_pos]  # [b, tm] reference indices
            d2 = ((grid.refs[idx] - q[rows, None, :]) ** 2).sum(-1)
            d2 = torch.where(valid, d2, torch.full_like(d2, math.inf))
            kk = min(k, tm)
            best_d, best_j = torch.topk(d2, kk, dim=1, largest=False, sorted=True)
            out_d[rows, :kk] = best_d
            out_i[rows, :kk] = torch.gather(idx, 1, best_j)
            s = e
    safe = grid.safe_radius(q, ijk)
    exact = out_d[:, -1] <= safe * safe
    return out_d, out_i, exact


def knn_brute(q: Tensor, refs: Tensor, k: int, chunk: int = DEFAULT_CHUNK) -> tuple[Tensor, Tensor]:
    """Exact k nearest refs of each query, chunked over refs (running top-k).

    Returns (dist2 [c, k] ascending, idx [c, k] long). Memory: O(chunk + c k).
    """
    c = q.shape[0]
    best_d = torch.full((c, 0), math.inf, dtype=q.dtype, device=q.device)
    best_i = torch.zeros((c, 0), dtype=torch.long, device=q.device)
    if c == 0:
        return best_d.new_zeros((0, k)), best_i.new_zeros((0, k))
    step_q = max(1, chunk // 4)
    out_d, out_i = [], []
    for qs in range(0, c, step_q):
        qq = q[qs : qs + step_q]
        bd, bi = best_d[qs : qs + step_q], best_i[qs : qs + step_q]
        step_r = max(1, chunk // (4 * qq.shape[0]))
        for rs in range(0, refs.shape[0], step_r):
            r = refs[rs : rs + step_r]
            d2 = ((qq[:, None, :] - r[None, :, :]) ** 2).sum(-1)
            ids = torch.arange(rs, rs + r.shape[0], device=q.device).expand_as(d2)
            cand_d = torch.cat([bd, d2], 1)
            cand_i = torch.cat([bi, ids], 1)
            kk = min(k, cand_d.shape[1])
            bd, j = torch.topk(cand_d, kk, dim=1, largest=False, sorted=True)
            bi = torch.gather(cand_i, 1, j)
        out_d.append(bd)
        out_i.append(bi)
    return torch.cat(out_d), torch.cat(out_i)


def grid_radius(queries: Tensor, refs: Tensor, k: int, chunk: int | None = None) -> float:
    """The hash-grid pass's first search radius for these points (same units): a brute
    search of a sample, so a caller that searches similar points again (K-Means' iterations)
    computes it once and passes it to `knn`."""
    chunk = default_chunk(queries.device) if chunk is None else chunk
    return _pick_cell(queries, refs, k, chunk, _GRID_QUANTILE) * _GRID_SLACK


def knn(
    queries: Tensor, refs: Tensor, k: int, *, chunk: int | None = None, cell: float | None = None,
    radius: float | None = None,
) -> tuple[Tensor, Tensor]:
    """Exact k nearest reference points of each query point.

    Args:
        queries: [N, 3] float, any unit (same as refs).
        refs: [Q, 3] float, same dtype and device; Q >= k.
        k: neighbours per query.
        chunk: (query, candidate) pairs held in memory at once; default: default_chunk.
        cell: grid cell size of the torch search; default: about max(2, k/2) refs per
            occupied cell.
        radius: first radius of the hash-grid pass (float32, k <= 16); default:
            `grid_radius`. Any radius gives the exact answer; a poor one costs time.
    Returns:
        (dist2 [N, k] squared distances ascending, idx [N, k] long indices into refs).
    """
    n, q_count = queries.shape[0], refs.shape[0]
    chunk = default_chunk(queries.device) if chunk is None else chunk
    if k > q_count:
        raise ValueError(f"knn: k={k} neighbours asked among only {q_count} reference points")
    if n == 0 or k == 0:
        return queries.new_zeros((n, k)), torch.zeros((n, k), dtype=torch.long, device=queries.device)
    if not (bool(torch.isfinite(queries).all()) and bool(torch.isfinite(refs).all())):
        raise ValueError("knn: the points hold NaN or inf")
    lo = torch.minimum(refs.min(0).values, queries.min(0).values)
    hi = torch.maximum(refs.max(0).values, queries.max(0).values)
    span = float((hi - lo).max())
    if span > _SAFE_SPAN or 0.0 < span < 1.0 / _SAFE_SPAN:
        # squared distances overflow (or underflow) float32 here, and with them the cell
        # choice (NaN cells never grow): search in coordinates scaled to the span, which
        # keeps the order of the distances, and scale the distances back
        f = 1.0 / span
        d2, i = knn((queries - lo) * f, (refs - lo) * f, k, chunk=chunk, cell=None if cell is None else cell * f,
                    radius=None if radius is None else radius * f)
        return d2.double().mul(span * span).to(d2.dtype), i
    dist = torch.empty((n, k), dtype=queries.dtype, device=queries.device)
    idx = torch.empty((n, k), dtype=torch.long, device=queries.device)
    pending = torch.arange(n, device=queries.device)
    if k <= KNN_MAX_K and queries.dtype == torch.float32 and refs.dtype == torch.float32:
        # the hash grid; the queries it leaves again with twice the radius, until the
        # radius spans every point (what rounding still leaves goes to the search below)
        radius = grid_radius(queries, refs, k, chunk) if radius is None else radius
        while pending.numel() > 0:
            d_g, i_g, ok = _grid_pass(queries[pending], refs, k, radius, lo, hi)
            dist[pending[ok]], idx[pending[ok]] = d_g[ok], i_g[ok]
            pending = pending[~ok]
            if not radius <= 2.0 * max(span, 1e-30):
                break
            radius *= 2.0
    if pending.numel() > 0 and cell is None:
        cell = _pick_cell(queries, refs, k, chunk)
    # Queries whose k-th candidate lies beyond their block's wall are retried with cells
    # twice as large; once a block spans the whole grid every answer is exact.
    while pending.numel() > 0:
        grid = _Grid(refs, cell)
        # Sorted by cell, so that each chunk holds neighbouring queries with similar
        # candidate counts (less padding).
        order = pending[torch.argsort(grid._key(grid.query_cells(queries[pending])), stable=True)]
        missed = []
        step = max(1, chunk // 27)
        for s in range(0, order.numel(), step):
            ids = order[s : s + step]
            d_c, i_c, exact = _topk_block(queries[ids], grid, k, chunk)
            dist[ids[exact]] = d_c[exact]
            idx[ids[exact]] = i_c[exact]
            missed.append(ids[~exact])
        pending = torch.cat(missed)
        cell *= 2.0
        if pending.numel() > 0 and not cell <= 4.0 * max(span, 1e-30):
            # a block already spans every point, so nothing is left but rounding: finish
            # those queries by brute force instead of growing cells forever
            d_b, i_b = knn_brute(queries[pending], refs, k, chunk)
            dist[pending], idx[pending] = d_b, i_b
            break
    return dist, idx


def _grid_pass(queries: Tensor, refs: Tensor, k: int, radius: float, lo: Tensor, hi: Tensor
               ) -> tuple[Tensor, Tensor, Tensor]:
    """First pass of `knn` for float32 and k <= KNN_MAX_K: one warp thread per query scans
    a hash grid of the refs within `radius` (kernels.grid_knn), on the queries' device
    without a host round trip. lo, hi [3]: a box holding the queries and the refs (knn's,
    computed once for all its passes). Returns (dist2 [N, k], idx [N, k] long, exact [N]
    bool); rows not exact hold what the kernel saw and are searched again by the caller."""
    import warp as wp

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.drivers.kernels import grid_knn

    init_warp_quietly()
    n, dev = queries.shape[0], queries.device
    dist = torch.empty((n, k), dtype=torch.float32, device=dev)
    idx = torch.empty((n, k), dtype=torch.long, device=dev)
    exact = torch.empty(n, dtype=torch.int32, device=dev)
    scale = float(torch.maximum(lo.abs(), hi.abs()).max())
    span = float((hi - lo).max())
    # The grid keeps cell indices within 2^20 of the origin; farther, the torch search
    # does everything.
    if not radius > 0 or (scale + radius) / radius >= 1 << 19:
        return dist, idx, torch.zeros(n, dtype=torch.bool, device=dev)
    cells = [max(1, math.ceil(float(e) / radius) + 3) for e in (hi - lo).tolist()]
    while math.prod(cells) > _GRID_MAX_CELLS:  # a hashed grid: fewer buckets, more candidates
        cells = [max(1, (c + 1) // 2) for c in cells]
    # Rounding margin: the grid's cell arithmetic and the float32 distances err by a few
    # ulps of the coordinates, so only a k-th neighbour this far inside the radius is sure.
    sure = radius - 8.0 * torch.finfo(torch.float32).eps * max(scale, span)
    sure2 = sure * sure if sure > 0 else -1.0
    q32, r32 = queries.contiguous(), refs.contiguous()
    wdev = str(dev) if dev.type == "cuda" else "cpu"
    stream = wp.stream_from_torch(dev) if dev.type == "cuda" else None
    with wp.ScopedDevice(wdev), (wp.ScopedStream(stream) if stream is not None else contextlib.nullcontext()):
        refs_w = wp.from_torch(r32, dtype=wp.vec3)
        grid = wp.HashGrid(*cells, device=wdev)
        grid.build(refs_w, radius)
        wp.launch(grid_knn, dim=n, device=wdev, inputs=[
            grid.id, refs_w, wp.from_torch(q32, dtype=wp.vec3), k, float(radius), float(sure2),
            wp.from_torch(dist, dtype=wp.float32), wp.from_torch(idx, dtype=wp.int64), wp.from_torch(exact, dtype=wp.int32)])
        if stream is not None:
            # the grid's buffers are freed when it goes out of scope here, possibly on another
            # stream than the search still reading them; the caller reads the rows next anyway
            wp.synchronize_stream(stream)
    return dist, idx, exact.bool()


def nearest_drivers(points: Tensor, drivers: Tensor, k: int = 8, *, chunk: int | None = None) -> Tensor:
    """Indices of the k nearest drivers of every point (exact, grid-accelerated).

    Args:
        points: [N, 3] float Gaussian centres (simulation units).
        drivers: [Q, 3] float driver positions, same device; Q >= k.
        k: neighbours per point (8 in the paper).
        chunk: (point, candidate) pairs held in memory at once (default: default_chunk);
            never an N x Q matrix.
    Returns:
        [N, k] long, nearest first.
    """
    return knn(points, drivers, k, chunk=chunk)[1]
