"""Quaternion helpers against each other and against known rotations (float64)."""
from __future__ import annotations

import math

import torch

from pd_tool.core.quaternion import matrix_to_quat, quat_conjugate, quat_multiply, quat_to_matrix


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


def test_numpy_matrix_matches_torch_and_repairs_broken_input() -> None:
    import numpy as np

    from pd_tool.core.quaternion import quat_to_matrix_np

    q = _random_quats(300, 3) * torch.rand(300, 1, dtype=torch.float64, generator=torch.Generator().manual_seed(4)).add(0.5)
    got = quat_to_matrix_np(q.numpy())
    assert np.allclose(got, quat_to_matrix(q, normalize=True).numpy(), atol=1e-12)
    # a zero quaternion is the identity; non-finite entries count as zero
    broken = np.array([[0.0, 0, 0, 0], [np.inf, 0, 0, 0], [np.nan, 1, 0, 0]])
    assert np.allclose(quat_to_matrix_np(broken), [np.eye(3), np.eye(3), np.diag([1.0, -1, -1])])


def test_warp_functions_match_torch() -> None:
    import warp as wp

    from pd_tool.core.quaternion import (
        quat_matrix_wp, quat_multiply_wp, rotation_from_cross_covariance, top_quaternion_wp,
    )

    @wp.kernel
    def apply(a: wp.array(dtype=wp.vec4), b: wp.array(dtype=wp.vec4), s: wp.array(dtype=wp.mat33),
              mats: wp.array(dtype=wp.mat33), prods: wp.array(dtype=wp.vec4), tops: wp.array(dtype=wp.vec4)):
        i = wp.tid()
        mats[i] = quat_matrix_wp(a[i])
        prods[i] = quat_multiply_wp(a[i], b[i])
        tops[i] = top_quaternion_wp(s[i], 12)

    n = 64
    a, b = _random_quats(n, 5), _random_quats(n, 6)
    S = torch.randn(n, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    out = [wp.zeros(n, dtype=t, device="cpu") for t in (wp.mat33, wp.vec4, wp.vec4)]
    wp.launch(apply, n, inputs=[wp.array(a.float().numpy(), dtype=wp.vec4, device="cpu"),
                                wp.array(b.float().numpy(), dtype=wp.vec4, device="cpu"),
                                wp.array(S.float().numpy(), dtype=wp.mat33, device="cpu"), *out], device="cpu")
    mats, prods, tops = (torch.from_numpy(o.numpy()).double() for o in out)
    assert torch.allclose(mats, quat_to_matrix(a), atol=1e-5)
    assert torch.allclose(prods, quat_multiply(a, b), atol=1e-5)
    assert torch.allclose(tops, rotation_from_cross_covariance(S), atol=1e-4)


def test_left_matrix_is_the_hamilton_product() -> None:
    from pd_tool.core.quaternion import quat_left_matrix

    a, b = _random_quats(1, seed=3)[0], _random_quats(500, seed=4)
    want = quat_multiply(a.expand(500, 4), b)
    got = b.numpy() @ quat_left_matrix(a.numpy()).T
    assert abs(got - want.numpy()).max() < 1e-14
