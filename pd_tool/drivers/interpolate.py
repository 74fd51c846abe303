"""Move every Gaussian with its nearest driving particles: batched rigid (Kabsch) fit.

For Gaussian i with neighbour drivers j in n(i) (8 in the paper), rest positions P_j and
current positions Y_j, the rigid fit is the rotation R_i maximising
sum_j (Y_j - cY) . R_i (P_j - cP) about the neighbours' centroids cP, cY (Kabsch with
the reflection fix: R_i is always a proper rotation). The Gaussian then moves to
x_i = R_i (X_i - cP) + cY and turns by R_i: q_i = q(R_i) * q_rest_i.

Why not an SVD: torch's SVD (and eigh) backward divides by differences of singular values
(eigenvalues); a pure translation of a symmetric neighbourhood has repeated ones and the
gradient becomes inf/NaN. We use Horn's closed-form quaternion instead: q(R_i) is the top
eigenvector of a symmetric 4 x 4 matrix built from the cross-covariance, and we take it by
repeated squaring of the shifted matrix (a power method): only products and
normalisations, so the gradient is finite everywhere and exact for the unrolled
computation (tests compare with float64 finite differences).

Default mode "rigid" (the paper's): Gaussians keep their shape, nothing can invert or
shear, and it is robust when the 8 drivers are nearly coplanar (thin parts). "affine"
additionally fits the local linear deformation F_i, so that stretched regions stretch
their Gaussians (covariance F Sigma F^T); use it for visibly stretching materials.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

POWER_SQUARINGS = 12  # squarings of the 4x4 matrix: the power method runs 2^12 steps
AFFINE_REG = 1e-3  # pull of the affine fit towards the rotation, relative to mean(eig(S))
MODES = ("rigid", "affine")


# --------------------------------------------------------------------------- quaternions


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a * b of wxyz quaternions [..., 4] (apply b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of unit wxyz quaternions [..., 4]."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(q.shape[:-1] + (3, 3))


def rotate_quats(q_rot: Tensor, quats_rest: Tensor) -> Tensor:
    """Orientation after rotating by q_rot: normalise(q_rot * quats_rest), wxyz [..., 4]."""
    q = quat_multiply(q_rot, quats_rest)
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


# --------------------------------------------------------------------------- rigid fit


def horn_matrix(S: Tensor) -> Tensor:
    """Horn's symmetric 4x4 matrix [..., 4, 4] of a cross-covariance S [..., 3, 3].

    S[a, b] = sum_j P_j[a] Y_j[b] (rest offsets P, current offsets Y). Its top eigenvector
    is the wxyz quaternion of the rotation R maximising sum_j Y_j . R P_j.
    """
    sxx, sxy, sxz = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    syx, syy, syz = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    szx, szy, szz = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    rows = [
        sxx + syy + szz, syz - szy, szx - sxz, sxy - syx,
        syz - szy, sxx - syy - szz, sxy + syx, szx + sxz,
        szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy,
        sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz,
    ]
    return torch.stack(rows, -1).reshape(S.shape[:-2] + (4, 4))


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
    for _ in range(squarings):
        M = M / M.diagonal(dim1=-2, dim2=-1).sum(-1)[..., None, None]  # trace > 0: PSD
        M = M @ M
    # M ~ q q^T (times a scale): the column on the largest diagonal entry is a safe pick
    # (q_j^2 >= 1/4 there).
    j = M.diagonal(dim1=-2, dim2=-1).argmax(-1)
    col = torch.gather(M, -1, j[..., None, None].expand(M.shape[:-1] + (1,)))[..., 0]
    q = col / col.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def kabsch(rest: Tensor, now: Tensor, squarings: int = POWER_SQUARINGS) -> tuple[Tensor, Tensor, Tensor]:
    """Batched rigid fit between point sets: now ~ R (rest - c_rest) + c_now.

    Args:
        rest: [..., K, 3] points at rest; now: [..., K, 3] the same points now.
    Returns:
        (q [..., 4] wxyz with w >= 0, R [..., 3, 3], c_rest [..., 3], c_now [..., 3]).
        A reflection is never returned (Kabsch's reflection fix).
    """
    c_rest = rest.mean(-2)
    c_now = now.mean(-2)
    P = rest - c_rest[..., None, :]
    S = P.transpose(-1, -2) @ (now - c_now[..., None, :])
    q = rotation_from_cross_covariance(S, squarings)
    return q, quat_to_matrix(q), c_rest, c_now


# --------------------------------------------------------------------------- interpolator


def _inv3_spd(A: Tensor) -> Tensor:
    """Inverse of symmetric positive-definite 3x3 matrices [..., 3, 3] by the adjugate."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 1], A[..., 1, 2], A[..., 2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    c11 = a * f - c * c
    c12 = b * c - a * e
    c22 = a * d - b * b
    det = a * c00 + b * c01 + c * c02
    adj = torch.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], -1).reshape(A.shape)
    return adj / det[..., None, None]


class DriverInterpolator:
    """Rest-state quantities of the interpolation, computed once; call it every frame.

    Args:
        rest_points: [N, 3] float Gaussian centres at rest (simulation units).
        rest_quats: [N, 4] wxyz unit Gaussian orientations at rest.
        drivers_rest: [Q, 3] driver positions at rest (same device and dtype).
        neighbors: [N, K] long indices into drivers (K = 8 from build_drivers).
        mode: "rigid" (default) or "affine" (see the module docstring).
        squarings: power-method squarings of the rotation fit.
        affine_reg: affine mode: weight of |F - R|^2 relative to the mean eigenvalue of
            the neighbours' rest second moment (keeps thin neighbourhoods from collapsing
            across their plane; biases F towards R by about affine_reg / anisotropy).
    """

    def __init__(
        self,
        rest_points: Tensor,
        rest_quats: Tensor,
        drivers_rest: Tensor,
        neighbors: Tensor,
        mode: str = "rigid",
        squarings: int = POWER_SQUARINGS,
        affine_reg: float = AFFINE_REG,
    ):
        if mode not in MODES:
            raise ValueError(f"interpolate: mode {mode!r} is not one of {MODES}")
        n = rest_points.shape[0]
        if rest_quats.shape != (n, 4) or neighbors.ndim != 2 or neighbors.shape[0] != n:
            raise ValueError(
                f"interpolate: expected rest_points [N,3], rest_quats [N,4], neighbors [N,K]; "
                f"got {tuple(rest_points.shape)}, {tuple(rest_quats.shape)}, {tuple(neighbors.shape)}"
            )
        self.mode = mode
        self.squarings = squarings
        self.neighbors = neighbors
        self.rest_quats = rest_quats
        nb_rest = drivers_rest[neighbors]  # [N, K, 3]
        self.c_rest = nb_rest.mean(1)
        self.P = nb_rest - self.c_rest[:, None, :]  # [N, K, 3] rest offsets, sum_j P_j = 0
        self.offset = rest_points - self.c_rest  # [N, 3] Gaussian relative to the centroid
        if mode == "affine":
            G = self.P.transpose(1, 2) @ self.P  # [N, 3, 3] rest second moment
            lam = affine_reg * G.diagonal(dim1=1, dim2=2).sum(-1) / 3.0
            lam = lam + torch.finfo(G.dtype).tiny ** 0.5
            self.lam = lam
            self.G_inv = _inv3_spd(G + lam[:, None, None] * torch.eye(3, dtype=G.dtype, device=G.device))

    def __call__(self, drivers_now: Tensor) -> tuple[Tensor, ...]:
        """Gaussians for driver positions drivers_now [Q, 3] (differentiable in it).

        Returns:
            rigid: (points_now [N, 3], quats_now [N, 4] wxyz);
            affine: (points_now, quats_now, F [N, 3, 3]) with F the local deformation:
            the Gaussian's covariance becomes F Sigma_rest F^T (see apply_deformation);
            quats_now is the rigid part's rotation in both modes.
        """
        Y = drivers_now[self.neighbors]  # [N, K, 3]
        c_now = Y.mean(1)
        # Centred although sum_j P_j = 0: in float32, far from the origin, the uncentred
        # products lose the digits that the affine solve amplifies.
        S = self.P.transpose(1, 2) @ (Y - c_now[:, None, :])  # S[a, b] = sum_j P_j[a] Y_j[b]
        q = rotation_from_cross_covariance(S, self.squarings)
        R = quat_to_matrix(q)
        quats_now = rotate_quats(q, self.rest_quats)
        if self.mode == "rigid":
            points_now = (R @ self.offset[:, :, None])[:, :, 0] + c_now
            return points_now, quats_now
        # Least squares of sum_j |F P_j - Y_j|^2 + lam |F - R|^2: thin (coplanar)
        # neighbourhoods keep the rotation across the plane instead of collapsing it.
        F = (S.transpose(1, 2) + self.lam[:, None, None] * R) @ self.G_inv
        points_now = (F @ self.offset[:, :, None])[:, :, 0] + c_now
        return points_now, quats_now, F


def interpolate(
    rest_points: Tensor,
    rest_quats: Tensor,
    drivers_rest: Tensor,
    drivers_now: Tensor,
    neighbors: Tensor,
    mode: str = "rigid",
) -> tuple[Tensor, ...]:
    """Move Gaussians with their neighbour drivers (one call; see DriverInterpolator).

    Args:
        rest_points: [N, 3] Gaussian centres at rest; rest_quats: [N, 4] wxyz unit.
        drivers_rest: [Q, 3] drivers at rest; drivers_now: [Q, 3] drivers now
            (gradients flow to drivers_now).
        neighbors: [N, K] long, each Gaussian's nearest drivers at rest.
        mode: "rigid" (default, the paper's: shape-preserving and robust) or "affine".
    Returns:
        rigid: (points_now [N, 3], quats_now [N, 4] wxyz);
        affine: (points_now, quats_now, F [N, 3, 3]).
    """
    return DriverInterpolator(rest_points, rest_quats, drivers_rest, neighbors, mode)(drivers_now)


def apply_deformation(quats: Tensor, scales: Tensor, F: Tensor) -> tuple[Tensor, Tensor]:
    """Orientation and scales of Gaussians whose covariance R S^2 R^T is deformed by F.

    Forward-only (for baking the affine mode): the eigen-decomposition's gradient is not
    safe for isotropic Gaussians.

    Args:
        quats: [N, 4] wxyz rest orientation; scales: [N, 3] linear std-devs; F: [N, 3, 3].
    Returns:
        (quats [N, 4] wxyz with w >= 0, scales [N, 3] linear std-devs, descending).
    """
    with torch.no_grad():
        R = quat_to_matrix(quats).double()
        L = F.double() @ R * scales.double()[:, None, :]  # F R S
        cov = L @ L.transpose(1, 2)
        evals, evecs = torch.linalg.eigh(cov)
        evals, evecs = evals.flip(-1), evecs.flip(-1)
        det = torch.linalg.det(evecs)
        evecs = evecs * torch.where(det < 0, -1.0, 1.0)[:, None, None].to(evecs)
        q = matrix_to_quat(evecs)
        return q.to(quats.dtype), evals.clamp_min(0).sqrt().to(scales.dtype)


def matrix_to_quat(R: Tensor) -> Tensor:
    """wxyz unit quaternions [..., 4] (w >= 0) of rotation matrices [..., 3, 3]."""
    # Shepperd's method through Horn's matrix: the quaternion of R is the top eigenvector
    # of horn_matrix(R^T) (R is its own best rotation).
    return rotation_from_cross_covariance(R.transpose(-1, -2))
