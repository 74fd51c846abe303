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


import torch
from torch import Tensor

from pd_tool.core.quaternion import (
    POWER_SQUARINGS,
    matrix_to_quat,
    quat_to_matrix,
    rotate_quats,
    rotation_from_cross_covariance,
)

AFFINE_REG = 1e-3  # pull of the affine fit towards the rotation, relative to mean(eig(S))
MODES = ("rigid", "affine")


# --------------------------------------------------------------------------- rigid fit


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
        backend: "auto" (default): a fused warp kernel for rigid float32 calls that need no
            gradient (bake), torch otherwise; "torch" or "warp" to force one.
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
        backend: str = "auto",
    ):
        if mode not in MODES:
            raise ValueError(f"interpolate: mode {mode!r} is not one of {MODES}")
        if backend not in ("auto", "torch", "warp"):
            raise ValueError(f"interpolate: backend {backend!r} is not 'auto', 'torch' or 'warp'")
        if backend == "warp" and (mode != "rigid" or rest_points.dtype != torch.float32):
            raise ValueError("interpolate: the warp backend does rigid float32 interpolation only")
        self.backend = backend
        self._warp = None  # rest-state warp arrays, made on first use
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
        self.rest_points = rest_points
        self.drivers_rest = drivers_rest
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
        if self._use_warp(drivers_now):
            return self._warp_rigid(drivers_now)
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


    def _use_warp(self, drivers_now: Tensor) -> bool:
        if self.backend == "warp":
            return True
        return (
            self.backend == "auto"
            and self.mode == "rigid"
            and drivers_now.dtype == torch.float32
            and self.rest_points.dtype == torch.float32
            and not (torch.is_grad_enabled() and drivers_now.requires_grad)
        )

    def _warp_rigid(self, drivers_now: Tensor) -> tuple[Tensor, Tensor]:
        """Forward-only fused kernel (kernels.rigid_interpolate); no autograd."""
        import warp as wp

        from pd_tool.core.device import init_warp_quietly
        from pd_tool.drivers.kernels import rigid_interpolate

        init_warp_quietly()
        if self._warp is None:
            keep = [
                self.drivers_rest.detach().float().contiguous(),
                self.neighbors.to(torch.int32).contiguous(),
                self.rest_points.detach().float().contiguous(),
                self.rest_quats.detach().float().contiguous(),
            ]
            self._warp = (keep, [
                wp.from_torch(keep[0], dtype=wp.vec3),
                wp.from_torch(keep[1], dtype=wp.int32),
                wp.from_torch(keep[2], dtype=wp.vec3),
                wp.from_torch(keep[3], dtype=wp.vec4),
            ])
        _, (d_rest, nb, x_rest, q_rest) = self._warp
        n = self.rest_points.shape[0]
        d_now = drivers_now.detach().float().contiguous()
        points = torch.empty((n, 3), dtype=torch.float32, device=d_now.device)
        quats = torch.empty((n, 4), dtype=torch.float32, device=d_now.device)
        # On CUDA, launch on torch's current stream so that torch and warp work is ordered.
        stream = wp.stream_from_torch(d_now.device) if d_now.is_cuda else None
        wp.launch(
            rigid_interpolate, dim=n, device=str(d_now.device) if d_now.is_cuda else "cpu", stream=stream,
            inputs=[d_rest, wp.from_torch(d_now, dtype=wp.vec3), nb, x_rest, q_rest, self.squarings],
            outputs=[wp.from_torch(points, dtype=wp.vec3), wp.from_torch(quats, dtype=wp.vec4)],
        )
        return points, quats


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
