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


@wp.func
def top_quaternion(S: wp.mat33, squarings: int) -> wp.vec4:
    """wxyz quaternion (w >= 0) of the best rotation for cross-covariance S (Horn)."""
    sxx, sxy, sxz = S[0, 0], S[0, 1], S[0, 2]
    syx, syy, syz = S[1, 0], S[1, 1], S[1, 2]
    szx, szy, szz = S[2, 0], S[2, 1], S[2, 2]
    fro = wp.sqrt(wp.ddot(S, S) + 1.0e-38)
    s = 1.7320508075688772 * fro + 1.0e-19
    M = wp.mat44(
        sxx + syy + szz + s, syz - szy, szx - sxz, sxy - syx,
        syz - szy, sxx - syy - szz + s, sxy + syx, szx + sxz,
        szx - sxz, sxy + syx, -sxx + syy - szz + s, syz + szy,
        sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz + s,
    )
    M = M * (1.0 / (2.0 * s))
    for i in range(squarings):
        if i % 3 == 2:
            M = M * (1.0 / (M[0, 0] + M[1, 1] + M[2, 2] + M[3, 3]))
        M = M @ M
    j = int(0)
    best = M[0, 0]
    for c in range(1, 4):
        if M[c, c] > best:
            best = M[c, c]
            j = c
    q = wp.normalize(wp.vec4(M[0, j], M[1, j], M[2, j], M[3, j]))
    if q[0] < 0.0:
        q = -q
    return q


@wp.func
def quat_mul_wxyz(a: wp.vec4, b: wp.vec4) -> wp.vec4:
    return wp.vec4(
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@wp.func
def quat_matrix_wxyz(q: wp.vec4) -> wp.mat33:
    w, x, y, z = q[0], q[1], q[2], q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


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
    q = top_quaternion(S, squarings)
    points_out[i] = quat_matrix_wxyz(q) @ (rest_points[i] - c_rest) + c_now
    r = quat_mul_wxyz(q, rest_quats[i])
    quats_out[i] = r / wp.length(r)
