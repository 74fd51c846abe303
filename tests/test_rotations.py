"""Quaternion helpers against each other and against known rotations (float64)."""
from __future__ import annotations

import math

import torch

from pd_tool.rotations import matrix_to_quat, quat_conjugate, quat_multiply, quat_to_matrix


def _random_quats(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    return torch.where(q[:, :1] < 0, -q, q)


def test_matrix_round_trip_all_angles() -> None:
    q = _random_quats(2000)
    # include 180-degree rotations, where w = 0 and a naive formula divides by zero
    q[:4] = torch.tensor([[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1], [0, 0.6, 0.8, 0]], dtype=torch.float64)
    back = matrix_to_quat(quat_to_matrix(q))
    # q and -q are the same rotation; compare up to sign
    assert torch.allclose((back * q).sum(1).abs(), torch.ones(len(q), dtype=torch.float64), atol=1e-12)


def test_product_matches_matrix_product() -> None:
    a, b = _random_quats(100, 1), _random_quats(100, 2)
    lhs = quat_to_matrix(quat_multiply(a, b))
    rhs = quat_to_matrix(a) @ quat_to_matrix(b)
    assert torch.allclose(lhs, rhs, atol=1e-12)
    ident = quat_multiply(a, quat_conjugate(a))
    assert torch.allclose(ident, torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand_as(ident), atol=1e-12)


def test_known_rotation() -> None:
    # 90 degrees about z takes x to y
    q = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=torch.float64)
    assert torch.allclose(quat_to_matrix(q) @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)
