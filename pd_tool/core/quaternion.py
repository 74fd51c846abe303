"""Quaternions in (w, x, y, z) order, the engine's one convention, in torch, numpy and warp.

- torch (batched over leading dimensions, differentiable): the Hamilton product and the
  rotation matrix as small bilinear forms (one matmul instead of thirty element-wise
  kernels on a GPU), and the best rotation for a cross-covariance through Horn's 4x4
  matrix and a power method (no SVD or eigh, whose backward is inf/NaN for repeated
  eigenvalues; see drivers/interpolate.py).
- numpy: rotation matrices for file I/O and preparation, robust to unnormalised input.
- warp (`@wp.func`, device code): the same matrix, product and Horn rotation for the
  kernels of the rasteriser and the rigid interpolation.

warp's own wp.quat is (x, y, z, w) and is not used; USD's is converted at the file edge.
"""
from __future__ import annotations

import math

import numpy as np
import torch
import warp as wp
from torch import Tensor

# Squarings of Horn's shifted 4x4 matrix: the power method runs 2^12 steps, enough for
# float64 precision unless a neighbourhood is nearly a line (see
# rotation_from_cross_covariance).
POWER_SQUARINGS = 12

__all__ = [
    "POWER_SQUARINGS", "horn_matrix", "matrix_to_quat", "quat_conjugate", "quat_matrix_wp", "quat_multiply",
    "quat_multiply_wp", "quat_to_matrix", "quat_to_matrix_np", "rotate_quats", "rotation_from_cross_covariance",
    "top_quaternion_wp",
]

# --------------------------------------------------------------------------- torch


def _bilinear_basis(rows: list[str]) -> Tensor:
    """[16, len(rows)] float64 coefficients of c_k = sum_ij B[4i+j, k] a_i b_j, from rows of
    text such as "+0*0 -1*1": each term is sign, index into a, index into b."""
    B = torch.zeros(16, len(rows), dtype=torch.float64)
    for k, row in enumerate(rows):
        for term in row.split():
            sign, i, j = (1.0 if term[0] == "+" else -1.0), int(term[1]), int(term[3])
            B[4 * i + j, k] += sign
    return B


_QMUL = _bilinear_basis([
    "+0*0 -1*1 -2*2 -3*3", "+0*1 +1*0 +2*3 -3*2", "+0*2 -1*3 +2*0 +3*1", "+0*3 +1*2 -2*1 +3*0",
])
# Row-major rotation matrix from the products q_i q_j; the constant 1 of the diagonal is
# written as w^2 + x^2 + y^2 + z^2, so the form is exact for unit quaternions only.
_QMAT = _bilinear_basis([
    "+0*0 +1*1 -2*2 -3*3", "+1*2 +2*1 -0*3 -3*0", "+1*3 +3*1 +0*2 +2*0",
    "+1*2 +2*1 +0*3 +3*0", "+0*0 -1*1 +2*2 -3*3", "+2*3 +3*2 -0*1 -1*0",
    "+1*3 +3*1 -0*2 -2*0", "+2*3 +3*2 +0*1 +1*0", "+0*0 -1*1 -2*2 +3*3",
])


def _horn_basis() -> Tensor:
    """[9, 16] map from S (row-major) to Horn's 4x4 matrix (row-major)."""
    sym = {  # entry (r, c) of N as signed S entries "ab"
        (0, 0): "+xx +yy +zz", (0, 1): "+yz -zy", (0, 2): "+zx -xz", (0, 3): "+xy -yx",
        (1, 1): "+xx -yy -zz", (1, 2): "+xy +yx", (1, 3): "+zx +xz",
        (2, 2): "-xx +yy -zz", (2, 3): "+yz +zy", (3, 3): "-xx -yy +zz",
    }
    axis = {"x": 0, "y": 1, "z": 2}
    B = torch.zeros(9, 16, dtype=torch.float64)
    for (r, c), text in sym.items():
        for term in text.split():
            k = 3 * axis[term[1]] + axis[term[2]]
            sign = 1.0 if term[0] == "+" else -1.0
            B[k, 4 * r + c] += sign
            if r != c:
                B[k, 4 * c + r] += sign
    return B


_HORN = _horn_basis()
_CACHE: dict = {}


def _basis(name: str, B: Tensor, like: Tensor) -> Tensor:
    key = (name, like.dtype, like.device)
    if key not in _CACHE:
        _CACHE[key] = B.to(like.device, like.dtype)
    return _CACHE[key]


def _bilinear(a: Tensor, b: Tensor, name: str, B: Tensor) -> Tensor:
    ab = (a[..., :, None] * b[..., None, :]).reshape(a.shape[:-1] + (16,))
    return ab @ _basis(name, B, ab)


def quat_left_matrix(q: np.ndarray) -> np.ndarray:
    """[4, 4] L with q * p = L @ p for a wxyz quaternion q [4] and any p [4]: rotating many
    quaternions by one is then a single matrix product, rows @ L.T."""
    w, x, y, z = np.asarray(q, np.float64)
    return np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of wxyz quaternions [..., 4] (apply b, then a)."""
    a, b = torch.broadcast_tensors(a, b)
    return _bilinear(a, b, "qmul", _QMUL)


def quat_conjugate(q: Tensor) -> Tensor:
    """Inverse of a unit quaternion [..., 4]."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_to_matrix(q: Tensor, normalize: bool = False) -> Tensor:
    """Rotation matrices [..., 3, 3] of wxyz quaternions [..., 4].

    The quaternions must be unit unless `normalize` is set (the form scales by |q|^2)."""
    if normalize:
        q = q / q.norm(dim=-1, keepdim=True)
    return _bilinear(q, q, "qmat", _QMAT).reshape(q.shape[:-1] + (3, 3))


def rotate_quats(q_rot: Tensor, quats_rest: Tensor) -> Tensor:
    """Orientation after rotating by q_rot: normalise(q_rot * quats_rest), wxyz [..., 4]."""
    q = quat_multiply(q_rot, quats_rest)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def horn_matrix(S: Tensor) -> Tensor:
    """Horn's symmetric 4x4 matrix [..., 4, 4] of a cross-covariance S [..., 3, 3].

    S[a, b] = sum_j P_j[a] Y_j[b] (rest offsets P, current offsets Y). Its top eigenvector
    is the wxyz quaternion of the rotation R maximising sum_j Y_j . R P_j.
    """
    flat = S.reshape(S.shape[:-2] + (9,))
    return (flat @ _basis("horn", _HORN, flat)).reshape(S.shape[:-2] + (4, 4))


def rotation_from_cross_covariance(S: Tensor, squarings: int = POWER_SQUARINGS) -> Tensor:
    """Best proper rotation for a cross-covariance S [..., 3, 3] as wxyz quaternions [..., 4].

    Power method by repeated squaring of N + s I, where s = sqrt(3) |S|_F bounds |eig(N)|
    so that the shifted matrix is positive semi-definite and its top eigenvector is N's.
    Convergence per squaring: the ratio (lambda_2 + s) / (lambda_1 + s) is squared; it is
    at most about 0.55 for planar and 0.33 for well-spread neighbourhoods, so 12
    squarings reach float64 precision unless the neighbourhood is nearly a line (where
    the rotation about that line is undetermined anyway) or nearly a mirror image of
    its rest state. S = 0 gives the identity.
    Returns the quaternion with w >= 0.
    """
    N = horn_matrix(S)
    tiny = torch.finfo(S.dtype).tiny ** 0.5
    s = math.sqrt(3.0) * torch.sqrt((S * S).sum((-1, -2)) + tiny * tiny) + tiny
    eye = torch.eye(4, dtype=S.dtype, device=S.device)
    M = N + s[..., None, None] * eye
    # (lambda_1 + s) / (2 s) >= (1 + sqrt 3) / (2 sqrt 3) = 0.79, so the top eigenvalue of
    # M / (2 s) shrinks at most to 0.79^8 over three squarings: normalising every third
    # squaring is enough to stay far from underflow (and saves GPU kernels).
    M = M / (2.0 * s)[..., None, None]
    for i in range(squarings):
        if i % 3 == 2:
            M = M / M.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]  # trace > 0: PSD
        M = M @ M
    # M ~ q q^T (times a scale): the column on the largest diagonal entry is a safe pick
    # (q_j^2 >= 1/4 there).
    j = M.diagonal(dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(M, -1, j[..., None, None].expand(M.shape[:-1] + (1,)))[..., 0]
    q = col / col.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def matrix_to_quat(R: Tensor) -> Tensor:
    """wxyz unit quaternions [..., 4] (w >= 0) of rotation matrices [..., 3, 3]."""
    # Shepperd's method through Horn's matrix: the quaternion of R is the top eigenvector
    # of horn_matrix(R^T) (R is its own best rotation). Stable at 180 degrees.
    return rotation_from_cross_covariance(R.transpose(-1, -2))


# --------------------------------------------------------------------------- numpy


def quat_to_matrix_np(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] float64 of wxyz quaternions [N, 4] of any norm.

    A zero or non-finite quaternion (a broken splat file) gives the identity."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where(np.isfinite(q), q, 0.0)
    norm = np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    q = np.where(norm > 1e-12, q / np.maximum(norm, 1e-12), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = np.ascontiguousarray(q.T)  # contiguous columns: strided ones run several times slower
    # written in place: nested stacks copy every entry twice
    R = np.empty((len(q), 3, 3))
    xx, yy, zz = x * x, y * y, z * z
    R[:, 0, 0], R[:, 1, 1], R[:, 2, 2] = 1 - 2 * (yy + zz), 1 - 2 * (xx + zz), 1 - 2 * (xx + yy)
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R[:, 0, 1], R[:, 1, 0] = 2 * (xy - wz), 2 * (xy + wz)
    R[:, 0, 2], R[:, 2, 0] = 2 * (xz + wy), 2 * (xz - wy)
    R[:, 1, 2], R[:, 2, 1] = 2 * (yz - wx), 2 * (yz + wx)
    return R


# --------------------------------------------------------------------------- warp


@wp.func
def quat_matrix_wp(q: wp.vec4) -> wp.mat33:
    """Rotation matrix of a unit wxyz quaternion (normalise first where q may drift)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def quat_multiply_wp(a: wp.vec4, b: wp.vec4) -> wp.vec4:
    """Hamilton product a * b of wxyz quaternions."""
    return wp.vec4(
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@wp.func
def top_quaternion_wp(S: wp.mat33, squarings: int) -> wp.vec4:
    """wxyz quaternion (w >= 0) of the best rotation for cross-covariance S: the float32
    device twin of rotation_from_cross_covariance."""
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
