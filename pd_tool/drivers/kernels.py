"""Warp device code for the forward-only rigid interpolation (bake, previews), and the
hash-grid pass of the exact k nearest neighbours (knn.py launches it; its reference is
_ref.knn_ref, the dense search).

One thread per Gaussian does what interpolate.DriverInterpolator does in torch (the
reference twin, tested against it): centroids of its K drivers at rest and now, the
cross-covariance S, Horn's 4x4 matrix, its top eigenvector by repeated squaring, then the
Gaussian's new centre and orientation. Fused, it reads each Gaussian's data once instead of
through ~100 torch kernels. Quaternions are (w, x, y, z) in the arrays (vec4), as in the
engine; warp's own wp.quat (x, y, z, w) is not used.
"""
from __future__ import annotations

import warp as wp

from pd_tool.core.quaternion import quat_matrix_wp, quat_multiply_wp, top_quaternion_wp


@wp.kernel(enable_backward=False)
def rigid_interpolate(
    drivers_rest: wp.array(dtype=wp.vec3),
    drivers_now: wp.array(dtype=wp.vec3),
    neighbors: wp.array2d(dtype=wp.int32),
    rest_points: wp.array(dtype=wp.vec3),
    rest_quats: wp.array(dtype=wp.vec4),
    squarings: int,
    points_out: wp.array(dtype=wp.vec3),
    quats_out: wp.array(dtype=wp.vec4),
):
    i = wp.tid()
    k_count = neighbors.shape[1]
    c_rest = wp.vec3(0.0)
    c_now = wp.vec3(0.0)
    for k in range(k_count):
        d = neighbors[i, k]
        c_rest += drivers_rest[d]
        c_now += drivers_now[d]
    inv = 1.0 / float(k_count)
    c_rest = c_rest * inv
    c_now = c_now * inv
    S = wp.mat33(0.0)
    for k in range(k_count):
        d = neighbors[i, k]
        S += wp.outer(drivers_rest[d] - c_rest, drivers_now[d] - c_now)
    q = top_quaternion_wp(S, squarings)
    points_out[i] = quat_matrix_wp(q) @ (rest_points[i] - c_rest) + c_now
    r = quat_multiply_wp(q, rest_quats[i])
    quats_out[i] = r / wp.length(r)


# --------------------------------------------------------------------------------------
# Exact k nearest neighbours on a hash grid (knn.py's first pass)
# --------------------------------------------------------------------------------------
KNN_MAX_K = 16  # neighbours a thread keeps in registers; knn.py searches larger k in torch
_KnnD = wp.types.vector(length=KNN_MAX_K, dtype=wp.float32)
_KnnI = wp.types.vector(length=KNN_MAX_K, dtype=wp.int32)


@wp.kernel(enable_backward=False)
def grid_knn(
    grid: wp.uint64,
    refs: wp.array(dtype=wp.vec3),
    queries: wp.array(dtype=wp.vec3),
    k: int,
    radius: float,
    sure2: float,
    out_d: wp.array2d(dtype=wp.float32),
    out_i: wp.array2d(dtype=wp.int64),
    exact: wp.array(dtype=wp.int32),
):
    """The k (<= KNN_MAX_K) nearest refs of query t among those the hash grid visits
    within `radius` (every ref that near, and some farther), by squared distance, ties by
    the lower index so that the grid's visiting order does not matter. exact[t] = 1 when
    the k-th lies within sqrt(sure2) (radius less a rounding margin): then no unvisited
    ref can be nearer. Missing entries are inf / 0."""
    t = wp.tid()
    p = queries[t]
    bd = _KnnD()
    bi = _KnnI()
    for s in range(KNN_MAX_K):
        bd[s] = wp.inf
        bi[s] = 0
    last = k - 1
    j = int(0)
    query = wp.hash_grid_query(grid, p, radius)
    while wp.hash_grid_query_next(query, j):
        r = refs[j] - p
        d2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
        if d2 < bd[last] or (d2 == bd[last] and j < bi[last]):
            s = last
            while s > 0 and (bd[s - 1] > d2 or (bd[s - 1] == d2 and bi[s - 1] > j)):
                bd[s] = bd[s - 1]
                bi[s] = bi[s - 1]
                s -= 1
            bd[s] = d2
            bi[s] = j
    for s in range(k):
        out_d[t, s] = bd[s]
        out_i[t, s] = wp.int64(bi[s])
    exact[t] = wp.where(bd[last] <= sure2, 1, 0)
