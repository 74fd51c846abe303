"""Hand-written reverse pass of the MPM substep: the differentiable path's backward.

Warp's generated adjoints of the scatter P2G replay every particle's 27 x 4 atomics under a
tape and add 27 x 4 more in reverse; the taped backward ran 12-15x the fast forward. Here
each stage's adjoint is written out:

- `g2p_adjoint` (per particle): the G2P's adjoint. Its only grid output, the cotangent of
  the grid velocity, is a scatter of the same form as the P2G (w_n (q + A dpos_n)), so on
  CUDA each warp sums its particles' shares as the forward's P2G does
  (gather.warp_row_sums: few atomics), and elsewhere they go straight to the grid.
- `grid_adjoint` (per node): the cotangents of node mass and momentum, with the boundary
  conditions' masks rebuilt from the stored forward values.
- `p2g_adjoint` (per particle): the P2G's adjoint is a gather (each particle reads its 27
  nodes' cotangents, no atomics), with the stress's vector-Jacobian product written out.

The forward values each adjoint reads (particle state and grid per substep) come from the
frame's slot, where its forward stored them, or from a recompute of the segment into a pool
reused by every segment and frame. The kernels reach the states through a table of their
arrays' addresses (kernels.stored_state), so that one captured graph serves every slot. With
x = base + u, the position's cotangent flows through u; the frame's start has u = 0, so
the cotangent of the start position is the cotangent of u at substep 0.

Derivation (per particle p and stencil node n, w_n the B-spline weight, dpos_n =
(offset_n - fx) dx, fx = x/dx - stencil base):
  P2G:  m_n += w_n m;  mv_n += w_n (mv_p + A_p dpos_n),
        mv_p = m (v + a dt),  A_p = m C - 4 dt / dx^2 V tau(F, E)
  G2P:  v' = sum w_n v_n;  C' = 4/dx^2 sum w_n v_n dpos_n^T;  F' = (I + dt C') F;
        u' = u + dt v'
and d dpos_n / dx = -I, so every position cotangent is sum_n gw_n grad w_n / dx - sum_n gdpos_n.
"""
from __future__ import annotations

import warp as wp

from pd_tool.sim import kernels as K
from pd_tool.sim.gather import (
    NO_CELL,
    PARTICLE_BLOCK,
    ROWS_BLOCK,
    block_tag,
    block_tagged,
    grid_threads,
    grid_update_tagged,
    launch_g2p2g_stored,
    red_add_vec4,
    rows_threads,
    warp_row_sums,
)

K.lean_launches(__name__)


@wp.func
def bspline_dw(fx: float) -> wp.vec3:
    """d/dfx of kernels.bspline_w (offsets 0, 1, 2)."""
    return wp.vec3(fx - 1.5, 2.0 - 2.0 * fx, fx - 0.5)


@wp.func
def cofactor(F: wp.mat33) -> wp.mat33:
    """J F^-T (defined for singular F too): columns f1 x f2, f2 x f0, f0 x f1."""
    Ft = wp.transpose(F)
    return wp.matrix_from_cols(wp.cross(Ft[1], Ft[2]), wp.cross(Ft[2], Ft[0]), wp.cross(Ft[0], Ft[1]))


@wp.func
def stress_vjp(F: wp.mat33, R: wp.mat33, E: float, lame_per_E: wp.vec2, G: wp.mat33):
    """Cotangents (dL/dF, dL/dE) of the fixed-corotated Kirchhoff stress, given G = dL/dtau
    and R = K.polar_rotation(F).

    tau = 2 mu (F F^T - R F^T) + lam (J^2 - J) I.
    """
    lm = E * lame_per_E
    mu = lm[0]
    lam = lm[1]
    J = wp.determinant(F)
    Gt = wp.transpose(G)
    trG = wp.trace(G)
    gF = (2.0 * mu) * ((G + Gt) * F - Gt * R)
    gF += K.polar_vjp(F, R, (-2.0 * mu) * (G * F))
    gF += (lam * (2.0 * J - 1.0) * trG) * cofactor(F)
    g_mu = 2.0 * wp.ddot(G, (F - R) * wp.transpose(F))
    g_lam = (J - 1.0) * J * trG
    g_E = g_mu * lame_per_E[0] + g_lam * lame_per_E[1]
    return gF, g_E


@wp.func
def scatter_direct(
    b: wp.vec3i,
    fx: wp.vec3,
    q: wp.vec3,
    A: wp.mat33,
    dx: float,
    out: wp.array3d(dtype=wp.vec4),
):
    """out_n += w_n (q + A dpos_n) over the 27 stencil nodes (the vec4s' w unused), with atomics."""
    wx = K.bspline_w(fx[0])
    wy = K.bspline_w(fx[1])
    wz = K.bspline_w(fx[2])
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                r = w * (q + A * dpos)
                red_add_vec4(out, b[0] + i, b[1] + j, b[2] + k, wp.vec4(r[0], r[1], r[2], 0.0))


@wp.func
def no_payload():
    """The (stencil base, fx, gv, A') of a lane with nothing to add (g2p_adjoint_particle's payload)."""
    return NO_CELL, wp.vec3(0.0), wp.vec3(0.0), wp.mat33(0.0)


@wp.func
def g2p_adjoint_particle(
    p: int,
    binned: int,
    ptcl: K.Particles,
    s: K.ParticleVars,
    s_next: K.ParticleVars,
    step: K.StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
    adj: K.ParticleVars,
    adj_grid_v: wp.array3d(dtype=wp.vec4),
):
    """Adjoint of G2P for particle p from state s (its u, G) to s_next (its v, C, read
    back): adj holds the cotangents of the substep's output state and its u, G are
    overwritten with the partial cotangents of the input u and G (the P2G adjoint adds the
    rest). G = F - I, so the cotangents of G and F are the same. The grid-velocity
    cotangent w_n (gv + A' dpos_n), A' = 4/dx^2 gC, goes straight to adj_grid_v (binned 0)
    or is returned, for the warp's sums (adjoint_row_sums), as the particle's stencil base
    node (NO_CELL: adds nothing) and its payload (fx, gv, A')."""
    dx = step.dx
    dt = step.dt
    nodes = step.nodes
    gu = adj.u[p]
    gFn = adj.G[p]
    adj.G[p] = wp.transpose(wp.identity(n=3, dtype=float) + dt * s_next.C[p]) * gFn
    base, fx, gvel, Ag = no_payload()
    if ptcl.is_static[p] != 0:
        # G2P gave a static particle zero velocity and C: nothing flows to the grid or x.
        adj.u[p] = gu
    else:
        inv_dx = step.inv_dx
        gvel = adj.v[p] + dt * gu
        Ag = (4.0 * inv_dx * inv_dx) * (adj.C[p] + dt * gFn * wp.transpose(K.deformation_gradient(s.G[p])))
        x = ptcl.base[p] + s.u[p]
        b = K.stencil_base(x, inv_dx, nodes)
        fx = x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2]))
        wx = K.bspline_w(fx[0])
        wy = K.bspline_w(fx[1])
        wz = K.bspline_w(fx[2])
        dwx = bspline_dw(fx[0])
        dwy = bspline_dw(fx[1])
        dwz = bspline_dw(fx[2])
        gfx = wp.vec3(0.0)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                    gw = wp.dot(grid_v[b[0] + i, b[1] + j, b[2] + k], gvel + Ag * dpos)
                    gfx += gw * wp.vec3(dwx[i] * wy[j] * wz[k], wx[i] * dwy[j] * wz[k], wx[i] * wy[j] * dwz[k])
        # sum_n w_n Ag^T v_n = Ag^T v' (the particle's new velocity): the dpos term in one product
        adj.u[p] = gu + gfx * inv_dx - wp.transpose(Ag) * s_next.v[p]
        if binned == 0:
            scatter_direct(b, fx, gvel, Ag, dx, adj_grid_v)
        else:
            base = b
    return base, fx, gvel, Ag


@wp.func
def adjoint_row_sums(base: wp.vec3i, fx: wp.vec3, gvel: wp.vec3, Ag: wp.mat33, step: K.StepParams,
                     adj_grid_v: wp.array3d(dtype=wp.vec4)):
    """The warp's grid-velocity cotangents (g2p_adjoint_particle's payloads, mass 0) summed
    into adj_grid_v (gather.warp_row_sums; tags nothing). Every lane of the warp calls it."""
    warp_row_sums(base, wp.vec4(Ag[0, 0], Ag[0, 1], Ag[0, 2], fx[0]), wp.vec4(Ag[1, 0], Ag[1, 1], Ag[1, 2], fx[1]),
                  wp.vec4(Ag[2, 0], Ag[2, 1], Ag[2, 2], fx[2]), wp.vec4(gvel[0], gvel[1], gvel[2], 0.0),
                  step.dx, step.nodes, adj_grid_v, step.fixed, 0)  # tag 0: no block array is written


@wp.func
def p2g_adjoint_particle(
    p: int,
    ptcl: K.Particles,
    s: K.ParticleVars,
    step: K.StepParams,
    a_ext: wp.vec3,
    adj_mmv: wp.array3d(dtype=wp.vec4),
    adj: K.ParticleVars,
    adj_E: wp.array(dtype=float),
):
    """Adjoint of P2G for particle p (state s), a gather of its 27 nodes' cotangents: sets
    adj.v and adj.C, adds to adj.u, adj.G (partials from the G2P adjoint) and adj_E (summed
    over substeps)."""
    dx = step.dx
    dt = step.dt
    inv_dx = step.inv_dx
    x = ptcl.base[p] + s.u[p]
    Fp = K.deformation_gradient(s.G[p])
    Ep = ptcl.E[p]
    m = ptcl.mass[p]
    kv = 4.0 * inv_dx * inv_dx * dt * ptcl.volume[p]
    lm = Ep * step.lame_per_E
    R = K.polar_rotation(Fp)
    A = m * s.C[p] - kv * K.kirchhoff_stress_polar(Fp, R, lm[0], lm[1])
    mvp = m * (s.v[p] + a_ext * dt)
    b = K.stencil_base(x, inv_dx, step.nodes)
    fx = x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2]))
    wx = K.bspline_w(fx[0])
    wy = K.bspline_w(fx[1])
    wz = K.bspline_w(fx[2])
    dwx = bspline_dw(fx[0])
    dwy = bspline_dw(fx[1])
    dwz = bspline_dw(fx[2])
    g_mv = wp.vec3(0.0)
    gA = wp.mat33(0.0)
    gfx = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * dx
                gq = adj_mmv[b[0] + i, b[1] + j, b[2] + k]
                gn = wp.vec3(gq[0], gq[1], gq[2])
                g_mv += w * gn
                gA += w * wp.outer(gn, dpos)
                gw = wp.dot(gn, mvp + A * dpos) + gq[3] * m
                gfx += gw * wp.vec3(dwx[i] * wy[j] * wz[k], wx[i] * dwy[j] * wz[k], wx[i] * wy[j] * dwz[k])
    adj.v[p] = m * g_mv
    adj.C[p] = m * gA
    gF, gE = stress_vjp(Fp, R, Ep, step.lame_per_E, -kv * gA)
    adj.G[p] = adj.G[p] + gF
    adj_E[p] = adj_E[p] + gE
    adj.u[p] = adj.u[p] + gfx * inv_dx - wp.transpose(A) * g_mv


@wp.kernel(enable_backward=False)
def g2p_adjoint(
    binned: int,
    count: int,
    ptcl: K.Particles,
    states: wp.array(dtype=wp.uint64),
    row: int,
    step: K.StepParams,
    grid_v: wp.array3d(dtype=wp.vec3),
    adj: K.ParticleVars,
    adj_grid_v: wp.array3d(dtype=wp.vec4),
):
    """g2p_adjoint_particle for each of the count particles from stored state `row` to
    row + 1 (the last substep of a segment). binned: launched over whole warps
    (gather.rows_threads), the warp sums the grid-velocity cotangents (adjoint_row_sums)."""
    t = wp.tid()
    base, fx, gvel, Ag = no_payload()
    if t < count:
        s = K.stored_state(states, row, count)
        s_next = K.stored_state(states, row + 1, count)
        base, fx, gvel, Ag = g2p_adjoint_particle(ptcl.order[t], binned, ptcl, s, s_next, step, grid_v, adj,
                                                  adj_grid_v)
    if binned != 0:
        adjoint_row_sums(base, fx, gvel, Ag, step, adj_grid_v)


@wp.kernel(enable_backward=False)
def p2g_adjoint(
    ptcl: K.Particles,
    states: wp.array(dtype=wp.uint64),
    row: int,
    step: K.StepParams,
    forces: K.Forces,
    t_offset: float,
    adj_mmv: wp.array3d(dtype=wp.vec4),
    adj: K.ParticleVars,
    adj_E: wp.array(dtype=float),
):
    """p2g_adjoint_particle for every particle from stored state `row` (the first substep
    of a segment, at t_frame + t_offset s)."""
    p = ptcl.order[wp.tid()]
    a_ext = K.external_accel(p, t_offset, forces)
    p2g_adjoint_particle(p, ptcl, K.stored_state(states, row, adj.u.shape[0]), step, a_ext, adj_mmv, adj, adj_E)


@wp.kernel(enable_backward=False)
def p2g_g2p_adjoint(
    ptcl: K.Particles,
    states: wp.array(dtype=wp.uint64),
    row: int,
    step: K.StepParams,
    forces: K.Forces,
    t_offset: float,
    grid_v_prev: wp.array3d(dtype=wp.vec3),
    adj_mmv: wp.array3d(dtype=wp.vec4),
    adj: K.ParticleVars,
    adj_E: wp.array(dtype=float),
    binned: int,
    count: int,
    adj_grid_v: wp.array3d(dtype=wp.vec4),
):
    """The P2G adjoint of a substep (stored state `row`, at t_frame + t_offset) fused with
    the G2P adjoint of the substep before (state row - 1, its grid velocity grid_v_prev):
    each thread owns its particle's cotangents, so the second reads what the first wrote,
    and the cotangents are read and written once instead of twice. binned as in
    g2p_adjoint."""
    t = wp.tid()
    base, fx, gvel, Ag = no_payload()
    if t < count:
        p = ptcl.order[t]
        s = K.stored_state(states, row, count)
        s_prev = K.stored_state(states, row - 1, count)
        a_ext = K.external_accel(p, t_offset, forces)
        p2g_adjoint_particle(p, ptcl, s, step, a_ext, adj_mmv, adj, adj_E)
        base, fx, gvel, Ag = g2p_adjoint_particle(p, binned, ptcl, s_prev, s, step, grid_v_prev, adj, adj_grid_v)
    if binned != 0:
        adjoint_row_sums(base, fx, gvel, Ag, step, adj_grid_v)


@wp.kernel(enable_backward=False)
def grid_adjoint(
    step: K.StepParams,
    grid_mmv: wp.array3d(dtype=wp.vec4),
    adj_grid_v: wp.array3d(dtype=wp.vec4),
    adj_mmv: wp.array3d(dtype=wp.vec4),
    binned: int,
    blocks: wp.array3d(dtype=int),
    tag: int,
):
    """Adjoint of kernels.node_velocity per node; consumes (zeroes) adj_grid_v and the stored
    momentum and mass (the next recompute's P2G adds into them: this saves a memset per
    substep). When binned, only the nodes of blocks the recompute tagged `tag` are visited
    (gather.block_tagged): every node with mass or a cotangent lies in one.

    A node no particle reached holds an all-zero vec4, and its grid-velocity cotangent is
    zero too (the cotangent scatter carries the same B-spline weights as the P2G; a weight
    so small that w m underflows leaves at most a denormal behind): it reads nothing more
    and writes nothing. Its adj_mmv keeps an older, finite value, which the P2G adjoint
    only ever multiplies by a zero weight and weight derivative (a particle's stencil
    nodes all get mass, except where a B-spline factor and its derivative are both 0).
    Most nodes are empty and the stored grids are cold in the cache, so this cut the kernel
    from 20.2 to 11.3 us at 100k / 64^3 and from 163 to 36 us at 300k / 128^3 (H200,
    docs/gpu-runs/vec4_reduction_{100k,300k}_h200.json). One thread a node over a 1-D
    launch of gather.grid_threads (kernels.node_of)."""
    nodes = step.nodes
    n = K.node_of(wp.tid(), nodes, step.inv_nodes)
    i = n[0]
    j = n[1]
    k = n[2]
    pad = step.pad
    if binned != 0 and not block_tagged(blocks, tag, i, j, k):
        return
    q = grid_mmv[i, j, k]
    m = q[3]
    if m == 0.0 and q[0] == 0.0 and q[1] == 0.0 and q[2] == 0.0:
        return
    g4 = adj_grid_v[i, j, k]
    adj_grid_v[i, j, k] = wp.vec4(0.0)
    grid_mmv[i, j, k] = wp.vec4(0.0)
    g = wp.vec3(g4[0], g4[1], g4[2])
    mv = wp.vec3(q[0], q[1], q[2])
    out = wp.vec4(0.0)
    damping_factor = step.damping_factor
    if m > K.MIN_NODE_MASS and step.fixed[i, j, k] == 0:
        inv_m = 1.0 / m  # one division for the node's seven
        vel = (mv * inv_m + step.dt * step.gravity) * damping_factor
        # each boundary condition zeroes one component by the sign of that component only
        if (i < pad and vel[0] < 0.0) or (i >= nodes[0] - pad and vel[0] > 0.0):
            g = wp.vec3(0.0, g[1], g[2])
        if (j < pad and vel[1] < 0.0) or (j >= nodes[1] - pad and vel[1] > 0.0):
            g = wp.vec3(g[0], 0.0, g[2])
        if (k < pad and vel[2] < 0.0) or (k >= nodes[2] - pad and vel[2] > 0.0):
            g = wp.vec3(g[0], g[1], 0.0)
        if step.use_ground != 0:
            if float(k) * step.dx <= step.ground_z and vel[2] < 0.0:
                g = wp.vec3(g[0], g[1], 0.0)
        gq = g * damping_factor  # cotangent of mv / m
        gmv = gq * inv_m
        out = wp.vec4(gmv[0], gmv[1], gmv[2], -wp.dot(gq, mv) * inv_m * inv_m)
    adj_mmv[i, j, k] = out


# --------------------------------------------------------------------------------------
# Launchers
# --------------------------------------------------------------------------------------
def recompute_segment(ctx, dt: float, k0: int, states: list, grids: list, binned: bool,
                      table: wp.array | None = None) -> None:
    """Forward substeps k0 .. k0 + len(grids) - 1 from the segment's first state, writing
    every later state and keeping each substep's grid mass, momentum and velocity in grids.

    binned (CUDA): as the fast path, each G2P and the next substep's P2G in one launch
    (gather.g2p2g_rows_stored), over the states whose table (kernels.state_table) is
    `table`, rows 0 .. len(grids); otherwise the atomic scatter P2G over `states`
    (ParticleStates)."""
    geo, dev = ctx.geo, ctx.device
    ptcl, step, forces = ctx.particles(), ctx.step(dt), ctx.forces_struct()
    n = ctx.base.shape[0]
    count = len(grids)
    # grids arrive with zero mass and momentum: adjoint_segment's grid_adjoint leaves them so
    if not binned:
        for i in range(count):
            g = grids[i]
            wp.launch(K.p2g, dim=n, device=dev, inputs=[
                ptcl, states[i].struct, step, forces, float((k0 + i) * dt), g.mmv])
            wp.launch(K.grid_update, dim=geo.nodes, device=dev, inputs=[step, g.mmv, g.v])
            wp.launch(K.g2p, dim=n, device=dev, block_dim=PARTICLE_BLOCK, inputs=[
                ptcl, states[i].struct, step, g.v, states[i + 1].struct, ctx.stats])
        return

    launch_g2p2g_stored(ctx, 0, table, 0, step, k0 * dt, grids[0].v, grids[0].mmv, grids[0].blocks, block_tag(k0, 0))
    for i in range(count):
        g = grids[i]
        wp.launch(grid_update_tagged, dim=grid_threads(geo), device=dev,
                  inputs=[step, g.mmv, g.v, 0, g.blocks, block_tag(k0, i)])
        if i < count - 1:
            # G2P of substep i into state i + 1, then its P2G into grid i + 1
            nxt = grids[i + 1]
            launch_g2p2g_stored(ctx, 1, table, i + 1, step, (k0 + i + 1) * dt, g.v, nxt.mmv, nxt.blocks,
                                block_tag(k0, i + 1))
        else:
            wp.launch(K.g2p_stored, dim=n, device=dev, block_dim=PARTICLE_BLOCK, inputs=[
                ptcl, table, i, step, g.v, ctx.stats])


def adjoint_segment(ctx, dt: float, k0: int, states: wp.array, grids: list, adj, adj_grid, binned: bool) -> None:
    """Reverse of substeps k0 .. k0 + len(grids) - 1 (forward values from recompute_segment):
    adj (u, v, C, F cotangents of the segment's last state as a ParticleState, plus E's
    running sum [N] float) becomes the cotangents of the segment's first state, in place.

    states: the table (kernels.state_table) of the segment's len(grids) + 1 stored states, rows
    0 .. len(grids). adj_grid = (adj_grid_v, adj_mmv), vec4 arrays (adj_grid_v's w unused):
    adj_grid_v must be zero on entry and is left zero; so are the grids' momentum and mass
    on exit (ready for the next recompute). binned: each warp sums the grid-velocity
    cotangents of its particles before one reduction a node (CUDA) instead of atomics a
    particle."""
    geo, dev = ctx.geo, ctx.device
    ptcl, step, forces = ctx.particles(), ctx.step(dt), ctx.forces_struct()
    adj_state, adj_E = adj
    n = adj_state.u.shape[0]
    adj_s = adj_state.struct
    adj_gv, adj_mmv = adj_grid
    count = len(grids)
    last = count - 1
    threads = rows_threads(n) if binned else n
    # ROWS_BLOCK: warp_row_sums' shared arrays are sized for it
    wp.launch(g2p_adjoint, dim=threads, device=dev, block_dim=ROWS_BLOCK, inputs=[
        int(binned), n, ptcl, states, last, step, grids[last].v, adj_s, adj_gv])
    for i in range(last, -1, -1):
        g = grids[i]
        wp.launch(grid_adjoint, dim=grid_threads(geo), device=dev,
                  inputs=[step, g.mmv, adj_gv, adj_mmv, int(binned), g.blocks, block_tag(k0, i)])
        t_offset = float((k0 + i) * dt)
        if i > 0:
            wp.launch(p2g_g2p_adjoint, dim=threads, device=dev, block_dim=ROWS_BLOCK, inputs=[
                ptcl, states, i, step, forces, t_offset, grids[i - 1].v, adj_mmv, adj_s, adj_E,
                int(binned), n, adj_gv])
        else:
            wp.launch(p2g_adjoint, dim=n, device=dev, block_dim=PARTICLE_BLOCK, inputs=[
                ptcl, states, 0, step, forces, t_offset, adj_mmv, adj_s, adj_E])
