"""Rigid / affine interpolation of Gaussians from driving particles."""
from __future__ import annotations

import math

import pytest
import torch

from pd_tool.core.quaternion import matrix_to_quat, quat_multiply, quat_to_matrix, rotate_quats
from pd_tool.drivers import DriverInterpolator, apply_deformation, interpolate, kabsch
from pd_tool.drivers._ref import affine_ref, interpolate_rigid_ref, kabsch_ref
from pd_tool.drivers.interpolate import AFFINE_REG
from pd_tool.drivers.knn import nearest_drivers

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# float32 coordinates of order 1: a rotation is recovered to a few ulp times the
# condition of the neighbourhood; 1e-5 is the bound we hold it to.
TOL32 = 1e-5
TOL64 = 1e-10


def random_rotations(n: int, gen: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    q = q / q.norm(dim=1, keepdim=True)
    return quat_to_matrix(q).to(dtype)


def same_rotation_quats(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Max deviation between unit quaternions up to sign."""
    return torch.minimum((a - b).abs().amax(-1), (a + b).abs().amax(-1)).max()


@pytest.mark.parametrize("dtype,tol", [(torch.float32, TOL32), (torch.float64, TOL64)])
def test_kabsch_recovers_random_rigid_motion(device, dtype, tol):
    gen = torch.Generator().manual_seed(1)
    b = 2000
    R = random_rotations(b, gen)
    t = torch.randn(b, 1, 3, generator=gen, dtype=torch.float64)
    rest = torch.rand(b, 8, 3, generator=gen, dtype=torch.float64) - 0.5
    now = rest @ R.transpose(1, 2) + t
    q, R_fit, c_rest, c_now = kabsch(rest.to(device, dtype), now.to(device, dtype))
    assert (R_fit.cpu().double() - R).abs().max() < tol
    moved = (R_fit @ (rest.to(device, dtype) - c_rest[:, None]).transpose(1, 2)).transpose(1, 2) + c_now[:, None]
    assert (moved.cpu().double() - now).abs().max() < tol
    assert (q[:, 0] >= 0).all()


def test_kabsch_matches_svd_reference_on_non_rigid_data(device):
    gen = torch.Generator().manual_seed(2)
    rest = torch.randn(3000, 8, 3, generator=gen, dtype=torch.float64)
    now = rest @ random_rotations(3000, gen).transpose(1, 2) + 0.3 * torch.randn(3000, 8, 3, generator=gen, dtype=torch.float64)
    # Mirror a third of them: the reference's reflection fix must be matched.
    now[:1000, :, 0] *= -1
    R_ref, _, _ = kabsch_ref(rest, now)
    _, R, _, _ = kabsch(rest.to(device), now.to(device))
    assert (R.cpu() - R_ref).abs().max() < 1e-9
    assert torch.allclose(torch.linalg.det(R.cpu()), torch.ones(3000, dtype=torch.float64))


def test_kabsch_coplanar_and_degenerate_neighbourhoods(device):
    gen = torch.Generator().manual_seed(3)
    R = random_rotations(500, gen)
    rest = torch.randn(500, 8, 3, generator=gen, dtype=torch.float64)
    rest[..., 2] = 0.0  # thin part: drivers on a plane
    now = rest @ R.transpose(1, 2) + 1.0
    _, R_fit, _, _ = kabsch(rest.to(device), now.to(device))
    assert (R_fit.cpu() - R).abs().max() < 1e-9
    # All drivers on one point: no rotation information; identity, not NaN.
    same = torch.zeros(4, 8, 3, dtype=torch.float64, device=device)
    q, R0, _, _ = kabsch(same, same + 2.0)
    assert torch.allclose(R0.cpu(), torch.eye(3, dtype=torch.float64).expand(4, 3, 3))


def _scene(n: int, q_count: int, gen: torch.Generator, dtype=torch.float64):
    drivers = torch.rand(q_count, 3, generator=gen, dtype=dtype)
    points = torch.rand(n, 3, generator=gen, dtype=dtype)
    quats = torch.randn(n, 4, generator=gen, dtype=dtype)
    quats = quats / quats.norm(dim=1, keepdim=True)
    nb = nearest_drivers(points, drivers, 8)
    return points, quats, drivers, nb


@pytest.mark.parametrize("mode", ["rigid", "affine"])
def test_rigidly_moved_drivers_move_every_gaussian_rigidly(device, mode):
    gen = torch.Generator().manual_seed(4)
    points, quats, drivers, nb = _scene(5000, 400, gen, torch.float32)
    R = random_rotations(1, gen)[0].float()
    t = torch.tensor([0.3, -1.2, 2.0])
    out = interpolate(
        points.to(device), quats.to(device), drivers.to(device),
        (drivers @ R.T + t).to(device), nb.to(device), mode=mode,
    )
    p_now, q_now = out[0].cpu(), out[1].cpu()
    assert (p_now - (points @ R.T + t)).abs().max() < TOL32 * 10  # coordinates up to ~3
    q_R = matrix_to_quat(R.double()).float()
    assert same_rotation_quats(q_now, rotate_quats(q_R.expand(5000, 4), quats)) < TOL32 * 10
    if mode == "affine":
        assert (out[2].cpu() - R).abs().max() < 1e-4


def test_rigid_interpolation_matches_reference_under_deformation(device):
    gen = torch.Generator().manual_seed(5)
    points, quats, drivers, nb = _scene(3000, 300, gen)
    # A smooth bend plus noise: not rigid anywhere.
    now = drivers.clone()
    now[:, 0] += 0.2 * torch.sin(3 * drivers[:, 1])
    now += 0.01 * torch.randn(now.shape, generator=gen, dtype=torch.float64)
    p_now, q_now = interpolate(points.to(device), quats.to(device), drivers.to(device), now.to(device), nb.to(device))
    p_ref, R_ref = interpolate_rigid_ref(points, drivers, now, nb)
    assert (p_now.cpu() - p_ref).abs().max() < 1e-9
    assert (quat_to_matrix(q_now.cpu()) - R_ref @ quat_to_matrix(quats)).abs().max() < 1e-9


def test_affine_matches_reference_and_stretches(device):
    gen = torch.Generator().manual_seed(6)
    points, quats, drivers, nb = _scene(2000, 300, gen)
    A = torch.tensor([[1.3, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.1]], dtype=torch.float64)
    now = drivers @ A.T + torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    now_noisy = now + 0.01 * torch.randn(now.shape, generator=gen, dtype=torch.float64)
    interp = DriverInterpolator(points.to(device), quats.to(device), drivers.to(device), nb.to(device), mode="affine")
    p, q, F = interp(now_noisy.to(device))
    _, R, _, _ = kabsch(drivers[nb], now_noisy[nb])
    F_ref = affine_ref(drivers[nb], now_noisy[nb], R, interp.lam.cpu())
    assert (F.cpu() - F_ref).abs().max() < 1e-9
    # A pure affine motion is reproduced exactly without the regulariser, and up to a
    # bias of the order of the regulariser with it.
    p_exact = A @ points.T
    p_exact = p_exact.T + torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    free = DriverInterpolator(points, quats, drivers, nb, mode="affine", affine_reg=1e-12)
    p, q, F = free(now)
    assert (F - A).abs().max() < 1e-8
    assert (p - p_exact).abs().max() < 1e-8
    p, q, F = interp(now.to(device))
    assert (F.cpu() - A).abs().mean() < AFFINE_REG
    assert (p.cpu() - p_exact).abs().mean() < AFFINE_REG


def test_affine_keeps_thickness_of_coplanar_neighbourhoods():
    # Drivers on the plane z = 0 give no information across it: F must rotate the
    # normal (like the rigid fit), not collapse it to zero.
    gen = torch.Generator().manual_seed(7)
    drivers = torch.rand(200, 3, generator=gen, dtype=torch.float64)
    drivers[:, 2] = 0
    points = torch.rand(500, 3, generator=gen, dtype=torch.float64) * torch.tensor([1, 1, 0.01], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(500, 4)
    nb = nearest_drivers(points, drivers, 8)
    R = random_rotations(1, gen)[0]
    _, _, F = interpolate(points, quats, drivers, drivers @ R.T, nb, mode="affine")
    normal = F @ torch.tensor([0, 0, 1.0], dtype=torch.float64)
    assert (normal - R[:, 2]).abs().max() < 1e-9


@pytest.mark.parametrize("mode", ["rigid", "affine"])
@pytest.mark.parametrize("motion", ["deformed", "translation", "rotation"])
def test_gradients_match_finite_differences(mode, motion):
    gen = torch.Generator().manual_seed(8)
    if motion == "deformed":
        points, quats, drivers, nb = _scene(6, 12, gen)
        now = drivers + 0.1 * torch.randn(drivers.shape, generator=gen, dtype=torch.float64)
    else:
        # Cube corners: every singular value of the cross-covariance is equal, where an
        # SVD (or eigh) backward divides by zero.
        drivers = torch.tensor(
            [[i, j, k] for i in (0.0, 1.0) for j in (0.0, 1.0) for k in (0.0, 1.0)], dtype=torch.float64
        )
        points = torch.rand(4, 3, generator=gen, dtype=torch.float64)
        quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(4, 4).clone()
        nb = torch.arange(8).expand(4, 8).clone()
        if motion == "translation":
            now = drivers + torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64)
        else:
            now = drivers @ random_rotations(1, gen)[0].T
    interp = DriverInterpolator(points, quats, drivers, nb, mode=mode)

    def f(x):
        return torch.cat([o.reshape(-1) for o in interp(x)])

    x = now.clone().requires_grad_(True)
    grad = torch.autograd.grad(f(x).square().sum(), x)[0]
    assert torch.isfinite(grad).all()
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-5)


def test_pure_translation_gradient_matches_svd_free_expectation():
    # Under a pure translation, moving every driver by d moves every Gaussian by d and
    # turns nothing: the gradient of sum(points) wrt each driver sums to N per axis.
    gen = torch.Generator().manual_seed(9)
    points, quats, drivers, nb = _scene(50, 40, gen)
    x = (drivers + 0.5).requires_grad_(True)
    p, q = interpolate(points, quats, drivers, x, nb)
    g = torch.autograd.grad(p.sum(), x)[0]
    assert torch.allclose(g.sum(0), torch.full((3,), 50.0, dtype=torch.float64))


def test_rotate_quats_and_matrix_round_trip():
    gen = torch.Generator().manual_seed(10)
    R = random_rotations(100, gen)
    q = matrix_to_quat(R)
    assert (quat_to_matrix(q) - R).abs().max() < 1e-12
    q2 = matrix_to_quat(random_rotations(100, gen))
    composed = quat_to_matrix(rotate_quats(q, q2))
    assert (composed - R @ quat_to_matrix(q2)).abs().max() < 1e-12
    assert torch.allclose(quat_multiply(q, q2).norm(dim=1), torch.ones(100, dtype=torch.float64))


def test_apply_deformation_reproduces_deformed_covariance():
    gen = torch.Generator().manual_seed(11)
    n = 200
    quats = matrix_to_quat(random_rotations(n, gen))
    scales = torch.rand(n, 3, generator=gen, dtype=torch.float64) + 0.1
    F = torch.eye(3, dtype=torch.float64) + 0.3 * torch.randn(n, 3, 3, generator=gen, dtype=torch.float64)
    q_new, s_new = apply_deformation(quats, scales, F)
    R0 = quat_to_matrix(quats)
    cov = F @ R0 @ torch.diag_embed(scales**2) @ R0.transpose(1, 2) @ F.transpose(1, 2)
    R1 = quat_to_matrix(q_new)
    cov_new = R1 @ torch.diag_embed(s_new**2) @ R1.transpose(1, 2)
    assert (cov_new - cov).abs().max() < 1e-10
    assert math.isclose(float(torch.linalg.det(R1).min()), 1.0, rel_tol=1e-9)


def test_warp_kernel_matches_torch_twin(device):
    # The fused forward kernel (bake) against the torch implementation (fit), float32.
    gen = torch.Generator().manual_seed(12)
    points, quats, drivers, nb = _scene(4000, 300, gen, torch.float32)
    now = drivers.clone()
    now[:, 0] += 0.2 * torch.sin(3 * drivers[:, 1])
    now = now @ random_rotations(1, gen)[0].float().T + 0.5
    args = [t.to(device) for t in (points, quats, drivers, nb)]
    p_t, q_t = DriverInterpolator(*args, backend="torch")(now.to(device))
    warp_interp = DriverInterpolator(*args, backend="warp")
    p_w, q_w = warp_interp(now.to(device))
    assert (p_w.cpu() - p_t.cpu()).abs().max() < 1e-5
    assert same_rotation_quats(q_w.cpu(), q_t.cpu()) < 1e-5
    # "auto" takes the kernel without gradients and torch with them.
    auto = DriverInterpolator(*args)
    with torch.no_grad():
        assert torch.equal(auto(now.to(device))[0], p_w)
    x = now.to(device).requires_grad_(True)
    p_a, _ = auto(x)
    assert p_a.requires_grad
