"""Driving particles of a prepared scene: how many, where, and what they carry."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from pd_tool.drivers.kmeans import DriverError, kmeans
from pd_tool.drivers.knn import nearest_drivers

MIN_PER_CELL = 8  # paper: occupied grid cells hold at least 8 drivers on average
# A ratio never asks for more than this many drivers per occupied cell: the grid cannot
# resolve motion finer than a cell, so more particles cost time and memory and add no
# accuracy (4 to 39 per cell gave the same error at grid 16 on the procedural plant).
# Without it a 300k-Gaussian scene at ratio 0.5 on a 16-cell grid would put thousands of
# particles in each cell.
MAX_PER_CELL = 64
NEIGHBORS = 8  # drivers per Gaussian for the interpolation (paper)


def driver_count(
    points_sim: Tensor,
    dx: float,
    *,
    ratio: float | None = None,
    count: int | None = None,
    min_per_cell: int = MIN_PER_CELL,
    max_per_cell: int = MAX_PER_CELL,
) -> int:
    """Number of driving particles for N Gaussians.

    Args:
        points_sim: [N, 3] Gaussian centres in simulation units.
        dx: simulation grid spacing (same units).
        ratio: drivers per Gaussian in (0, 1]; overrides the default rule, capped at
            max_per_cell drivers per occupied cell.
        count: an exact number of drivers (>= 1); overrides ratio and the rule.
        min_per_cell: the default rule: min_per_cell drivers times the number of grid
            cells (spacing dx, origin 0) holding at least one Gaussian.
    Returns:
        Q with 1 <= Q <= N.
    """
    n = int(points_sim.shape[0])
    if n == 0:
        raise DriverError("driver_count: the scene has no Gaussians to drive; check the foreground selection")
    if count is not None:
        if int(count) < 1:
            raise DriverError(f"driver_count: count={count}; give at least 1 driver")
        q = int(count)
    elif ratio is not None:
        if not 0.0 < float(ratio) <= 1.0:
            raise DriverError(f"driver_count: ratio={ratio}; use a fraction in (0, 1], e.g. 0.1")
        q = int(round(float(ratio) * n))
        if dx > 0.0 and q > max_per_cell:
            q = min(q, max_per_cell * _occupied_cells(points_sim, dx))
    else:
        if not dx > 0.0:
            raise DriverError(f"driver_count: grid spacing dx={dx}; it must be > 0")
        q = min_per_cell * _occupied_cells(points_sim, dx)
    return max(1, min(q, n))


def _occupied_cells(points_sim: Tensor, dx: float) -> int:
    """Grid cells (spacing dx, origin 0) holding at least one point."""
    return int(torch.unique(torch.floor(points_sim / dx).long(), dim=0).shape[0])


@dataclass
class DriverSet:
    """Driving particles and how the Gaussians hang on them.

    Attributes:
        positions: [Q, 3] driver positions at rest (cluster means), simulation units.
        volume: [Q] summed volume of the members (simulation units^3).
        mass: [Q] summed mass of the members (kg, or whatever unit mass came in).
        static: [Q] bool, True where most (strictly more than half) members are static.
        labels: [N] long, the driver (cluster) of each Gaussian.
        neighbors: [N, K] long, each Gaussian's K = min(8, Q) nearest drivers at rest.
        points_rest: [N, 3] Gaussian centres at rest (what neighbors refers to).
        counts: [Q] long, members per driver (>= 1).
    """

    positions: Tensor
    volume: Tensor
    mass: Tensor
    static: Tensor
    labels: Tensor
    neighbors: Tensor
    points_rest: Tensor
    counts: Tensor

    @property
    def rest_positions(self) -> Tensor:
        """[Q, 3] drivers at rest (alias of positions)."""
        return self.positions

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def hung_on(self, points: Tensor, neighbors: int = NEIGHBORS) -> DriverSet:
        """The same drivers with other particles hung on them: points [M, 3] (simulation
        units) each on its `neighbors` nearest drivers, labelled by the nearest. For drivers
        clustered from other points than the ones they move (sub-particles)."""
        near = nearest_drivers(points, self.positions, min(neighbors, len(self)))
        return DriverSet(positions=self.positions, volume=self.volume, mass=self.mass, static=self.static,
                         labels=near[:, 0].clone(), neighbors=near, points_rest=points, counts=self.counts)


def build_drivers(
    points_sim: Tensor,
    volume: Tensor,
    mass: Tensor,
    static: Tensor,
    dx: float,
    *,
    ratio: float | None = None,
    count: int | None = None,
    seed: int = 0,
    neighbors: int = NEIGHBORS,
    static_drivers: str = "nodes",
    **kmeans_options,
) -> DriverSet:
    """Cluster the Gaussians into driving particles (K-Means) and link each to its drivers.

    Args:
        points_sim: [N, 3] float Gaussian centres at rest, simulation units (the grid's
            nodes sit at integer multiples of dx).
        volume: [N] particle volumes; mass: [N] particle masses; static: [N] bool.
        dx: simulation grid spacing: for the default count rule (driver_count) and for
            grouping static Gaussians by grid node.
        ratio / count: the number of moving drivers (driver_count over the free
            Gaussians when static_drivers="nodes", over all of them with "majority").
        seed: K-Means seed (deterministic per seed and device).
        neighbors: drivers per Gaussian (8, the paper's).
        static_drivers: "nodes" (default): free Gaussians are clustered by K-Means; static
            Gaussians get one static driver per grid node nearest to them (the node the
            simulator pins), so the drivers pin exactly the nodes that every Gaussian would.
            "majority": one K-Means over all Gaussians; a driver is static where most of its
            members are (the paper's recipe; it moves the clamped boundary, see
            docs/drivers.md).
        kmeans_options: passed to kmeans (iters, tol, chunk, init).
    Returns:
        DriverSet; with "nodes" the moving drivers come first, then the static ones.
    """
    n = int(points_sim.shape[0])
    dev = points_sim.device
    for name, t in (("volume", volume), ("mass", mass), ("static", static)):
        if t.shape != (n,):
            raise DriverError(f"build_drivers: {name} must be [{n}] like points_sim, got {tuple(t.shape)}")
    static = static.to(device=dev, dtype=torch.bool)
    if static_drivers == "majority":
        q = driver_count(points_sim, dx, ratio=ratio, count=count)
        centres, labels = kmeans(points_sim, q, seed=seed, **kmeans_options)
    elif static_drivers == "nodes":
        if not dx > 0.0:
            raise DriverError(f"build_drivers: grid spacing dx={dx}; it must be > 0")
        free_idx = torch.nonzero(~static).squeeze(1)
        static_idx = torch.nonzero(static).squeeze(1)
        labels = torch.empty(n, dtype=torch.long, device=dev)
        parts = []
        q_free = 0
        if free_idx.numel() > 0:
            q_free = driver_count(points_sim[free_idx], dx, ratio=ratio, count=count)
            c_free, l_free = kmeans(points_sim[free_idx], q_free, seed=seed, **kmeans_options)
            labels[free_idx] = l_free
            parts.append(c_free)
        if static_idx.numel() > 0:
            node = torch.floor(points_sim[static_idx] / dx + 0.5).long()
            _, l_static = torch.unique(node, dim=0, return_inverse=True)
            labels[static_idx] = q_free + l_static
            q_static = int(l_static.max()) + 1
            sums = torch.zeros((q_static, 3), dtype=torch.float64, device=dev)
            sums.index_add_(0, l_static, points_sim[static_idx].double())
            cnt = torch.bincount(l_static, minlength=q_static)[:, None].double()
            # The mean of points nearest to one node is nearest to it too (its cell is convex).
            parts.append((sums / cnt).to(points_sim.dtype))
        centres = torch.cat(parts)
        q = centres.shape[0]
    else:
        raise DriverError(f"build_drivers: static_drivers={static_drivers!r}; use 'nodes' or 'majority'")
    acc = torch.float64
    vol = torch.zeros(q, dtype=acc, device=dev).index_add_(0, labels, volume.to(dev, acc))
    m = torch.zeros(q, dtype=acc, device=dev).index_add_(0, labels, mass.to(dev, acc))
    counts = torch.bincount(labels, minlength=q)
    n_static = torch.zeros(q, dtype=torch.long, device=dev)
    n_static.index_add_(0, labels, static.to(torch.long))
    nb = nearest_drivers(points_sim, centres, min(neighbors, q))
    return DriverSet(
        positions=centres,
        volume=vol.to(volume.dtype),
        mass=m.to(mass.dtype),
        static=2 * n_static > counts,
        labels=labels,
        neighbors=nb,
        points_rest=points_sim,
        counts=counts,
    )
