"""K-Means, nearest drivers, driver count and driver sets."""
from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from pd_tool.drivers import DriverError, build_drivers, driver_count, kmeans, nearest_drivers
from pd_tool.drivers._ref import knn_ref, lloyd_ref
from pd_tool.drivers.knn import knn

ROOT = Path(__file__).resolve().parents[2]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def torus(n: int, gen: torch.Generator, noise: float = 0.0) -> torch.Tensor:
    """Points on a torus surface (radii 1 and 0.3): Gaussians lie on surfaces."""
    u = torch.rand(n, 2, generator=gen) * 2 * torch.pi
    r = 1 + 0.3 * u[:, 1].cos()
    p = torch.stack([r * u[:, 0].cos(), r * u[:, 0].sin(), 0.3 * u[:, 1].sin()], 1)
    return p + noise * torch.randn(n, 3, generator=gen)


@pytest.mark.parametrize("k", [1, 8])
@pytest.mark.parametrize("layout", ["volume", "surface", "outside", "sparse"])
def test_knn_matches_dense_reference(device, k, layout):
    gen = torch.Generator().manual_seed(0)
    if layout == "volume":
        q, r = torch.rand(6000, 3, generator=gen), torch.rand(700, 3, generator=gen)
    elif layout == "surface":
        q = torus(6000, gen)
        r = torus(800, gen, noise=0.002)
    elif layout == "outside":  # queries far outside the references' box
        q, r = 4 * torch.randn(3000, 3, generator=gen), torch.rand(300, 3, generator=gen)
    else:  # two far clusters and a few stragglers: very uneven density
        r = torch.cat([torch.rand(400, 3, generator=gen) * 0.01, 5 + torch.rand(400, 3, generator=gen), torch.rand(8, 3, generator=gen) * 5])
        q = torch.cat([torch.rand(2000, 3, generator=gen) * 0.01, 5 + torch.rand(2000, 3, generator=gen), torch.rand(500, 3, generator=gen) * 6])
    d2, idx = knn(q.to(device), r.to(device), k, chunk=1 << 16)
    d2_ref, idx_ref = knn_ref(q, r, k)
    # a caller's radius far too small (or stale) costs retries, never exactness
    d2_small, _ = knn(q.to(device), r.to(device), k, chunk=1 << 16, radius=1e-4)
    assert torch.allclose(d2_small.cpu().double(), d2_ref, atol=1e-6, rtol=1e-5)
    assert torch.allclose(d2.cpu().double(), d2_ref, atol=1e-6, rtol=1e-5)
    # Indices may differ only where distances tie.
    recomputed = ((q[:, None, :] - r[idx.cpu()]) ** 2).sum(-1).double()
    assert torch.allclose(recomputed, d2_ref, atol=1e-6, rtol=1e-5)
    assert (idx.cpu() == idx_ref).float().mean() > 0.999


def test_nearest_drivers_shape_and_order(device):
    gen = torch.Generator().manual_seed(1)
    pts, drv = torch.rand(1000, 3, generator=gen), torch.rand(100, 3, generator=gen)
    nb = nearest_drivers(pts.to(device), drv.to(device), 8)
    assert nb.shape == (1000, 8) and nb.dtype == torch.long
    d = ((pts[:, None] - drv[nb.cpu()]) ** 2).sum(-1)
    assert (d[:, 1:] >= d[:, :-1]).all()


def test_kmeans_follows_dense_lloyd_from_the_same_start(device):
    gen = torch.Generator().manual_seed(2)
    # Well separated blobs plus background: no empty cluster, no ties.
    centres = torch.rand(40, 3, generator=gen) * 10
    pts = (centres[torch.randint(0, 40, (4000,), generator=gen)] + torch.randn(4000, 3, generator=gen)).to(device)
    k = 60
    km = sys.modules["pd_tool.drivers.kmeans"]
    init = km._init_morton(pts, k, torch.Generator().manual_seed(5))
    c_ref, l_ref = lloyd_ref(pts.cpu(), init.cpu(), iters=8)
    assert torch.bincount(l_ref, minlength=k).min() > 0
    c, labels = kmeans(pts, k, seed=5, iters=8, tol=0.0)
    assert torch.equal(labels.cpu(), l_ref)
    assert torch.allclose(c.cpu().double(), c_ref, atol=1e-5)


@pytest.mark.parametrize("init", ["morton", "kmeans++"])
def test_kmeans_is_deterministic_and_seeded(device, init):
    gen = torch.Generator().manual_seed(3)
    pts = torus(5000, gen, noise=0.01).to(device)
    c1, l1 = kmeans(pts, 300, seed=7, init=init)
    c2, l2 = kmeans(pts, 300, seed=7, init=init)
    assert torch.equal(c1, c2) and torch.equal(l1, l2)
    c3, _ = kmeans(pts, 300, seed=8, init=init)
    assert not torch.equal(c1, c3)
    # Centres are the means of their members, and every cluster has members.
    counts = torch.bincount(l1, minlength=300)
    assert counts.min() >= 1
    means = torch.zeros(300, 3, dtype=torch.float64, device=device).index_add_(0, l1, pts.double()) / counts[:, None]
    assert torch.allclose(c1.double(), means, atol=1e-6)


def test_kmeans_improves_on_its_start():
    gen = torch.Generator().manual_seed(4)
    pts = torus(20000, gen, noise=0.01)
    km = sys.modules["pd_tool.drivers.kmeans"]
    init = km._init_morton(pts, 500, torch.Generator().manual_seed(0))
    inertia0 = knn_ref(pts, init, 1)[0].mean()
    c, labels = kmeans(pts, 500, seed=0)
    inertia = ((pts - c[labels]) ** 2).sum(1).double().mean()
    assert inertia < 0.8 * inertia0


def test_kmeans_reseeds_empty_clusters_with_duplicate_points():
    # 10 distinct locations, each 50 times: with k = 25 many starting centres coincide and
    # their clusters empty out; every cluster must still end with a member.
    gen = torch.Generator().manual_seed(5)
    pts = torch.rand(10, 3, generator=gen).repeat(50, 1)
    pts[::7] += 0.01 * torch.rand(pts[::7].shape, generator=gen)
    c, labels = kmeans(pts, 25, seed=0)
    counts = torch.bincount(labels, minlength=25)
    assert counts.min() >= 1
    means = torch.zeros(25, 3, dtype=torch.float64).index_add_(0, labels, pts.double()) / counts[:, None]
    assert torch.allclose(c.double(), means, atol=1e-6)
    # k = N: every point its own cluster.
    few = torch.rand(30, 3, generator=gen)
    c, labels = kmeans(few, 30)
    assert torch.equal(torch.sort(labels).values, torch.arange(30))


def test_kmeans_rejects_bad_input():
    with pytest.raises(DriverError, match="clusters"):
        kmeans(torch.rand(10, 3), 11)
    with pytest.raises(DriverError, match="NaN"):
        kmeans(torch.tensor([[0.0, 0.0, float("nan")]] * 3), 2)


def test_kmeans_memory_is_bounded_on_200k_points():
    # In a fresh process: peak resident memory (ru_maxrss, which sees torch's allocations)
    # grown by clustering 200k points into 20k drivers and finding 8 nearest drivers each.
    # A full distance matrix would be 200k x 20k x 4 bytes = 16 GB; the bound is 1/64 of it
    # (the chunk of 2^20 candidate pairs costs about 60 bytes a pair).
    script = textwrap.dedent(
        """
        import resource, torch
        from pd_tool.drivers import kmeans, nearest_drivers
        torch.set_num_threads(1)
        g = torch.Generator().manual_seed(0)
        n = 200_000
        u = torch.rand(n, 2, generator=g) * 6.283
        r = 1 + 0.3 * u[:, 1].cos()
        pts = torch.stack([r * u[:, 0].cos(), r * u[:, 0].sin(), 0.3 * u[:, 1].sin()], 1)
        pts = pts + 0.01 * torch.randn(n, 3, generator=g)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        c, l = kmeans(pts, 20_000, seed=0, iters=4, chunk=1 << 20)
        nb = nearest_drivers(pts, c, 8, chunk=1 << 20)
        after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        assert torch.bincount(l, minlength=20_000).min() >= 1 and nb.shape == (n, 8)
        print((after - before) * 1024)  # ru_maxrss is in KiB on Linux
        """
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr
    grown = int(out.stdout.strip().splitlines()[-1])
    full_matrix = 200_000 * 20_000 * 4
    assert grown < full_matrix / 64, f"K-Means grew the peak RSS by {grown / 2**20:.0f} MiB"


def test_driver_count_rules():
    dx = 0.1
    # 3 occupied cells, 100 points each.
    pts = torch.cat([torch.full((100, 3), 0.05), torch.full((100, 3), 0.15), torch.full((100, 3), 0.55)])
    assert driver_count(pts, dx) == 24
    assert driver_count(pts, dx, min_per_cell=200) == 300  # never more than N
    assert driver_count(pts, dx, ratio=0.1) == 30
    assert driver_count(pts, dx, count=7) == 7
    assert driver_count(pts, dx, count=10**6) == 300
    assert driver_count(pts[:1], dx, ratio=0.01) == 1
    with pytest.raises(DriverError, match="ratio"):
        driver_count(pts, dx, ratio=1.5)
    with pytest.raises(DriverError, match="count"):
        driver_count(pts, dx, count=0)
    with pytest.raises(DriverError, match="no Gaussians"):
        driver_count(pts[:0], dx)


def test_driver_ratio_is_capped_per_occupied_cell():
    dx = 0.1
    pts = torch.cat([torch.full((500, 3), 0.05), torch.full((500, 3), 0.55)])  # 2 occupied cells
    assert driver_count(pts, dx, ratio=0.5) == 2 * 64  # not 500: the grid cannot use them
    assert driver_count(pts, dx, ratio=0.5, max_per_cell=1000) == 500
    assert driver_count(pts, dx, ratio=0.05) == 50  # under the cap: the ratio rules


def _sums_match(ds, pts, volume, mass):
    q = len(ds)
    labels = ds.labels.cpu()
    vol_ref = torch.zeros(q, dtype=torch.float64).index_add_(0, labels, volume.cpu().double())
    assert torch.allclose(ds.volume.cpu().double(), vol_ref, atol=1e-5)
    assert torch.allclose(ds.mass.sum().cpu(), mass.sum().cpu(), rtol=1e-5)
    means = torch.zeros(q, 3, dtype=torch.float64).index_add_(0, labels, pts.cpu().double()) / ds.counts.cpu()[:, None]
    assert torch.allclose(ds.positions.cpu().double(), means, atol=1e-6)
    _, nb_ref = knn_ref(pts.cpu(), ds.positions.cpu(), 8)
    assert (ds.neighbors.cpu() == nb_ref).float().mean() > 0.999


def test_build_drivers_majority_mode(device):
    gen = torch.Generator().manual_seed(6)
    pts = torus(3000, gen, noise=0.01).to(device)
    volume = torch.rand(3000, generator=gen).to(device)
    mass = 2.0 * volume
    static = (pts[:, 2] < -0.1).to(device)
    ds = build_drivers(pts, volume, mass, static, dx=0.1, ratio=0.1, seed=0, static_drivers="majority")
    q = len(ds)
    assert q == 300 and ds.positions.shape == (q, 3) and ds.neighbors.shape == (3000, 8)
    _sums_match(ds, pts, volume, mass)
    labels = ds.labels.cpu()
    frac = torch.zeros(q).index_add_(0, labels, static.cpu().float()) / torch.bincount(labels, minlength=q)
    assert torch.equal(ds.static.cpu(), frac > 0.5)


def test_build_drivers_static_nodes_mode(device):
    # Default: free Gaussians by K-Means (the ratio counts those), static ones grouped by
    # the grid node nearest to them, so that drivers pin exactly the Gaussians' nodes.
    gen = torch.Generator().manual_seed(7)
    pts = torus(3000, gen, noise=0.01).to(device) + 2.0  # positive, like a simulation box
    volume = torch.rand(3000, generator=gen).to(device)
    mass = 3.0 * volume
    static = (pts[:, 2] < 1.9).to(device)
    dx = 0.1
    ds = build_drivers(pts, volume, mass, static, dx, ratio=0.1, seed=0)
    _sums_match(ds, pts, volume, mass)
    labels = ds.labels.cpu()
    # No driver mixes static and free Gaussians.
    mixed = torch.zeros(len(ds)).index_add_(0, labels, static.cpu().float()) / ds.counts.cpu()
    assert ((mixed == 0) | (mixed == 1)).all()
    assert torch.equal(ds.static.cpu(), mixed == 1)
    n_free = int((~static).sum())
    assert int((~ds.static).sum()) == round(0.1 * n_free)

    def nodes(p):
        return {tuple(v) for v in torch.floor(p.cpu().double() / dx + 0.5).long().tolist()}

    assert nodes(ds.positions[ds.static]) == nodes(pts[static])
    assert int(ds.static.sum()) == len(nodes(pts[static]))


def test_build_drivers_on_a_real_capture(shared_data):
    from plyfile import PlyData

    v = PlyData.read(str(shared_data / "udon.ply"))["vertex"]
    pts = torch.from_numpy(np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float32))
    n = pts.shape[0]
    ext = float((pts.max(0).values - pts.min(0).values).max())
    dx = ext / 32
    ds = build_drivers(pts - pts.min(0).values, torch.ones(n), torch.ones(n), torch.zeros(n, dtype=torch.bool), dx)
    pts = pts - pts.min(0).values
    occupied = torch.unique(torch.floor(pts / dx).long(), dim=0).shape[0]
    assert len(ds) == min(8 * occupied, n)
    assert ds.counts.min() >= 1 and int(ds.counts.sum()) == n
    # Each Gaussian's own driver is among its nearest few (K-Means converged).
    own = (ds.neighbors == ds.labels[:, None]).any(1).float().mean()
    assert own > 0.95


def test_build_drivers_all_free_all_static_and_bad_mode():
    gen = torch.Generator().manual_seed(8)
    pts = torch.rand(500, 3, generator=gen)
    ones = torch.ones(500)
    free = build_drivers(pts, ones, ones, torch.zeros(500, dtype=torch.bool), 0.1, count=40)
    assert len(free) == 40 and not free.static.any()
    fixed = build_drivers(pts, ones, ones, torch.ones(500, dtype=torch.bool), 0.1, count=40)
    assert fixed.static.all() and int(fixed.counts.sum()) == 500
    with pytest.raises(DriverError, match="static_drivers"):
        build_drivers(pts, ones, ones, torch.zeros(500, dtype=torch.bool), 0.1, static_drivers="some")


@pytest.mark.parametrize("k", [1, 8, 16])
def test_grid_pass_rows_it_calls_exact_are_exact(device, k):
    """The hash-grid kernel against the dense search: every row it calls exact is, whatever
    the radius (a small one leaves many rows to the torch search), and equal distances go
    to the lower index whatever order the grid visits them in."""
    knn_mod = sys.modules["pd_tool.drivers.knn"]
    gen = torch.Generator().manual_seed(6)
    q, r = torus(3000, gen), torus(500, gen, noise=0.003)
    d_ref, i_ref = knn_ref(q, r, k)
    kth = d_ref[:, -1].sqrt()
    qd, rd = q.to(device), r.to(device)
    lo, hi = torch.minimum(qd.min(0).values, rd.min(0).values), torch.maximum(qd.max(0).values, rd.max(0).values)
    for radius in (float(kth.quantile(0.3)), float(kth.quantile(0.95)) * 1.1, 5.0):
        d, i, exact = knn_mod._grid_pass(qd, rd, k, radius, lo, hi)
        exact = exact.cpu()
        assert exact.float().mean() > (0.2 if radius < 1 else 0.999)
        assert torch.allclose(d.cpu()[exact].double(), d_ref[exact], atol=1e-6, rtol=1e-5)
        assert (i.cpu()[exact] == i_ref[exact]).float().mean() > 0.999
        # no row called exact whose k-th neighbour lies beyond the radius
        assert not (exact & (kth > radius)).any()
    dup = torch.cat([r[:50], r[:50], r[50:]])  # each of the first 50 twice: ties
    d, i, _ = knn_mod._grid_pass(r[:50].to(device), dup.to(device), 2, 0.5, dup.min(0).values.to(device),
                                 dup.max(0).values.to(device))
    assert torch.equal(i.cpu(), torch.stack([torch.arange(50), torch.arange(50, 100)], 1))
    assert (d.cpu() == 0).all()
