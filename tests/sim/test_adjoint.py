"""Hand-written adjoint kernels (pd_tool/sim/adjoint.py) against warp's taped adjoints,
which tests/sim/test_grad.py checks against a float64 twin and finite differences: every
boundary condition, forces, damping, static particles, crowded cells, long frames."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp

from pd_tool.sim import DiffSim, Force, SimConfig
from pd_tool.sim import gather
from pd_tool.sim.adjoint import stress_vjp
from pd_tool.sim.kernels import kirchhoff_stress, lame, lame_per_e, polar_rotation

TOL = 1e-4  # both are float32 sums of the same terms in different orders


def rel_err(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))


def block(dx: float, per_cell_axis: int, seed: int):
    h = dx / per_cell_axis
    axes = [np.arange(3 * dx + 0.5 * h, 5 * dx, h)] * 3
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    x = x + rng.uniform(-0.3, 0.3, x.shape) * h  # off the lattice: every weight differs
    x = x[rng.permutation(len(x))]  # input order unlike the cell order the kernels run in
    return x, x[:, 2] < 3.5 * dx, np.full(len(x), h**3), rng


def frame_grads(x, static, vol, cfg: SimConfig, binned: bool, seed: int, substeps: int, near_rest: bool,
                device: str = "cpu"):
    rng = np.random.default_rng(seed)
    n = len(x)
    sim = DiffSim(vol, vol * 1000, static, cfg, device=device)
    sim.binned = binned
    xt = torch.tensor(x, dtype=torch.float32)
    v = torch.tensor(rng.normal(0, 0.5, (n, 3)), dtype=torch.float32)
    v[torch.tensor(static)] = 0
    C = torch.zeros(n, 3, 3) if near_rest else torch.tensor(rng.normal(0, 0.5, (n, 3, 3)), dtype=torch.float32)
    F = torch.eye(3).expand(n, 3, 3).clone()
    if not near_rest:
        F = F + torch.tensor(rng.normal(0, 0.05, (n, 3, 3)), dtype=torch.float32)
    E = torch.tensor(rng.uniform(1e4, 3e4, n), dtype=torch.float32)
    ins = [t.to(sim.torch_device).requires_grad_() for t in (xt, v, C, F, E)]
    push = Force(mask=x[:, 0] > 0.5, accel=(5.0, -2.0, 8.0), t_start=2e-3, t_end=6e-3)
    out = sim.frame(tuple(ins[:4]), ins[4], 1e-3 * substeps, substeps, [push])
    g = torch.Generator().manual_seed(seed + 1)
    loss = sum((o * torch.randn(o.shape, generator=g).to(o.device)).sum() for o in out)
    return [gr.cpu() for gr in torch.autograd.grad(loss, ins)]


@pytest.mark.parametrize("binned,segment", [(False, 4), (True, 4), (True, None)])
@pytest.mark.parametrize("near_rest", [True, False])
def test_adjoint_matches_tape_with_every_boundary(binned, segment, near_rest, device):
    """Walls (the block touches the wall layers), ground plane, Dirichlet nodes, damping,
    a force window inside the frame, 9 substeps in segments of 4 (checkpoints) or in one
    (segment None: the whole frame fits the memory budget)."""
    x, static, vol, _ = block(1 / 8, 2, seed=0)
    grads = {}
    for mode in ("adjoint", "tape"):
        cfg = SimConfig(grid_res=8, damping=2.0, segment=segment if mode == "adjoint" else 4, ground_z=0.4,
                        backward=mode)
        grads[mode] = frame_grads(x, static, vol, cfg, binned and mode == "adjoint", 7, 9, near_rest, device)
    for name, a, b in zip("xvCFE", grads["adjoint"], grads["tape"]):
        assert torch.all(torch.isfinite(a)), name
        assert float(b.abs().max()) > 0, name  # the comparison sees a gradient
        assert rel_err(a, b) < TOL, (name, rel_err(a, b))


def test_binned_adjoint_with_crowded_cells(device):
    """64 particles a cell against chunks of CHUNK: each cell's grid-velocity cotangent is
    summed by several chunks; the sum must not change."""
    x, static, vol, _ = block(1 / 8, 4, seed=1)
    assert len(x) / 8 > gather.CHUNK  # 2 x 2 x 2 cells
    cfg_a = SimConfig(grid_res=8, segment=3, backward="adjoint")
    cfg_t = SimConfig(grid_res=8, segment=3, backward="tape")
    for a, b in zip(frame_grads(x, static, vol, cfg_a, True, 3, 5, False, device),
                    frame_grads(x, static, vol, cfg_t, False, 3, 5, False, device)):
        assert rel_err(a, b) < TOL


def test_stress_vjp_matches_torch_autograd():
    """stress_vjp against torch autograd of the float64 stress (polar via SVD, away from
    repeated singular values where torch's SVD gradient is defined)."""
    rng = np.random.default_rng(5)
    n, nu = 64, 0.3
    F = np.eye(3) + rng.normal(0, 0.2, (n, 3, 3))
    F[np.linalg.det(F) < 0.2] = np.eye(3) * 1.1
    E = rng.uniform(1e3, 1e5, n)
    G = rng.normal(0, 1, (n, 3, 3))

    @wp.kernel
    def vjp(F: wp.array(dtype=wp.mat33), E: wp.array(dtype=float), G: wp.array(dtype=wp.mat33), lpe: wp.vec2,
            gF: wp.array(dtype=wp.mat33), gE: wp.array(dtype=float), tau: wp.array(dtype=wp.mat33)):
        p = wp.tid()
        a, b = stress_vjp(F[p], polar_rotation(F[p]), E[p], lpe, G[p])
        gF[p] = a
        gE[p] = b
        lm = lame(E[p], 0.3)
        tau[p] = kirchhoff_stress(F[p], lm[0], lm[1])

    arr = lambda a, t: wp.array(a.astype(np.float32), dtype=t)  # noqa: E731
    gF, gE, tau = wp.zeros(n, dtype=wp.mat33), wp.zeros(n, dtype=float), wp.zeros(n, dtype=wp.mat33)
    wp.launch(vjp, dim=n, inputs=[arr(F, wp.mat33), arr(E, float), arr(G, wp.mat33), wp.vec2(*lame_per_e(nu)),
                                  gF, gE, tau])

    Ft = torch.tensor(F.astype(np.float32), dtype=torch.float64, requires_grad=True)
    Et = torch.tensor(E.astype(np.float32), dtype=torch.float64, requires_grad=True)
    U, _, Vh = torch.linalg.svd(Ft)
    R = U @ Vh
    mu = Et / (2 * (1 + nu))
    lam = Et * nu / ((1 + nu) * (1 - 2 * nu))
    J = torch.linalg.det(Ft)
    ref = 2 * mu[:, None, None] * (Ft - R) @ Ft.transpose(1, 2) + (lam * (J - 1) * J)[:, None, None] * torch.eye(3)
    assert rel_err(tau.numpy(), ref.detach()) < 1e-5
    rF, rE = torch.autograd.grad((ref * torch.tensor(G)).sum(), [Ft, Et])
    assert rel_err(gF.numpy(), rF) < 1e-4
    assert rel_err(gE.numpy(), rE) < 1e-4
