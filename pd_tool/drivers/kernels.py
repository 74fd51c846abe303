"""Warp device code for the forward-only rigid interpolation (bake, previews).

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
