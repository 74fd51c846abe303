"""P2G with few float atomics for the fast path: particles grouped in runs of one cell, nine
threads per run, one per row of three stencil nodes.

The scatter P2G (kernels.p2g_scatter) does 27 x 4 float atomics per particle. On a GPU
those atomics, not arithmetic, bound the substep (bench/sim_profile.py: 105 of the 136 us
of a 100k-particle substep on an H200). Here:

1. `g2p_bin` (per particle): G2P of this substep (skipped for a run's first binning), then
   the particle's P2G payload for the next one (B-spline offset fx, mass, momentum, MLS
   affine matrix: the stress is evaluated once per particle) and its stencil cell.
2. `find_runs` (per particle): the solver stores particles in cell order, so a cell's
   particles sit next to each other. A run is such a stretch, cut at multiples of
   RUN_MAX when the cell is crowded (a thin leaf on a fine grid: up to 500 particles in a
   cell), so that its particles are summed by runs in parallel instead of one long loop.
   Each run's first particle appends itself to the list of runs.
3. `p2g_runs` (9 threads per run, each owning a row of 3 stencil nodes): sum the run's
   particles' contributions to those nodes, then one reduction per node (`red_add_vec4`:
   momentum and mass in one 128-bit `red` on sm_90+). Atomics drop by the particles per run
   (about 8), and the threads of a run read the same payload (L1 broadcasts) and write
   different nodes.
4. `grid_update_clear_bins` (per node): the usual grid update, clearing the grid and the
   run count for the next substep.

No particle is ever left out: particles that drift out of cell order only make more,
shorter runs (one per particle at worst, 27 reductions each, as the scatter's 27).

Only untaped runs use this (the fast path, and the differentiable path's forward and
recompute); the taped replay keeps the scatter P2G, whose adjoint warp generates.
"""
from __future__ import annotations

import warp as wp

from pd_tool.sim import kernels as K

RUN_MAX = 32  # a crowded cell's particles are cut into runs of 16 to 47 at multiples of this
RUN_MAX_W = wp.constant(RUN_MAX)
# CUDA threads per block (warp's default is 256); module attributes so that
# bench/sim_profile.py --blocks can sweep them. H200, 100k particles: the particle kernel
# takes 32 us at 256, 25 at 128, 24 at 64; the per-cell sums 29-31 us at any size.
PARTICLE_BLOCK = 64
CELL_BLOCK = 256
# Runs summed per pass of the per-run kernel: it is launched for this many (or every
# possible) runs and loops, instead of one idle thread group per possible run.
RUNS_PER_PASS = 16384


# One 128-bit reduction instead of four 32-bit atomics. Hopper (sm_90) has vector `red`
# for f32; warp's atomic_add on a vec4 issues one atomic per component. H200, 100k
# particles / 64^3: the cell sums take 14.4 us instead of 26.7, the adjoint's cotangent
# scatter 14.1 instead of 22.3 (bench/try_vec4_red.py at 72a21c2,
# docs/gpu-runs/vec4_reduction_100k_h200.json). The address is converted to a global one
# because vector `red` exists only for the global space. Older GPUs and the CPU add per
# component. No adjoint: only untaped kernels use it.
_RED_ADD_VEC4 = """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
    wp::vec4* p = wp::address(arr, i, j, k);
    asm volatile("{ .reg .u64 ga; cvta.to.global.u64 ga, %0; red.global.add.v4.f32 [ga], {%1, %2, %3, %4}; }"
                 :: "l"(p), "f"(value[0]), "f"(value[1]), "f"(value[2]), "f"(value[3]) : "memory");
#else
    wp::atomic_add(wp::address(arr, i, j, k), value);
#endif
"""


@wp.func_native(_RED_ADD_VEC4)
def red_add_vec4(arr: wp.array3d(dtype=wp.vec4), i: int, j: int, k: int, value: wp.vec4):
    """arr[i, j, k] += value, atomically, with no result (untaped kernels only)."""
    ...


@wp.struct
class CellLists:
    """Particle runs and the per-particle P2G payload, on the device.

    cell [N]: each particle's stencil cell this substep (-1: in no run); starts [<= N]: the
    first particle of each run, n_starts [1] runs in all;
    pay_fx [N]: B-spline offset x/dx - base; pay_mv [N]: momentum (kg m/s) and mass (kg);
    pay_A [N]: MLS affine matrix m C - 4/dx^2 dt V tau (kg/s)."""

    cell: wp.array(dtype=int)
    starts: wp.array(dtype=int)
    n_starts: wp.array(dtype=int)
    pay_fx: wp.array(dtype=wp.vec3)
    pay_mv: wp.array(dtype=wp.vec4)
    pay_A: wp.array(dtype=wp.mat33)


@wp.func
def bin_particle(
    p: int,
    x: wp.vec3,
    v: wp.vec3,
    C: wp.mat33,
    F: wp.mat33,
    E: float,
    vol: float,
    m: float,
    a_ext: wp.vec3,
    nu: float,
    dx: float,
    dt: float,
    nodes: wp.vec3i,
    lists: CellLists,
):
    """Write particle p's P2G payload and stencil cell."""
    inv_dx = 1.0 / dx
    b = K.stencil_base(x, inv_dx, nodes)
    lists.cell[p] = (b[0] * nodes[1] + b[1]) * nodes[2] + b[2]
    lm = K.lame(E, nu)
    tau = K.kirchhoff_stress(F, lm[0], lm[1])
    lists.pay_fx[p] = x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2]))
    mv = m * (v + a_ext * dt)
    lists.pay_mv[p] = wp.vec4(mv[0], mv[1], mv[2], m)
    lists.pay_A[p] = m * C - (4.0 * inv_dx * inv_dx * dt * vol) * tau


@wp.func
def splits_run(lists: CellLists, p: int, c: int) -> int:
    """1 where a stretch of cell c's particles is cut before particle p: at multiples of
    RUN_MAX, where at least RUN_MAX / 2 of the cell's particles come before (a cell of a
    few particles that happens to straddle a multiple stays one run)."""
    cut = int(0)
    if p % RUN_MAX_W == 0 and p >= RUN_MAX_W // 2:
        if lists.cell[p - RUN_MAX_W // 2] == c:
            cut = 1
    return cut


@wp.kernel(enable_backward=False)
def find_runs(lists: CellLists):
    """Particle p starts a run where its cell differs from particle p - 1's or where a
    crowded cell's stretch is cut (splits_run); run starts append themselves to
    lists.starts. A cell of -1 (a particle with nothing to add: the adjoint's static ones)
    is in no run."""
    p = wp.tid()
    c = lists.cell[p]
    prev = int(-1)
    if p > 0:
        prev = lists.cell[p - 1]
    if c >= 0:
        if c != prev or splits_run(lists, p, c) != 0:
            lists.starts[wp.atomic_add(lists.n_starts, 0, 1)] = p


@wp.kernel(enable_backward=False)
def g2p_bin(
    do_g2p: int,
    ptcl: K.Particles,
    s_in: K.ParticleVars,
    state: K.ParticleVars,
    step: K.StepParams,
    forces: K.Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    lists: CellLists,
    stats: wp.array(dtype=float),
):
    """G2P of this substep from s_in (its u and F) into `state` (unless do_g2p is 0: the
    run's first binning), then the payload and binning of `state` for the next substep at
    t_frame + t_offset_next (s). The fast path passes the same arrays as s_in and state (in
    place: each thread owns its particle); the backward's recompute passes the previous
    substep's, keeping every state. Thread t handles particle t (ptcl.order is not read:
    both callers store the particles in cell order)."""
    p = wp.tid()
    if do_g2p != 0:
        K.g2p_gather(p, ptcl, s_in, step, grid_v, state, stats)
    a_ext = K.external_accel(p, t_offset_next, forces)
    bin_particle(p, ptcl.base[p] + state.u[p], state.v[p], state.C[p], K.deformation_gradient(state.G[p]),
                 ptcl.E[p], ptcl.volume[p], ptcl.mass[p], a_ext, step.nu, step.dx, step.dt, step.nodes, lists)


@wp.func
def bspline_at(fx: float, a: int) -> float:
    """Quadratic B-spline weight of stencil offset a (0, 1, 2) at fx in [0.5, 1.5)."""
    w = 0.0
    if a == 0:
        w = 0.5 * (1.5 - fx) * (1.5 - fx)
    elif a == 1:
        w = 0.75 - (fx - 1.0) * (fx - 1.0)
    else:
        w = 0.5 * (fx - 0.5) * (fx - 0.5)
    return w


@wp.func
def cell_row_terms(
    run: int,
    a: int,
    b: int,
    lists: CellLists,
    dx: float,
    nodes: wp.vec3i,
):
    """The shares of the particles of run `run` (from particle lists.starts[run] to the
    next change of cell or cut) of the three nodes (a, b, 0..2) of their cell's stencil: the node index of the first, the masses sum w_n m and
    the vectors sum w_n (q + A dpos_n) of the payload (mass, q = momentum, A = affine
    matrix). The adjoint's scatter uses the vector sums alone (adjoint.py)."""
    start = lists.starts[run]
    cell = lists.cell[start]
    ck = cell % nodes[2]
    cj = (cell // nodes[2]) % nodes[1]
    ci = cell // (nodes[1] * nodes[2])
    m0 = float(0.0)
    m1 = float(0.0)
    m2 = float(0.0)
    mv0 = wp.vec3(0.0)
    mv1 = wp.vec3(0.0)
    mv2 = wp.vec3(0.0)
    n = lists.cell.shape[0]
    q = start
    while q < n:
        if q > start:
            if lists.cell[q] != cell or splits_run(lists, q, cell) != 0:
                break
        fx = lists.pay_fx[q]
        pm = lists.pay_mv[q]
        A = lists.pay_A[q]
        wab = bspline_at(fx[0], a) * bspline_at(fx[1], b)
        wz = K.bspline_w(fx[2])
        mom = wp.vec3(pm[0], pm[1], pm[2])
        # (off - fx) dx with off = (a, b, c): A times it is linear in c
        d0 = wp.vec3(float(a) - fx[0], float(b) - fx[1], -fx[2]) * dx
        q0 = mom + A * d0
        dq = wp.vec3(A[0, 2], A[1, 2], A[2, 2]) * dx
        w0 = wab * wz[0]
        w1 = wab * wz[1]
        w2 = wab * wz[2]
        m0 += w0 * pm[3]
        m1 += w1 * pm[3]
        m2 += w2 * pm[3]
        mv0 += w0 * q0
        mv1 += w1 * (q0 + dq)
        mv2 += w2 * (q0 + 2.0 * dq)
        q += 1
    return wp.vec3i(ci + a, cj + b, ck), wp.vec3(m0, m1, m2), mv0, mv1, mv2


@wp.func
def cell_row_sums(
    run: int,
    a: int,
    b: int,
    lists: CellLists,
    dx: float,
    nodes: wp.vec3i,
    grid_mmv: wp.array3d(dtype=wp.vec4),
):
    """cell_row_terms of one run and row, then three (momentum, mass) reductions."""
    n, m, mv0, mv1, mv2 = cell_row_terms(run, a, b, lists, dx, nodes)
    red_add_vec4(grid_mmv, n[0], n[1], n[2], wp.vec4(mv0[0], mv0[1], mv0[2], m[0]))
    red_add_vec4(grid_mmv, n[0], n[1], n[2] + 1, wp.vec4(mv1[0], mv1[1], mv1[2], m[1]))
    red_add_vec4(grid_mmv, n[0], n[1], n[2] + 2, wp.vec4(mv2[0], mv2[1], mv2[2], m[2]))


@wp.func
def cell_lane_row(t: int) -> wp.vec3i:
    """Thread t of a nine-threads-per-run launch: (run lane, stencil offsets a, b) of the
    row of nodes (a, b, 0..2) it owns."""
    lane = t // 9
    o = t - 9 * lane
    a = o // 3
    return wp.vec3i(lane, a, o - 3 * a)


@wp.kernel(enable_backward=False)
def p2g_runs(
    lists: CellLists,
    dx: float,
    nodes: wp.vec3i,
    runs_per_pass: int,
    grid_mmv: wp.array3d(dtype=wp.vec4),
):
    """Thread (run lane, stencil offsets a, b): for the runs lane, lane + runs_per_pass,
    ... (the count is known only on the device), that run's shares of the row of nodes
    (a, b, 0..2).

    Nine threads a run: each payload read serves three nodes, and the run's threads read
    the same payload (L1 broadcasts). Measured on an H200 at 100k particles: 27 threads a
    cell 34 us, 9 threads 29 us, 3 threads 29 us; launching 9 threads per particle and
    letting only each cell's first particle work, to save the shared run counter, 44 us.
    """
    lane_row = cell_lane_row(wp.tid())
    n = lists.n_starts[0]
    slot = lane_row[0]
    while slot < n:
        cell_row_sums(slot, lane_row[1], lane_row[2], lists, dx, nodes, grid_mmv)
        slot += runs_per_pass


@wp.kernel(enable_backward=False)
def grid_update_clear_bins(
    step: K.StepParams,
    grid_mmv: wp.array3d(dtype=wp.vec4),
    grid_v: wp.array3d(dtype=wp.vec3),
    clear_grid: int,
    lists: CellLists,
):
    """The grid update that also empties the run list for the next binning and, with
    clear_grid (the fast path), zeroes mass and momentum for the next P2G; the backward's
    recompute keeps them (its adjoint reads them)."""
    i, j, k = wp.tid()
    grid_v[i, j, k] = K.node_velocity(grid_mmv[i, j, k], i, j, k, step)
    if clear_grid != 0:
        grid_mmv[i, j, k] = wp.vec4(0.0)
    if i == 0 and j == 0 and k == 0:
        lists.n_starts[0] = 0


def alloc_cell_lists(n_particles: int, device) -> CellLists:
    """CellLists for n_particles particles (zeroed)."""
    n = max(1, n_particles)
    z = lambda n, t=int: wp.zeros(n, dtype=t, device=device)  # noqa: E731
    lists = CellLists()
    lists.cell, lists.starts, lists.n_starts = z(n), z(n), z(1)
    lists.pay_fx, lists.pay_mv, lists.pay_A = z(n, wp.vec3), z(n, wp.vec4), z(n, wp.mat33)
    return lists


def runs_per_pass(lists: CellLists) -> int:
    """Thread groups of a per-run launch: one per possible run, at most RUNS_PER_PASS."""
    return min(RUNS_PER_PASS, lists.starts.shape[0])


def run_substeps_binned(ctx, n: int, dt: float, st, g, lists: CellLists) -> None:
    """n substeps in place without a tape, with the binned P2G (see module doc).

    Same arguments as solver.run_substeps_fused plus the cell lists; the same result up to
    the order of float sums. Four launches per substep. The run count is cleared here
    first, so a call (or a replay of its captured graph) never sees one left by the one
    before.
    """
    dev, geo = ctx.device, ctx.geo
    ptcl, step, forces, sv = ctx.particles(), ctx.step(dt), ctx.forces_struct(), st.struct
    nodes, dx = geo.nodes_vec, float(geo.dx)
    count = st.u.shape[0]
    g.mmv.zero_()
    lists.n_starts.zero_()

    def bin_particles(do_g2p: int, t_offset: float) -> None:
        wp.launch(g2p_bin, dim=count, device=dev, block_dim=PARTICLE_BLOCK, inputs=[
            do_g2p, ptcl, sv, sv, step, forces, float(t_offset), g.v, lists, ctx.stats])
        wp.launch(find_runs, dim=count, device=dev, block_dim=PARTICLE_BLOCK, inputs=[lists])

    bin_particles(0, 0.0)
    per_pass = runs_per_pass(lists)
    for s in range(n):
        wp.launch(p2g_runs, dim=9 * per_pass, device=dev, block_dim=CELL_BLOCK,
                  inputs=[lists, dx, nodes, per_pass, g.mmv])
        wp.launch(grid_update_clear_bins, dim=geo.nodes, device=dev, inputs=[step, g.mmv, g.v, 1, lists])
        if s < n - 1:
            bin_particles(1, (s + 1) * dt)
        else:
            wp.launch(K.g2p, dim=count, device=dev, block_dim=PARTICLE_BLOCK,
                      inputs=[ptcl, sv, step, g.v, sv, ctx.stats])
