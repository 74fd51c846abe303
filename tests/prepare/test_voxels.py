"""The interior fill's voxel passes (pd_tool/prepare/voxels.py) on each device against
direct references: ray walks, breadth-first searches, a scan of every seed, and the
nearest-seed search's numpy twin."""
from __future__ import annotations

import math
from collections import deque

import numpy as np
import pytest
import torch

from pd_tool.prepare import voxels as vx


def _t(a: np.ndarray, device: str) -> torch.Tensor:
    return torch.as_tensor(a, device=device)


def _sandwich_ref(shell: np.ndarray) -> np.ndarray:
    """The 13-line vote (a share, 0-1) by walking each line out of the grid from every voxel."""
    out = np.zeros(shell.shape)
    for x in np.ndindex(shell.shape):
        for d in vx.DIRS[:13]:
            both = True
            for sgn in (1, -1):
                y, hit = np.array(x) + sgn * np.array(d), False
                while ((y >= 0) & (y < shell.shape)).all():
                    if shell[tuple(y)]:
                        hit = True
                        break
                    y = y + sgn * np.array(d)
                both &= hit
            out[x] += both
    return out / 13


def _bfs(seed: np.ndarray, free: np.ndarray) -> np.ndarray:
    """6-step distance (inf unreached) from `seed` through `free` voxels."""
    dist = np.full(free.shape, np.inf)
    todo = deque()
    for x in map(tuple, np.argwhere(seed & free)):
        dist[x] = 0
        todo.append(x)
    while todo:
        x = todo.popleft()
        for ax in range(3):
            for s in (-1, 1):
                y = list(x)
                y[ax] += s
                y = tuple(y)
                if 0 <= y[ax] < free.shape[ax] and free[y] and dist[y] == np.inf:
                    dist[y] = dist[x] + 1
                    todo.append(y)
    return dist


def test_directions_pair_with_their_opposites():
    assert len(vx.DIRS) == 26 and len(set(vx.DIRS)) == 26
    for i, d in enumerate(vx.DIRS):
        assert vx.DIRS[25 - i] == tuple(-c for c in d)


@pytest.mark.parametrize("shape", [(7, 6, 5), (3, 9, 4), (5, 5, 1)])
def test_ray_vote_matches_line_walks(device, shape):
    """Each line family, sheared along its shortest axis, on uneven grids; both scans."""
    rng = np.random.default_rng(sum(shape))
    shell = rng.random(shape) < 0.15
    want = _sandwich_ref(shell)
    np.testing.assert_array_equal(vx.ray_votes(_t(shell, device)).cpu().numpy(), want * vx.LINES)
    for d in vx.DIRS:
        a = vx.sandwiched(_t(shell, device), d, by_planes=True)
        b = vx.sandwiched(_t(shell, device), d, by_planes=False)
        assert torch.equal(a, b), d


def test_a_closed_box_votes_every_line_inside_and_none_outside(device):
    shell = np.zeros((9, 10, 11), bool)
    shell[2:7, 2:8, 2:9] = True
    shell[3:6, 3:7, 3:8] = False  # a hollow box, one voxel thick
    vote = vx.ray_votes(_t(shell, device)).cpu().numpy()
    assert (vote[3:6, 3:7, 3:8] == vx.LINES).all()
    assert (vote[0] == 0).all() and (vote[:, :, -1] == 0).all()


def test_flood_matches_bfs(device):
    rng = np.random.default_rng(3)
    free = rng.random((9, 8, 7)) < 0.6
    seed = np.zeros_like(free)
    seed[0] = True
    got = vx.flood(_t(seed, device), _t(free, device)).cpu().numpy()
    np.testing.assert_array_equal(got, np.isfinite(_bfs(seed, free)))


def test_drop_border_components_keeps_only_enclosed_pockets(device):
    rng = np.random.default_rng(6)
    mask = rng.random((8, 9, 7)) < 0.55
    border = np.zeros_like(mask)
    border[[0, -1]] = border[:, [0, -1]] = border[:, :, [0, -1]] = True
    want = mask & ~np.isfinite(_bfs(border, mask))
    got = vx.drop_border_components(_t(mask, device)).cpu().numpy()
    np.testing.assert_array_equal(got, want)
    assert want.any() and (mask & ~want).any()  # both kinds of component are there


def test_deep_is_a_6_step_distance(device):
    rng = np.random.default_rng(7)
    mask = np.ones((12, 11, 10), bool)
    mask[rng.random(mask.shape) < 0.03] = False
    depth = 2
    dist = _bfs(~mask, np.ones_like(mask))  # 6-steps from the nearest voxel outside the mask
    got = vx.deep(_t(mask, device), depth).cpu().numpy()
    np.testing.assert_array_equal(got, mask & (dist > depth))


def test_grow_into_shell_splits_the_band_at_its_middle(device):
    """A ball's shell band 4 voxels thick: the inner two layers join the interior, the
    outer two do not; a band of odd thickness splits its middle layer by the checkerboard."""
    ix = np.indices((24, 24, 24)).transpose(1, 2, 3, 0) - 11.5
    r = np.sqrt((ix**2).sum(-1))
    for inner, outer in ((6, 10), (6, 9)):
        interior, shell = r < inner, (r >= inner) & (r < outer)
        got = vx.grow_into_shell(_t(interior, device), _t(shell, device)).cpu().numpy()
        assert (got[interior]).all() and not got[r >= outer].any()
        d_in = _bfs(interior, shell | interior)  # steps from the interior through the band
        d_out = _bfs(~shell & ~interior, shell | ~interior)
        band = shell & np.isfinite(d_in)
        np.testing.assert_array_equal(got[band & (d_in < d_out)], True)
        np.testing.assert_array_equal(got[band & (d_in > d_out)], False)
        tie = band & (d_in == d_out)
        if tie.any():
            assert 0 < got[tie].mean() < 1  # ties go to both sides


def _jfa_ref(seeds, cells, shape, corner, size):
    """The nearest-seed search in numpy, in the same order as voxels.jump_flood."""
    lab = np.full(shape, -1, np.int64)
    lab[tuple(cells.T)] = np.arange(len(seeds))  # the last seed of a voxel wins
    centre = (np.indices(shape, np.float32).transpose(1, 2, 3, 0) * np.float32(size)
              + (corner + 0.5 * size).astype(np.float32))

    def dist(lb):
        d = ((seeds[np.maximum(lb, 0)] - centre) ** 2).sum(-1)
        d[lb < 0] = np.inf
        return d

    def shift(t, off):
        out = np.full_like(t, -1)
        src, dst = [], []
        for o, n in zip(off, t.shape):
            if abs(o) >= n:
                return out
            src.append(slice(max(0, o), n + min(0, o)))
            dst.append(slice(max(0, -o), n - max(0, o)))
        out[tuple(dst)] = t[tuple(src)]
        return out

    best = dist(lab)
    step = 1 << max(0, int(math.ceil(math.log2(max(shape)))) - 1)
    steps = []
    while step >= 1:
        steps.append(step)
        step //= 2
    for step in steps + [1]:
        for off in vx.DIRS:
            cand = shift(lab, [o * step for o in off])
            dc = dist(cand)
            better = dc < best
            lab[better] = cand[better]
            best[better] = dc[better]
    return lab, best


def test_jump_flood_matches_numpy_and_is_near_the_nearest(device):
    rng = np.random.default_rng(8)
    shape, size = (13, 9, 11), 0.1
    corner = np.array([-0.3, 0.2, 1.0])
    seeds = (corner + rng.random((60, 3)) * np.array(shape) * size).astype(np.float32)
    seeds[1] = seeds[0] + 1e-3  # two seeds in one voxel: the later one seeds it
    cells = np.clip(np.floor((seeds - corner) / size).astype(np.int64), 0, np.array(shape) - 1)
    got = vx.jump_flood(_t(seeds, device), _t(cells, device), shape,
                        torch.as_tensor(corner, dtype=torch.float64), size).cpu().numpy()
    want, best = _jfa_ref(seeds, cells, shape, corner, size)
    np.testing.assert_array_equal(got, want)
    assert (got >= 0).all()
    # within a voxel diagonal of the true nearest seed of each centre
    centre = corner + (np.indices(shape).transpose(1, 2, 3, 0) + 0.5) * size
    true = np.sqrt(((centre[..., None, :] - seeds) ** 2).sum(-1)).min(-1)
    assert (np.sqrt(best) <= true + math.sqrt(3) * size).all()
