"""Driving particles: simulate a few, move every Gaussian with its nearest ones.

Public API (torch, CPU or CUDA; shapes in the docstrings of each function):

    from pd_tool.drivers import build_drivers, DriverInterpolator

    drivers = build_drivers(points_sim, volume, mass, static, dx)   # K-Means + 8-NN
    # ... simulate drivers.positions -> x_now [Q, 3] ...
    move = DriverInterpolator(drivers.points_rest, quats, drivers.positions,
                              drivers.neighbors)                    # once
    points_now, quats_now = move(x_now)                              # every frame

- kmeans(points [N,3], k, *, seed=0, iters=20, tol=1e-4, chunk=None, init="morton")
  -> (centres [k,3], labels [N]): Lloyd with exact grid-accelerated assignment, memory
  O(N + k + chunk) (never N x k), deterministic per seed and device, no empty cluster.
- driver_count(points_sim [N,3], dx, *, ratio=None, count=None, min_per_cell=8) -> int:
  default: 8 drivers per occupied grid cell (the paper's rule); or ratio * N; or count;
  always 1..N.
- build_drivers(points_sim, volume [N], mass [N], static [N] bool, dx, *, ratio=None,
  count=None, seed=0, static_drivers="nodes") -> DriverSet(positions [Q,3], volume [Q]
  (summed), mass [Q] (summed), static [Q], labels [N], neighbors [N,8], points_rest [N,3],
  counts [Q]). Default "nodes": K-Means over the free Gaussians (ratio/count/rule count
  those), plus one static driver per grid node pinned by static Gaussians, so the drivers
  clamp the same nodes as all Gaussians would; "majority": one K-Means, static by majority.
  Recommended ratio (docs/drivers.md): 1/4 (RMS error < 1% of the object's size on
  the plant for every poke tried); 1/10 for drafts.
- nearest_drivers(points [N,3], drivers [Q,3], k=8) -> [N,k] long: exact, grid-based.
- DriverInterpolator(..., backend="auto"): a fused warp kernel for rigid float32 calls
  without gradient (bake), torch otherwise (fit).
- interpolate(rest_points, rest_quats, drivers_rest, drivers_now, neighbors,
  mode="rigid") -> (points_now [N,3], quats_now [N,4] wxyz) for "rigid", plus
  F [N,3,3] for "affine". DriverInterpolator is the same with the rest state computed
  once (use it per frame). Differentiable in drivers_now with finite gradients even for
  pure translations (Horn quaternion + power method in pd_tool.core.quaternion, no
  SVD/eigh backward).
  Default "rigid", the paper's: shape-preserving, robust for thin (coplanar)
  neighbourhoods; "affine" also stretches/shears Gaussians (apply_deformation turns
  F into new quats and scales for baking).
- kabsch(rest [...,K,3], now [...,K,3]) -> (q, R, c_rest, c_now): batched rigid fit.
"""
from pd_tool.drivers.build import MIN_PER_CELL, NEIGHBORS, DriverSet, build_drivers, driver_count
from pd_tool.drivers.interpolate import (
    DriverInterpolator,
    apply_deformation,
    interpolate,
    kabsch,
)
from pd_tool.drivers.kmeans import DriverError, kmeans
from pd_tool.drivers.knn import knn, nearest_drivers

__all__ = [
    "MIN_PER_CELL",
    "NEIGHBORS",
    "DriverError",
    "DriverInterpolator",
    "DriverSet",
    "apply_deformation",
    "build_drivers",
    "driver_count",
    "interpolate",
    "kabsch",
    "kmeans",
    "knn",
    "nearest_drivers",
]
