"""Boolean voxel-grid passes of the interior fill, in torch on the scan's device.

The fill's analysis grid holds up to fill.MAX_VOXELS (4M) voxels. On a GPU each pass below
is a few kernels over the whole grid; on a CPU each is a vectorised loop. Every function
takes and returns tensors on one device and gives the same answer on every device (they
are integer and boolean work, and the nearest-seed search sums its float32 distances in a
fixed order).

References (tests/prepare/test_voxels.py): brute-force ray walks for `ray_votes`, a
breadth-first search for `flood` and for `deep`'s 6-step distance, and every seed's
distance for `jump_flood`.
"""
from __future__ import annotations

import math
from typing import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

# the 26 neighbour directions, in np.ndindex order less the centre; the first 13 and the
# last 13 are opposites of each other (DIRS[i] == -DIRS[25 - i])
DIRS: list[tuple[int, int, int]] = [
    (a - 1, b - 1, c - 1) for a in range(3) for b in range(3) for c in range(3) if (a, b, c) != (1, 1, 1)
]

Check = Callable[[str], None]  # the fill's deadline check: raises once time is up


def _no_check(stage: str) -> None:
    return None


def close(mask: Tensor) -> Tensor:
    """Morphological closing of a bool grid [X, Y, Z] with a 3x3x3 cube: seals pinholes one
    voxel wide. Voxels of `mask` stay set."""
    t = mask[None, None].to(torch.float32)
    dil = F.max_pool3d(t, 3, 1, 1)
    ero = 1.0 - F.max_pool3d(1.0 - dil, 3, 1, 1)
    return (ero[0, 0] > 0.5) | mask


def _grid_in_lines(lines: Tensor, n: tuple[int, int, int], step: tuple[int, int]) -> Tensor:
    """The view [n0, n1, n2] of a grid stored sheared in `lines` [n0, L1, L2] (contiguous):
    grid voxel (i, p, q) sits at lines[i, p + o1 - step1 i, q + o2 - step2 i], so that each
    row lines[:, u, w] holds one line of the grid along (1, step1, step2). The offsets o
    keep every voxel inside; L = n + n0 - 1 on a stepped axis, n on the other."""
    l1, l2 = lines.shape[1:]
    o1 = n[0] - 1 if step[0] > 0 else 0
    o2 = n[0] - 1 if step[1] > 0 else 0
    return lines.as_strided(n, (l1 * l2 - step[0] * l2 - step[1], l2, 1), lines.storage_offset() + o1 * l2 + o2)


def _between(lines: Tensor, by_planes: bool) -> Tensor:
    """bool [n0, ...]: set where `lines` (bool [n0, ...]) is set both before and after along
    the first axis. by_planes: a loop over the planes (on a CPU five times faster than a
    cumulative sum down the outer axis); else one cumulative sum (one kernel on a GPU)."""
    if by_planes:
        seen = torch.zeros_like(lines[0])
        before = torch.empty_like(lines)
        for i in range(lines.shape[0]):
            before[i] = seen
            seen |= lines[i]
        seen.zero_()
        for i in range(lines.shape[0] - 1, -1, -1):
            before[i] &= seen
            seen |= lines[i]
        return before
    count_type = torch.int16 if lines.shape[0] < 2**15 else torch.int32
    count = lines.cumsum(0, dtype=count_type)  # set voxels up to and including each one
    return (count > lines.to(count_type)) & (count[-1:] > count)


def sandwiched(shell: Tensor, d: tuple[int, int, int], by_planes: bool | None = None) -> Tensor:
    """bool [X, Y, Z]: the voxels whose line along direction d (components -1, 0 or 1, not
    all 0) meets `shell` on both sides of them before it leaves the grid.

    The grid is stored sheared, so that every line along d is a row along the first axis
    (the shortest of d's non-zero axes, for the least padding), and a scan down the rows
    finds the shell before and after each voxel. The sheared copy holds
    n0 (n1 + n0 - 1) (n2 + n0 - 1) voxels for a body diagonal, n0 the line axis's length.
    by_planes: see _between; default: on a CPU."""
    nz = [i for i in range(3) if d[i] != 0]
    a = min(nz, key=lambda i: shell.shape[i])
    b, c = [i for i in range(3) if i != a]
    sign = d[a]
    step = (d[b] * sign, d[c] * sign)
    t = shell.permute(a, b, c)
    n = tuple(t.shape)
    lines = torch.zeros((n[0], n[1] + (n[0] - 1) * abs(step[0]), n[2] + (n[0] - 1) * abs(step[1])),
                        dtype=torch.bool, device=shell.device)
    _grid_in_lines(lines, n, step).copy_(t)
    both = _between(lines, shell.device.type == "cpu" if by_planes is None else by_planes)
    inv = [0, 0, 0]
    for pos, axis in enumerate((a, b, c)):
        inv[axis] = pos
    return _grid_in_lines(both, n, step).permute(*inv)


LINES = 13  # neighbour lines through a voxel: DIRS[:13], each with its opposite


def ray_votes(shell: Tensor, check: Check = _no_check) -> Tensor:
    """uint8 [X, Y, Z] in 0-LINES: how many of the 13 neighbour lines through each voxel
    meet `shell` on both sides of it.

    Outside a convex object no line does (a line meets a convex body on one side of an
    outside point only), so the vote is 0 there; a bowl's or a torus hole's concavity gets
    the few lines across it; inside a closed shell, all 13. Counts, not fractions: a GPU's
    division by 13 can land an ulp off the CPU's, and thresholds must not move with it."""
    votes = torch.zeros(shell.shape, dtype=torch.uint8, device=shell.device)
    for d in DIRS[:LINES]:
        check("casting rays")
        votes += sandwiched(shell, d)
    return votes


def _spread(reach: Tensor, free: Tensor, axis: int) -> Tensor:
    """reach grown along `axis` over whole runs of `free`: every voxel of a run of free
    voxels (along that axis) that holds a reached voxel is reached."""
    r = reach.movedim(axis, -1)
    f = free.movedim(axis, -1)
    shape = r.shape
    n = shape[-1]
    r2, f2 = r.reshape(-1, n), f.reshape(-1, n)
    lines = r2.shape[0]
    # a run id per voxel: blocked voxels start a new run, and each line has its own ids
    run = torch.cumsum(~f2, 1) + (torch.arange(lines, device=reach.device) * (n + 1))[:, None]
    lit = torch.zeros(lines * (n + 1), dtype=torch.bool, device=reach.device)
    lit[run[r2]] = True
    return (lit[run] & f2).reshape(shape).movedim(-1, axis)


def flood(seed: Tensor, free: Tensor, check: Check = _no_check) -> Tensor:
    """bool [X, Y, Z]: the voxels of `free` 6-connected to `seed` through `free`. Whole
    runs along an axis spread at once, so a pass per axis crosses a straight corridor."""
    reach = seed & free
    while True:
        before = int(reach.sum())
        for axis in range(3):
            check("flood filling")
            reach = _spread(reach, free, axis)
        if int(reach.sum()) == before:
            return reach


def drop_border_components(mask: Tensor, check: Check = _no_check) -> Tensor:
    """`mask` less its 6-connected components that touch the grid's border."""
    border = torch.zeros_like(mask)
    border[[0, -1]] = True
    border[:, [0, -1]] = True
    border[:, :, [0, -1]] = True
    return mask & ~flood(border, mask, check)


def dilate6(m: Tensor) -> Tensor:
    """m grown by one 6-neighbour step (faces only)."""
    out = m.clone()
    out[1:] |= m[:-1]
    out[:-1] |= m[1:]
    out[:, 1:] |= m[:, :-1]
    out[:, :-1] |= m[:, 1:]
    out[:, :, 1:] |= m[:, :, :-1]
    out[:, :, :-1] |= m[:, :, 1:]
    return out


def deep(mask: Tensor, depth: int, check: Check = _no_check) -> Tensor:
    """The voxels of `mask` more than `depth` 6-steps from every voxel outside it (the grid's
    outside does not count)."""
    reach = ~mask
    for _ in range(depth):
        check("measuring the shell thickness")
        reach = dilate6(reach)
    return mask & ~reach


def grow_into_shell(interior: Tensor, shell: Tensor, check: Check = _no_check) -> Tensor:
    """`interior` plus the inner half of the shell band: fronts grow at once from the
    interior and from the outside through the band; voxels that both reach in the same step
    go alternately to each side."""
    inside = interior.clone()
    outside = ~shell & ~interior
    todo = shell & ~interior
    # a checkerboard splits the voxels that both fronts reach at once, and flips each step,
    # so that neither side is favoured over the whole surface
    ix = [torch.arange(s, device=shell.device) for s in shell.shape]
    even = ((ix[0][:, None, None] + ix[1][None, :, None] + ix[2][None, None, :]) % 2) == 0
    flip = False
    while bool(todo.any()):
        check("splitting the shell band")
        gi = dilate6(inside) & todo
        go = dilate6(outside) & todo
        if not (bool(gi.any()) or bool(go.any())):
            break
        tie = gi & go
        tie_in = tie & (~even if flip else even)
        inside |= (gi & ~go) | tie_in
        outside |= (go & ~gi) | (tie & ~tie_in)
        todo &= ~(gi | go)
        flip = not flip
    return inside


def shift(t: Tensor, off: tuple[int, int, int], fill: int = -1) -> Tensor:
    """out[x] = t[x + off], `fill` where x + off leaves the grid."""
    out = torch.full_like(t, fill)
    src, dst = [], []
    for o, n in zip(off, t.shape):
        if abs(o) >= n:
            return out
        src.append(slice(max(0, o), n + min(0, o)))
        dst.append(slice(max(0, -o), n - max(0, o)))
    out[tuple(dst)] = t[tuple(src)]
    return out


def sq_dist(points: Tensor, centres: Tensor) -> Tensor:
    """Squared distances [...] of float32 points [..., 3] and centres [..., 3], summed x,
    then y, then z (numpy's order, so that ties break alike everywhere)."""
    d = points - centres
    return (d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]) + d[..., 2] * d[..., 2]


def jump_flood(seeds: Tensor, cells: Tensor, shape: tuple[int, int, int], corner: Tensor, size: float,
               check: Check = _no_check) -> Tensor:
    """int64 [X, Y, Z]: for each voxel of a grid of `shape`, the index of an approximately
    nearest seed point to its centre (-1 only when there are no seeds).

    seeds [N, 3] float32 positions; cells [N, 3] int64 their voxels (in the grid); corner [3]
    float64 the grid's low corner; size the voxel edge (the unit of both). Each voxel starts with the highest
    index of the seeds it holds, then jump flooding with steps 2^k ... 1 and one more unit
    pass (JFA+1) takes a neighbour's seed whenever it is strictly nearer; neighbours are
    visited in DIRS order, so ties keep the first."""
    dev = seeds.device
    dims = torch.tensor(shape, device=dev)
    flat = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    lab = torch.full((math.prod(shape),), -1, dtype=torch.int64, device=dev)
    lab.scatter_reduce_(0, flat, torch.arange(len(seeds), device=dev), reduce="amax")
    lab = lab.reshape(shape)
    ix = [torch.arange(s, dtype=torch.float32, device=dev) for s in shape]
    centre = torch.stack(torch.meshgrid(*ix, indexing="ij"), -1) * torch.tensor(size, dtype=torch.float32) \
        + (corner.to(dev, torch.float64) + 0.5 * size).to(torch.float32)

    def dist(lb: Tensor) -> Tensor:
        return torch.where(lb >= 0, sq_dist(seeds[lb.clamp(min=0)], centre), torch.inf)

    best = dist(lab)
    steps = []
    step = 1 << max(0, int(math.ceil(math.log2(max(shape)))) - 1)
    while step >= 1:
        steps.append(step)
        step //= 2
    for step in steps + [1]:
        check("finding nearest Gaussians")
        for off in DIRS:
            cand = shift(lab, (off[0] * step, off[1] * step, off[2] * step))
            dc = dist(cand)
            better = dc < best
            lab = torch.where(better, cand, lab)
            best = torch.where(better, dc, best)
    return lab
