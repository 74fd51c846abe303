"""Warp device code for the MLS-MPM simulator: @wp.struct, @wp.func and @wp.kernel only.

solver.py launches these; _ref.py holds float64 numpy/torch twins used by the tests.
The substep kernels take their inputs grouped in four structs (Particles, ParticleVars,
StepParams, Forces); the host builds each once per solver, frame or state buffer and
passes the same instances to every launch (solver.SubstepContext).

Conventions shared by every kernel:
- Particle position = base[p] + u[p]. `base` is a fixed float32 position (rest position in
  the fast path, frame-start position in the differentiable path) and `u` the displacement
  from it. Keeping the small displacement as state avoids the float32 rounding of
  x += dt * v when a substep moves a point by less than one ulp of x (design.md).
- The deformation gradient is kept as G = F - I, for the same reason: a stiff part takes
  thousands of substeps a frame, and a substep's strain increment (1e-8 to 1e-6) is below
  float32's spacing at 1 (1.2e-7). F stored near I rounds each increment away, or to the
  same wrong value every substep, so a clamped strip's bending strain drifts or vanishes;
  G keeps it to float32's relative precision. Kernels use F = I + G where they need F.
- `order[t]` is the particle handled by thread t (particles sorted by cell, so that
  neighbouring threads touch neighbouring grid nodes). Any permutation gives the same result.
- Grid nodes (i, j, k) sit at (i, j, k) * dx; arrays have shape (nx + 1, ny + 1, nz + 1).
- Quadratic B-spline weights; MLS-MPM (Hu et al. 2018): the affine matrix C doubles as the
  velocity gradient in the update of F.
"""
from __future__ import annotations

import numpy as np
import warp as wp

# Stats slots written by the kernels and read once per frame by the guard (solver.py).
STAT_NONFINITE = 0  # particles with a NaN/inf position, velocity or F
STAT_EDGE = 1  # particles that reached the outer cell of the grid
STAT_COLLAPSED = 2  # particles with det F <= min_det_f (inverted or collapsed volume)
STAT_VMAX = 3  # max particle speed (m/s), frame-end kernel only
STAT_KINETIC = 4  # kinetic energy (J), frame-end kernel only
N_STATS = 5
# frame_stats spreads its two reductions over this many (max speed, kinetic energy) lanes
# after the N_STATS slots: one address taking an atomic from every particle serialises
# (0.3 ms a frame at 100k particles on an H200); the host folds the lanes.
STAT_LANES = 256
N_STATS_WITH_LANES = N_STATS + 2 * STAT_LANES


def lean_launches(module: str) -> None:
    """Compile MODULE's kernels without warp's grid-stride loop, where this warp offers it.

    One thread an element with an early return: no launch here caps warp's blocks
    (`max_blocks`), so the loop only costs instructions and registers. H200, block of 100k /
    64^3 and 300k / 128^3: bake forward 3-7% faster, forward + backward 2-4%
    (`docs/gpu-runs/sim_grid_stride_h200.json`). CPU kernels have no such loop."""
    if "default_grid_stride" in wp.get_module_options(module):  # warp >= 1.19
        wp.set_module_options({"default_grid_stride": False}, module)


lean_launches(__name__)


# --------------------------------------------------------------------------------------
# Argument bundles
# --------------------------------------------------------------------------------------
@wp.struct
class Particles:
    """Per-particle constants: order [N] (thread -> particle), base [N] vec3 position (m),
    E [N] Young's modulus (Pa), volume [N] (m^3), mass [N] (kg), is_static [N] (0/1)."""

    order: wp.array(dtype=int)
    base: wp.array(dtype=wp.vec3)
    E: wp.array(dtype=float)
    volume: wp.array(dtype=float)
    mass: wp.array(dtype=float)
    is_static: wp.array(dtype=int)


@wp.struct
class ParticleVars:
    """One particle state (or its cotangents): u [N] vec3 displacement from base (m),
    v [N] vec3 (m/s), C [N] mat33 affine velocity (1/s), G [N] mat33 the deformation
    gradient less the identity, F - I (see the module docstring)."""

    u: wp.array(dtype=wp.vec3)
    v: wp.array(dtype=wp.vec3)
    C: wp.array(dtype=wp.mat33)
    G: wp.array(dtype=wp.mat33)


def state_table(fields: list) -> wp.array:
    """The base addresses of a frame's stored state arrays (u, v, C, G: [rows, N] each,
    contiguous), [4] uint64 on their device, for stored_state."""
    return wp.array(np.array([f.ptr for f in fields[:4]], dtype=np.uint64), dtype=wp.uint64,
                    device=fields[0].device)


@wp.func
def stored_state(states: wp.array(dtype=wp.uint64), row: int, n: int) -> ParticleVars:
    """State `row` of a frame's stored substeps: views of row `row` of the [rows, n] arrays
    u, v, C, G whose base addresses `states` holds (state_table). The differentiable path's
    kernels read and write a stored frame's states through such a table, not through
    arrays bound at launch, so that one captured graph serves every slot of stored frames:
    the table's contents name the slot."""
    r = wp.uint64(row) * wp.uint64(n)  # 64-bit: rows x N may pass 2^31
    s = ParticleVars()  # bytes a particle: 12 a vec3, 36 a mat33
    s.u = wp.array(ptr=states[0] + r * wp.uint64(12), shape=(n,), dtype=wp.vec3)
    s.v = wp.array(ptr=states[1] + r * wp.uint64(12), shape=(n,), dtype=wp.vec3)
    s.C = wp.array(ptr=states[2] + r * wp.uint64(36), shape=(n,), dtype=wp.mat33)
    s.G = wp.array(ptr=states[3] + r * wp.uint64(36), shape=(n,), dtype=wp.mat33)
    return s


@wp.struct
class StepParams:
    """Grid, material and boundary constants of a substep.

    dx: cell size (m); inv_dx: 1 / dx (1/m); dt: substep (s); nodes: grid nodes per axis;
    inv_nodes: their reciprocals (node_of); lame_per_E: (mu, lambda) / E for the Poisson's
    ratio (lame_per_e), so that a kernel multiplies where it would divide per particle;
    min_det_f: guard threshold on det F;
    edge_lo, edge_hi: guard box (m); pad: wall layers (nodes); gravity (m/s^2);
    damping_factor: exp(-damping dt); use_ground (0/1), ground_z (m); fixed [nodes] int:
    Dirichlet nodes."""

    dx: float
    inv_dx: float
    dt: float
    nodes: wp.vec3i
    inv_nodes: wp.vec3
    lame_per_E: wp.vec2
    min_det_f: float
    edge_lo: wp.vec3
    edge_hi: wp.vec3
    pad: int
    gravity: wp.vec3
    damping_factor: float
    use_ground: int
    ground_z: float
    fixed: wp.array3d(dtype=int)


@wp.struct
class Forces:
    """User accelerations: n of them (the arrays hold at least one row), mask [K, N] float,
    accel [K] vec3 (m/s^2), window [K] vec2 [t_start, t_end) (s); t_frame [1]: the time (s)
    a launch's t_offset counts from, kept on the device so that a captured graph replays
    for any frame."""

    n: int
    mask: wp.array2d(dtype=float)
    accel: wp.array(dtype=wp.vec3)
    window: wp.array(dtype=wp.vec2)
    t_frame: wp.array(dtype=float)



# --------------------------------------------------------------------------------------
# Polar rotation with a gradient that stays bounded at F = I
# --------------------------------------------------------------------------------------
POLAR_MAX_ITERS = 16  # scaled Newton iterations (near rest it stops after 1-3)
POLAR_TOL = 1e-6  # Frobenius change that ends the Newton iteration (float32)
MIN_NODE_MASS = wp.constant(1.0e-15)  # kg; lighter grid nodes are treated as empty (see node_velocity)


@wp.func
def polar_rotation(F: wp.mat33) -> wp.mat33:
    """Rotation R of the polar decomposition F = R S (det F > 0), by scaled Newton.

    X <- (g X + X^-T / g) / 2 with Frobenius scaling g = (|X^-1| / |X|)^(1/2) converges
    quadratically to R (Higham 1986). It is several times cheaper than svd3 for the
    near-rotations MPM produces, and more accurate in float32 at F = I.
    """
    X = F
    it = int(0)
    while it < POLAR_MAX_ITERS:
        Xi = wp.inverse(X)
        g2 = wp.sqrt(wp.ddot(Xi, Xi) / wp.ddot(X, X))
        g = wp.sqrt(g2)
        # 1 / g as g / g^2: a matrix over a scalar divides each of its nine entries, and
        # on CUDA each IEEE division carries a slow-path check
        Xn = (0.5 * g) * X + (0.5 * g / g2) * wp.transpose(Xi)
        d = Xn - X
        X = Xn
        it += 1
        if wp.ddot(d, d) < POLAR_TOL * POLAR_TOL:
            it = POLAR_MAX_ITERS
    return X


@wp.func
def polar_vjp(F: wp.mat33, R: wp.mat33, adj_R: wp.mat33) -> wp.mat33:
    """dL/dF through R = polar_rotation(F), given R and dL/dR.

    With F = R S and Omega = R^T dR = [w]x:  R^T dF - dF^T R = [(tr(S) I - S) w]x, so
    w = (tr(S) I - S)^-1 axial(R^T dF - dF^T R). The matrix tr(S) I - S has eigenvalues
    s_i + s_j (2 at rest), unlike the s_i^2 - s_j^2 that warp's svd3 adjoint divides by,
    so this gradient stays bounded at F = I. Its adjoint: dL/dF = R [y]x with
    y = (tr(S) I - S)^-1 m, m = axial part of R^T adj_R (m . w = <R^T adj_R, [w]x>).
    """
    S = wp.transpose(R) * F
    S = 0.5 * (S + wp.transpose(S))
    A = wp.identity(n=3, dtype=float) * wp.trace(S) - S
    M = wp.transpose(R) * adj_R
    m = wp.vec3(M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1])
    y = wp.inverse(A) * m
    return R * wp.mat33(0.0, -y[2], y[1], y[2], 0.0, -y[0], -y[1], y[0], 0.0)


@wp.func_grad(polar_rotation)
def adj_polar_rotation(F: wp.mat33, adj_ret: wp.mat33):
    wp.adjoint[F] += polar_vjp(F, polar_rotation(F), adj_ret)


@wp.func
def kirchhoff_stress(F: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """Fixed-corotated Kirchhoff stress tau = 2 mu (F - R) F^T + lam (J - 1) J I, in Pa."""
    return kirchhoff_stress_polar(F, polar_rotation(F), mu, lam)


@wp.func
def kirchhoff_stress_polar(F: wp.mat33, R: wp.mat33, mu: float, lam: float) -> wp.mat33:
    """kirchhoff_stress given R = polar_rotation(F), for callers that need R again (the
    hand-written P2G adjoint: one polar decomposition per particle instead of two)."""
    J = wp.determinant(F)
    return 2.0 * mu * (F - R) * wp.transpose(F) + wp.identity(n=3, dtype=float) * (lam * (J - 1.0) * J)


@wp.func
def lame(E: float, nu: float) -> wp.vec2:
    """(mu, lambda) in Pa from Young's modulus E (Pa) and Poisson's ratio nu."""
    return wp.vec2(E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)))


def lame_per_e(nu: float) -> tuple[float, float]:
    """(mu, lambda) / E for Poisson's ratio nu, in float64 (StepParams.lame_per_E)."""
    return 1.0 / (2.0 * (1.0 + nu)), nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def reciprocal_f32(x: float) -> float:
    """1 / x as a float32 division, the value a kernel's 1.0 / x gives (StepParams.inv_dx,
    inv_nodes): host and kernels then find the same stencil cells and nodes."""
    return float(np.float32(1.0) / np.float32(x))


# --------------------------------------------------------------------------------------
# Stencil helpers
# --------------------------------------------------------------------------------------
# The grid kernels run one thread a node over a 1-D launch and find the node here: warp's
# 3-D thread index divides by the launch's shape at run time, and an integer division by a
# run-time value costs about twenty instructions on a GPU, paid by every node's thread.
MAX_NODE_ROWS = 1 << 22  # nodes[0] * nodes[1] below this keeps node_of exact (GridGeometry checks it)


@wp.func
def split_index(t: int, n: int, inv_n: float) -> wp.vec2i:
    """(t // n, t % n) for t >= 0 with t // n < MAX_NODE_ROWS, n >= 1, inv_n = float32(1 / n).

    The float product is within 3 2^-24 of t / n relative, under 1 absolutely below
    MAX_NODE_ROWS, so its truncation is the quotient or one off, which the remainder's
    sign corrects."""
    q = int(float(t) * inv_n)
    r = t - q * n
    if r < 0:
        q -= 1
        r += n
    elif r >= n:
        q += 1
        r -= n
    return wp.vec2i(q, r)


@wp.func
def node_of(t: int, nodes: wp.vec3i, inv_nodes: wp.vec3) -> wp.vec3i:
    """Node (i, j, k) of linear index t = (i nodes[1] + j) nodes[2] + k."""
    ij_k = split_index(t, nodes[2], inv_nodes[2])
    i_j = split_index(ij_k[0], nodes[1], inv_nodes[1])
    return wp.vec3i(i_j[0], i_j[1], ij_k[1])


@wp.func
def cell_index(b: wp.vec3i, nodes: wp.vec3i) -> int:
    """Linear index of the cell whose stencil starts at node b (k fastest)."""
    return (b[0] * nodes[1] + b[1]) * nodes[2] + b[2]


@wp.func
def stencil_base(x: wp.vec3, inv_dx: float, nodes: wp.vec3i) -> wp.vec3i:
    """Lowest node of the 3x3x3 stencil, clamped so that a runaway (even NaN) particle
    can never index outside the grid: memory stays safe and the guard reports it."""
    b = wp.vec3i(0, 0, 0)
    for d in range(3):
        q = x[d] * inv_dx - 0.5
        # NaN fails both comparisons and lands on 0.
        if q >= 0.0:
            if q < float(nodes[d] - 3):
                b[d] = int(q)
            else:
                b[d] = nodes[d] - 3
    return b


@wp.func_grad(stencil_base)
def adj_stencil_base(x: wp.vec3, inv_dx: float, nodes: wp.vec3i, adj_ret: wp.vec3i):
    # The stencil base is piecewise constant in x: zero gradient. Without this, warp would
    # push integer-truncated adjoints back through the int() casts into x.
    pass


@wp.func
def bspline_w(fx: float) -> wp.vec3:
    """Quadratic B-spline weights of node offsets 0, 1, 2 at fx = x/dx - base in [0.5, 1.5)."""
    return wp.vec3(0.5 * (1.5 - fx) * (1.5 - fx), 0.75 - (fx - 1.0) * (fx - 1.0), 0.5 * (fx - 0.5) * (fx - 0.5))


@wp.func
def external_accel(p: int, t_offset: float, forces: Forces) -> wp.vec3:
    """Sum of the user accelerations (m/s^2) acting on particle p at t_frame + t_offset (s)."""
    t = forces.t_frame[0] + t_offset
    a = wp.vec3(0.0)
    for k in range(forces.n):
        win = forces.window[k]
        if t >= win[0] and t < win[1]:
            a += forces.accel[k] * forces.mask[k, p]
    return a


# --------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------
@wp.kernel
def cell_keys(
    base: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    inv_dx: float,
    nodes: wp.vec3i,
    keys: wp.array(dtype=int),
    values: wp.array(dtype=int),
):
    """Linear stencil-base cell of every particle, the key for sorting by cell."""
    p = wp.tid()
    keys[p] = cell_index(stencil_base(base[p] + u[p], inv_dx, nodes), nodes)
    values[p] = p


@wp.kernel
def mark_fixed_nodes(
    base: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    is_static: wp.array(dtype=int),
    inv_dx: float,
    nodes: wp.vec3i,
    fixed: wp.array3d(dtype=int),
):
    """Dirichlet nodes: the node nearest to each static particle gets zero velocity."""
    p = wp.tid()
    if is_static[p] != 0:
        x = base[p] + u[p]
        i = wp.clamp(int(wp.floor(x[0] * inv_dx + 0.5)), 0, nodes[0] - 1)
        j = wp.clamp(int(wp.floor(x[1] * inv_dx + 0.5)), 0, nodes[1] - 1)
        k = wp.clamp(int(wp.floor(x[2] * inv_dx + 0.5)), 0, nodes[2] - 1)
        fixed[i, j, k] = 1


@wp.func
def deformation_gradient(G: wp.mat33) -> wp.mat33:
    """F = I + G from the state's G (the module docstring says why G is kept)."""
    return wp.identity(n=3, dtype=float) + G


@wp.func
def p2g_scatter(
    x: wp.vec3,
    v: wp.vec3,
    C: wp.mat33,
    F: wp.mat33,
    E: float,
    vol: float,
    m: float,
    a_ext: wp.vec3,
    lame_per_E: wp.vec2,
    dx: float,
    dt: float,
    nodes: wp.vec3i,
    grid_mmv: wp.array3d(dtype=wp.vec4),
):
    """Scatter one particle's MLS momentum (kg m/s) and mass (kg) to its 27 nodes, as
    (momentum, mass) vec4s (lame_per_E: StepParams')."""
    inv_dx = 1.0 / dx
    b = stencil_base(x, inv_dx, nodes)
    fx = x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2]))
    lm = E * lame_per_E
    tau = kirchhoff_stress(F, lm[0], lm[1])
    affine = m * C - (4.0 * inv_dx * inv_dx * dt * vol) * tau
    mv = m * (v + a_ext * dt)
    wx = bspline_w(fx[0])
    wy = bspline_w(fx[1])
    wz = bspline_w(fx[2])
    for i in range(3):
        for j in range(3):
            wij = wx[i] * wy[j]
            for k in range(3):
                w = wij * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                q = w * (mv + affine * dpos)
                wp.atomic_add(grid_mmv, b[0] + i, b[1] + j, b[2] + k, wp.vec4(q[0], q[1], q[2], w * m))


@wp.kernel
def p2g(
    ptcl: Particles,
    state: ParticleVars,
    step: StepParams,
    forces: Forces,
    t_offset: float,
    grid_mmv: wp.array3d(dtype=wp.vec4),
):
    """Particle to grid: mass (kg) and momentum (kg m/s) with the MLS stress impulse, at
    substep time t_frame + t_offset (s).

    m_i v_i += N [m_p v_p + m_p a_ext dt + (m_p C_p - 4/dx^2 dt V_p tau_p)(x_i - x_p)].
    """
    p = ptcl.order[wp.tid()]
    a_ext = external_accel(p, t_offset, forces)
    p2g_scatter(ptcl.base[p] + state.u[p], state.v[p], state.C[p], deformation_gradient(state.G[p]),
                ptcl.E[p], ptcl.volume[p], ptcl.mass[p], a_ext, step.lame_per_E, step.dx, step.dt, step.nodes,
                grid_mmv)


@wp.func
def node_velocity(mmv: wp.vec4, i: int, j: int, k: int, step: StepParams) -> wp.vec3:
    """Velocity of one node (m/s) from its (momentum, mass), with every boundary condition.

    Nodes lighter than MIN_NODE_MASS count as empty: a particle at the edge of a node's
    B-spline support gives it a mass of order 1e-18 kg, and the adjoint of mv / m,
    -mv / m^2, overflows float32 there (seen as NaN gradients on CUDA)."""
    pad = step.pad
    nodes = step.nodes
    vel = wp.vec3(0.0)
    m = mmv[3]
    if m > MIN_NODE_MASS:
        # times 1 / m: a vec3 over a scalar is three divisions
        vel = (wp.vec3(mmv[0], mmv[1], mmv[2]) * (1.0 / m) + step.dt * step.gravity) * step.damping_factor
        if i < pad and vel[0] < 0.0:
            vel = wp.vec3(0.0, vel[1], vel[2])
        if i >= nodes[0] - pad and vel[0] > 0.0:
            vel = wp.vec3(0.0, vel[1], vel[2])
        if j < pad and vel[1] < 0.0:
            vel = wp.vec3(vel[0], 0.0, vel[2])
        if j >= nodes[1] - pad and vel[1] > 0.0:
            vel = wp.vec3(vel[0], 0.0, vel[2])
        if k < pad and vel[2] < 0.0:
            vel = wp.vec3(vel[0], vel[1], 0.0)
        if k >= nodes[2] - pad and vel[2] > 0.0:
            vel = wp.vec3(vel[0], vel[1], 0.0)
        if step.use_ground != 0:
            if float(k) * step.dx <= step.ground_z and vel[2] < 0.0:
                vel = wp.vec3(vel[0], vel[1], 0.0)
        if step.fixed[i, j, k] != 0:
            vel = wp.vec3(0.0)
    return vel


@wp.kernel
def grid_update(
    step: StepParams,
    grid_mmv: wp.array3d(dtype=wp.vec4),
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Grid velocity (m/s) = momentum / mass + dt g, damped, then boundary conditions.

    Walls: in the `pad` outer node layers the velocity component pointing out of the grid
    is removed (free-slip), so particles cannot leave. Ground: nodes at z <= ground_z lose
    their downward velocity. Dirichlet: fixed nodes get zero velocity.
    """
    i, j, k = wp.tid()
    grid_v[i, j, k] = node_velocity(grid_mmv[i, j, k], i, j, k, step)


@wp.kernel(enable_backward=False)
def grid_update_and_clear(
    step: StepParams,
    grid_mmv: wp.array3d(dtype=wp.vec4),
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """grid_update that also zeroes mass and momentum for the next P2G (fast path only)."""
    i, j, k = wp.tid()
    grid_v[i, j, k] = node_velocity(grid_mmv[i, j, k], i, j, k, step)
    grid_mmv[i, j, k] = wp.vec4(0.0)


@wp.func
def g2p_values(
    p: int,
    ptcl: Particles,
    s_in: ParticleVars,
    step: StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
):
    """Grid to particle p from s_in's u and G: the new (u, v, C, G), with F <- (I + dt C) F
    as G <- G + dt C (I + G) and u <- u + dt v."""
    dx = step.dx
    dt = step.dt
    inv_dx = step.inv_dx
    up = s_in.u[p]
    x = ptcl.base[p] + up
    Gp = s_in.G[p]
    b = stencil_base(x, inv_dx, step.nodes)
    fx = x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2]))
    vel = wp.vec3(0.0)
    Cn = wp.mat33(0.0)
    wx = bspline_w(fx[0])
    wy = bspline_w(fx[1])
    wz = bspline_w(fx[2])
    for i in range(3):
        for j in range(3):
            wij = wx[i] * wy[j]
            for k in range(3):
                w = wij * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gv = grid_v[b[0] + i, b[1] + j, b[2] + k]
                vel += w * gv
                Cn += (4.0 * inv_dx * inv_dx * w) * wp.outer(gv, dpos)
    if ptcl.is_static[p] != 0:
        # Static particles stay where they are, undeformed (they still lend mass to P2G).
        vel = wp.vec3(0.0)
        Cn = wp.mat33(0.0)
    Gn = Gp + (dt * Cn) * deformation_gradient(Gp)
    un = up + dt * vel
    return un, vel, Cn, Gn


@wp.func
def g2p_guard(x: wp.vec3, v: wp.vec3, G: wp.mat33, step: StepParams, stats: wp.array(dtype=float)):
    """Count a particle at x (m) with velocity v and F = I + G in the guard's stats if it is
    not finite, collapsed or at the grid's edge (no atomics in the normal case)."""
    J = wp.determinant(deformation_gradient(G))
    if not (wp.isfinite(x) and wp.isfinite(v) and wp.isfinite(J)):
        wp.atomic_add(stats, STAT_NONFINITE, 1.0)
    else:
        if not (J > step.min_det_f):
            wp.atomic_add(stats, STAT_COLLAPSED, 1.0)
        if wp.min(x - step.edge_lo) < 0.0 or wp.max(x - step.edge_hi) > 0.0:
            wp.atomic_add(stats, STAT_EDGE, 1.0)


@wp.func
def g2p_gather(
    p: int,
    ptcl: Particles,
    s_in: ParticleVars,
    step: StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
    s_out: ParticleVars,
    stats: wp.array(dtype=float),
):
    """Grid to particle p (g2p_values): reads u, G of s_in, writes u, v, C, G of s_out, then
    the guard."""
    un, vel, Cn, Gn = g2p_values(p, ptcl, s_in, step, grid_v)
    s_out.u[p] = un
    s_out.v[p] = vel
    s_out.C[p] = Cn
    s_out.G[p] = Gn
    g2p_guard(ptcl.base[p] + un, vel, Gn, step, stats)


@wp.kernel
def g2p(
    ptcl: Particles,
    s_in: ParticleVars,
    step: StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
    s_out: ParticleVars,
    stats: wp.array(dtype=float),
):
    """Grid to particle (see g2p_gather).

    Each thread reads and writes only its own particle, so in the fast path the outputs may
    alias the inputs. Under a tape they must be separate arrays. Guard counters go to
    `stats` only on failure (no atomics in the normal case).
    """
    g2p_gather(ptcl.order[wp.tid()], ptcl, s_in, step, grid_v, s_out, stats)


@wp.kernel(enable_backward=False)
def g2p_stored(
    ptcl: Particles,
    states: wp.array(dtype=wp.uint64),
    row: int,
    step: StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
    stats: wp.array(dtype=float),
):
    """g2p from stored state `row` into row + 1 (stored_state): a stored frame's last
    substep."""
    n = ptcl.order.shape[0]
    g2p_gather(ptcl.order[wp.tid()], ptcl, stored_state(states, row, n), step, grid_v,
               stored_state(states, row + 1, n), stats)


@wp.kernel(enable_backward=False)
def g2p_p2g(
    ptcl: Particles,
    state: ParticleVars,
    step: StepParams,
    forces: Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    grid_mmv: wp.array3d(dtype=wp.vec4),
    stats: wp.array(dtype=float),
):
    """Fast path only: G2P of this substep, in place, fused with the P2G of the next one
    (at t_frame + t_offset_next, s).

    The particle's state is read once per substep instead of twice, and one launch is saved.
    """
    p = ptcl.order[wp.tid()]
    g2p_gather(p, ptcl, state, step, grid_v, state, stats)
    a_ext = external_accel(p, t_offset_next, forces)
    p2g_scatter(ptcl.base[p] + state.u[p], state.v[p], state.C[p], deformation_gradient(state.G[p]),
                ptcl.E[p], ptcl.volume[p], ptcl.mass[p], a_ext, step.lame_per_E, step.dx, step.dt, step.nodes,
                grid_mmv)


# frame_stats' particles a thread: its loads are independent (an unrolled loop), and it
# sends 2 atomics for them to the 2 x STAT_LANES lanes, where one thread a particle sent
# 200k at 100k particles.
STATS_PER_THREAD = 8


@wp.kernel(enable_backward=False)
def frame_stats(
    v: wp.array(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    stride: int,
    stats: wp.array(dtype=float),
):
    """Max speed (m/s) and kinetic energy (J) at the end of a frame, for CFL and rest checks,
    per lane (see STAT_LANES; guard.fold_stat_lanes folds them). Thread t folds particles
    t, t + stride, ..., STATS_PER_THREAD of them, before its two atomics
    (launch_frame_stats)."""
    t = wp.tid()
    vmax = float(0.0)
    kinetic = float(0.0)
    bad = float(0.0)
    for j in range(STATS_PER_THREAD):
        p = t + j * stride
        if p < v.shape[0]:
            vp = v[p]
            s2 = wp.dot(vp, vp)
            if wp.isfinite(s2):
                vmax = wp.max(vmax, wp.sqrt(s2))
                kinetic += 0.5 * mass[p] * s2
            else:
                bad += 1.0
    lane = N_STATS + 2 * (t % STAT_LANES)
    wp.atomic_max(stats, lane, vmax)
    wp.atomic_add(stats, lane + 1, kinetic)
    if bad > 0.0:
        wp.atomic_add(stats, STAT_NONFINITE, bad)


def launch_frame_stats(v: wp.array, mass: wp.array, stats: wp.array, device) -> None:
    """frame_stats over the particles' velocities v [N] m/s and masses [N] kg, adding into
    stats (zeroed lanes)."""
    threads = max(1, -(-v.shape[0] // STATS_PER_THREAD))
    wp.launch(frame_stats, dim=threads, device=device, inputs=[v, mass, threads, stats])


@wp.kernel
def compose_positions(
    base: wp.array(dtype=wp.vec3),
    u: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec3),
):
    """x = base + u (m)."""
    p = wp.tid()
    x[p] = base[p] + u[p]


@wp.kernel
def stress_kernel(
    F: wp.array(dtype=wp.mat33),
    E: wp.array(dtype=float),
    nu: float,
    tau: wp.array(dtype=wp.mat33),
):
    """Kirchhoff stress of each F (Pa); used by tests of the stress and its gradient."""
    p = wp.tid()
    lm = lame(E[p], nu)
    tau[p] = kirchhoff_stress(F[p], lm[0], lm[1])


@wp.kernel
def polar_kernel(F: wp.array(dtype=wp.mat33), R: wp.array(dtype=wp.mat33)):
    """R of each F; used by tests of the polar adjoint."""
    p = wp.tid()
    R[p] = polar_rotation(F[p])
