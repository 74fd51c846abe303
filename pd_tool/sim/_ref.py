"""Float64 torch twins of the kernels: slow, dense, obviously right, differentiable.

Each function mirrors the kernel of the same name without `_ref` (kernels.py). Tests run
both on the same inputs and compare values, and compare warp's adjoints with torch autograd
through these twins (and these twins with finite differences).
"""
from __future__ import annotations

import math

import torch

POLAR_ITERS = 30  # fixed Newton iterations: converged to float64 for the test inputs
MIN_NODE_MASS = 1e-15  # kg, as kernels.MIN_NODE_MASS: lighter nodes count as empty


def polar_rotation_ref(F: torch.Tensor) -> torch.Tensor:
    """R of F = R S for [..., 3, 3] F with det F > 0 (scaled Newton, differentiable)."""
    X = F
    for _ in range(POLAR_ITERS):
        Xi = torch.linalg.inv(X)
        g = ((Xi * Xi).sum((-2, -1)) / (X * X).sum((-2, -1))).sqrt().sqrt()[..., None, None]
        X = 0.5 * (g * X + Xi.transpose(-1, -2) / g)
    return X


def lame_ref(E: torch.Tensor, nu: float) -> tuple[torch.Tensor, torch.Tensor]:
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def kirchhoff_stress_ref(F: torch.Tensor, E: torch.Tensor, nu: float) -> torch.Tensor:
    """[N, 3, 3] fixed-corotated Kirchhoff stress (Pa) of [N, 3, 3] F and [N] E (Pa)."""
    mu, lam = lame_ref(E, nu)
    R = polar_rotation_ref(F)
    J = torch.linalg.det(F)
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    return (2.0 * mu[:, None, None] * (F - R) @ F.transpose(-1, -2)
            + (lam * (J - 1.0) * J)[:, None, None] * eye)


def _stencil(x: torch.Tensor, dx: float, nodes: tuple[int, int, int]):
    """Stencil base [N, 3] long (clamped like the kernel), fx [N, 3], weights [N, 3, 3]."""
    q = x.detach() / dx - 0.5
    hi = torch.tensor([n - 3 for n in nodes], dtype=q.dtype, device=q.device)
    b = torch.minimum(torch.clamp(q, min=0.0), hi).floor().long()
    fx = x / dx - b.to(x.dtype)
    w = torch.stack([0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2], -1)
    return b, fx, w


def _offsets():
    for i in range(3):
        for j in range(3):
            for k in range(3):
                yield i, j, k


def p2g_ref(base, u, v, C, F, E, volume, mass, nu, dx, dt, nodes, accel):
    """Grid mass [nodes] and momentum [nodes + (3,)] (kg, kg m/s); accel [N, 3] m/s^2."""
    x = base + u
    b, fx, w = _stencil(x, dx, nodes)
    tau = kirchhoff_stress_ref(F, E, nu)
    affine = mass[:, None, None] * C - (4.0 / dx**2 * dt) * volume[:, None, None] * tau
    mv = mass[:, None] * (v + accel * dt)
    nx, ny, nz = nodes
    gm = torch.zeros(nx * ny * nz, dtype=x.dtype, device=x.device)
    gmv = torch.zeros(nx * ny * nz, 3, dtype=x.dtype, device=x.device)
    for i, j, k in _offsets():
        wijk = w[:, 0, i] * w[:, 1, j] * w[:, 2, k]
        off = torch.tensor([i, j, k], dtype=x.dtype, device=x.device)
        dpos = (off - fx) * dx
        idx = ((b[:, 0] + i) * ny + b[:, 1] + j) * nz + b[:, 2] + k
        gm = gm.index_add(0, idx, wijk * mass)
        gmv = gmv.index_add(0, idx, wijk[:, None] * (mv + (affine @ dpos[:, :, None])[:, :, 0]))
    return gm.reshape(nodes), gmv.reshape(*nodes, 3)


def grid_update_ref(gm, gmv, fixed, dx, dt, gravity, damping, pad, ground_z=None):
    """Grid velocity [nodes + (3,)] m/s with walls, ground and Dirichlet nodes."""
    nodes = gm.shape
    g = torch.tensor(gravity, dtype=gmv.dtype, device=gmv.device)
    safe_m = torch.where(gm > MIN_NODE_MASS, gm, torch.ones_like(gm))
    vel = (gmv / safe_m[..., None] + dt * g) * math.exp(-damping * dt)
    vel = torch.where((gm > MIN_NODE_MASS)[..., None], vel, torch.zeros_like(vel))
    idx = torch.stack(torch.meshgrid(*[torch.arange(n, device=gm.device) for n in nodes], indexing="ij"), -1)
    comps = []
    for d in range(3):
        c = vel[..., d]
        c = torch.where((idx[..., d] < pad) & (c < 0), torch.zeros_like(c), c)
        c = torch.where((idx[..., d] >= nodes[d] - pad) & (c > 0), torch.zeros_like(c), c)
        if d == 2 and ground_z is not None:
            c = torch.where((idx[..., 2].to(c.dtype) * dx <= ground_z) & (c < 0), torch.zeros_like(c), c)
        comps.append(c)
    vel = torch.stack(comps, -1)
    return torch.where(fixed[..., None] != 0, torch.zeros_like(vel), vel)


def g2p_ref(base, u, F, static, gv, dx, dt):
    """New (u, v, C, F) from the grid velocity; static particles keep u, F and get v = C = 0."""
    x = base + u
    nodes = tuple(gv.shape[:3])
    b, fx, w = _stencil(x, dx, nodes)
    vel = torch.zeros_like(x)
    Cn = torch.zeros_like(F)
    for i, j, k in _offsets():
        wijk = w[:, 0, i] * w[:, 1, j] * w[:, 2, k]
        off = torch.tensor([i, j, k], dtype=x.dtype, device=x.device)
        dpos = (off - fx) * dx
        g = gv[b[:, 0] + i, b[:, 1] + j, b[:, 2] + k]
        vel = vel + wijk[:, None] * g
        Cn = Cn + (4.0 / dx**2) * wijk[:, None, None] * g[:, :, None] * dpos[:, None, :]
    moving = (~static)[:, None]
    vel = torch.where(moving, vel, torch.zeros_like(vel))
    Cn = torch.where(moving[:, :, None], Cn, torch.zeros_like(Cn))
    eye = torch.eye(3, dtype=F.dtype, device=F.device)
    Fn = (eye + dt * Cn) @ F
    return u + dt * vel, vel, Cn, Fn


def fixed_nodes_ref(x: torch.Tensor, static: torch.Tensor, dx: float, nodes) -> torch.Tensor:
    """[nodes] int: 1 at the node nearest to each static particle."""
    fixed = torch.zeros(nodes, dtype=torch.int64)
    if static.any():
        idx = torch.floor(x[static].detach() / dx + 0.5).long()
        for d in range(3):
            idx[:, d] = idx[:, d].clamp(0, nodes[d] - 1)
        fixed[idx[:, 0], idx[:, 1], idx[:, 2]] = 1
    return fixed


def substeps_ref(x, v, C, F, E, volume, mass, static, *, nu, dx, nodes, dt, n_substeps, gravity,
                 damping, pad, ground_z=None, accel_fn=None, t0=0.0):
    """n_substeps of MPM from state (x, v, C, F); returns the new (x, v, C, F).

    accel_fn(t) -> [N, 3] external acceleration at time t (s), or None.
    """
    fixed = fixed_nodes_ref(x, static, dx, nodes)
    u = torch.zeros_like(x)
    for s in range(n_substeps):
        a = accel_fn(t0 + s * dt) if accel_fn is not None else torch.zeros_like(x)
        gm, gmv = p2g_ref(x, u, v, C, F, E, volume, mass, nu, dx, dt, nodes, a)
        gv = grid_update_ref(gm, gmv, fixed, dx, dt, gravity, damping, pad, ground_z)
        u, v, C, F = g2p_ref(x, u, F, static, gv, dx, dt)
    return x + u, v, C, F
