"""Slow but obviously right twins of the driver operations (dense, float64), for tests."""
from __future__ import annotations

import torch
from torch import Tensor


def knn_ref(queries: Tensor, refs: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """Dense k nearest neighbours: (dist2 [N, k] ascending, idx [N, k])."""
    d2 = ((queries.double()[:, None, :] - refs.double()[None, :, :]) ** 2).sum(-1)
    return torch.topk(d2, k, dim=1, largest=False, sorted=True)


def lloyd_ref(points: Tensor, centres: Tensor, iters: int) -> tuple[Tensor, Tensor]:
    """Dense Lloyd iterations from given centres (no empty-cluster handling needed when
    the test data has none): (centres [k, 3] float64, labels [N])."""
    x = points.double()
    c = centres.double()
    labels = None
    for _ in range(iters):
        labels = torch.cdist(x, c).argmin(1)
        k = c.shape[0]
        sums = torch.zeros((k, 3), dtype=torch.float64).index_add_(0, labels, x)
        c = sums / torch.bincount(labels, minlength=k)[:, None].double()
    return c, labels


def kabsch_ref(rest: Tensor, now: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Textbook Kabsch by SVD with the reflection fix, float64.

    rest, now: [B, K, 3]. Returns (R [B, 3, 3], c_rest [B, 3], c_now [B, 3]) with
    now ~ R (rest - c_rest) + c_now.
    """
    P = rest.double()
    Y = now.double()
    cp, cy = P.mean(1), Y.mean(1)
    H = (P - cp[:, None]).transpose(1, 2) @ (Y - cy[:, None])  # sum P Y^T
    U, _, Vh = torch.linalg.svd(H)
    d = torch.sign(torch.linalg.det(Vh.transpose(1, 2) @ U.transpose(1, 2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(1, 2) @ D @ U.transpose(1, 2)
    return R, cp, cy


def interpolate_rigid_ref(
    rest_points: Tensor, drivers_rest: Tensor, drivers_now: Tensor, neighbors: Tensor
) -> tuple[Tensor, Tensor]:
    """Rigid interpolation via kabsch_ref: (points_now [N, 3], R [N, 3, 3]) float64."""
    R, cp, cy = kabsch_ref(drivers_rest[neighbors], drivers_now[neighbors])
    x = (R @ (rest_points.double() - cp)[:, :, None])[:, :, 0] + cy
    return x, R


def affine_ref(rest: Tensor, now: Tensor, R: Tensor, lam: Tensor) -> Tensor:
    """argmin_F sum_j |F P_j - Y_j|^2 + lam |F - R|^2 by a dense linear solve: [B, 3, 3]."""
    P = rest.double() - rest.double().mean(1, keepdim=True)
    Y = now.double() - now.double().mean(1, keepdim=True)
    G = P.transpose(1, 2) @ P + lam.double()[:, None, None] * torch.eye(3, dtype=torch.float64)
    rhs = Y.transpose(1, 2) @ P + lam.double()[:, None, None] * R.double()  # F G = rhs
    return torch.linalg.solve(G.transpose(1, 2), rhs.transpose(1, 2)).transpose(1, 2)
