"""P2G with few float atomics for the fast path: particles in cell order, each cell's shares
summed before one reduction a node.

The scatter P2G (kernels.p2g_scatter) does 27 x 4 float atomics per particle. On a GPU
those atomics, not arithmetic, bound the substep (bench/sim_profile.py: 105 of the 136 us
of a 100k-particle substep on an H200). Here, per substep:

1. `g2p2g_rows` (per particle, whole warps): G2P of this substep (skipped for a call's
   first P2G), then the particle's P2G payload for the next one (B-spline offset fx, mass,
   momentum, MLS affine matrix: the stress is evaluated once per particle), stashed in
   shared memory with its stencil cell. Then, within each warp, 27 lanes in three groups of
   nine each own a row of three stencil nodes and sum the shares of a third of the warp's
   particles while the cell stays the same, adding the sums to the grid when it changes,
   one reduction per node (`red_add_vec4`: momentum and mass in one 128-bit `red` on
   sm_90+). The solver stores particles in cell order, so a group holds one cell's
   particles or a few cells'.
2. `grid_update_tagged` (per node): the usual grid update, clearing the grid for the
   next substep. It visits only the nodes of the 4^3-node blocks that step 1 tagged this
   substep: a thin object leaves most of its grid empty.

The backward's grid-velocity cotangent is summed the same way, in the G2P adjoint's launch
(adjoint.adjoint_row_sums). The same sums also run from a payload in global memory in a
launch of their own, the fast path's with `MPMSolver(warp_sums=False)`: `g2p_bin` writes
it, `p2g_chunks` sums it in chunks of CHUNK consecutive particles, nine threads a chunk. A
group's or chunk's length is fixed, so no thread waits on a long loop through a crowded
cell (a thin leaf on a fine grid: up to 500 particles a cell) and no list of where cells
start is built.

No particle is ever left out: particles that drift out of cell order only make more
changes of cell (one per particle at worst, 27 reductions each, as the scatter's 27).

Only untaped runs use this (the fast path, and the differentiable path's forward and
recompute); the taped replay keeps the scatter P2G, whose adjoint warp generates.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from pd_tool.sim import kernels as K

K.lean_launches(__name__)

# Particles a chunk sums. H100, substep of the 300k-Gaussian plant with 3 mm leaves (118,626
# particles on 89 x 75 x 128 cells), P2G: 36.7 us at 8, 37.2 at 16, 43.1 at 32; runs of one
# cell cut at 8 / 32 particles took 39.3 / 59.0 plus 7-10 us to list them
# (bench/sim_profile.py --scene thin --chunk K).
CHUNK = 8
CHUNK_W = wp.constant(CHUNK)
# CUDA threads per block (warp's default is 256); module attributes so that
# bench/sim_profile.py --blocks can sweep them. H200, 100k particles: the particle kernel
# takes 32 us at 256, 25 at 128, 24 at 64; the per-cell sums 29-31 us at any size.
PARTICLE_BLOCK = 64
CELL_BLOCK = 256
# Threads a block of g2p2g_rows, fixed: its shared arrays are sized for it at import.
ROWS_BLOCK = 64
# Grid nodes per edge of an activity block: the chunk sums tag the blocks their nodes lie
# in, and the grid kernels visit only nodes of blocks tagged this substep (block_tagged).
BLOCK = 4
BLOCK_W = wp.constant(BLOCK)


# One 128-bit reduction instead of four 32-bit atomics. Hopper (sm_90) has vector `red`
# for f32; warp's atomic_add on a vec4 issues one atomic per component. H200, 100k
# particles / 64^3: the cell sums take 14.4 us instead of 26.7, the adjoint's cotangent
# scatter 14.1 instead of 22.3 (bench/try_vec4_red.py at 72a21c2,
# docs/gpu-runs/vec4_reduction_100k_h200.json). The address is converted to a global one
# because vector `red` exists only for the global space. Older GPUs and the CPU add per
# component. No adjoint: only untaped kernels use it.
def _red_v4(ptr: str, x: str, y: str, z: str, w: str) -> str:
    """CUDA source adding the floats (x, y, z, w) to the wp::vec4 at `ptr` (C expressions):
    one vector `red` on sm_90+, per-component atomics before."""
    return f"""
#if (__CUDA_ARCH__ >= 900)
    asm volatile("{{ .reg .u64 ga; cvta.to.global.u64 ga, %0; red.global.add.v4.f32 [ga], {{%1, %2, %3, %4}}; }}"
                 :: "l"({ptr}), "f"({x}), "f"({y}), "f"({z}), "f"({w}) : "memory");
#else
    wp::atomic_add({ptr}, wp::vec4({x}, {y}, {z}, {w}));
#endif
"""


_RED_ADD_VEC4 = f"""
#if defined(__CUDA_ARCH__)
    wp::vec4* p = wp::address(arr, i, j, k);
    {_red_v4("p", "value[0]", "value[1]", "value[2]", "value[3]")}
#else
    wp::atomic_add(wp::address(arr, i, j, k), value);
#endif
"""


@wp.func_native(_RED_ADD_VEC4)
def red_add_vec4(arr: wp.array3d(dtype=wp.vec4), i: int, j: int, k: int, value: wp.vec4):
    """arr[i, j, k] += value, atomically, with no result (untaped kernels only)."""
    ...


# warp's vec4 has the alignment of a float, so nvcc splits a vec4 access into four 32-bit
# ones. These read and write a vec4 array element (16-byte aligned: an array starts on 256
# bytes and its elements are 16 bytes) with one 128-bit access. The load goes through the
# read-only cache (__ldg), so an array read with it must not be written by the same launch.
# The CPU reads and writes plainly. No adjoint: untaped kernels only.
_LOAD_VEC4 = """
#if defined(__CUDA_ARCH__)
    const float4 q = __ldg(reinterpret_cast<const float4*>(wp::address(arr, i)));
    return wp::vec4(q.x, q.y, q.z, q.w);
#else
    return *wp::address(arr, i);
#endif
"""
_STORE_VEC4 = """
#if defined(__CUDA_ARCH__)
    *reinterpret_cast<float4*>(wp::address(arr, i)) = make_float4(value[0], value[1], value[2], value[3]);
#else
    *wp::address(arr, i) = value;
#endif
"""


@wp.func_native(_LOAD_VEC4)
def load_vec4(arr: wp.array(dtype=wp.vec4), i: int) -> wp.vec4:
    """arr[i] in one 128-bit load (arr not written by this launch)."""
    ...


@wp.func_native(_STORE_VEC4)
def store_vec4(arr: wp.array(dtype=wp.vec4), i: int, value: wp.vec4):
    """arr[i] = value in one 128-bit store."""
    ...


@wp.struct
class CellLists:
    """Each particle's stencil cell and P2G payload, on the device.

    cell [N]: each particle's stencil cell this substep (-1: adds nothing); pay_mv [N]:
    momentum (kg m/s) and mass (kg); pay_r0, pay_r1, pay_r2 [N]: row d of the MLS affine
    matrix A = m C - 4/dx^2 dt V tau (kg/s) in lanes 0-2 and the B-spline offset
    x_d/dx - base_d in lane 3. Four vec4s, so that the chunk sums read a particle's payload
    in four 128-bit loads (store_payload, load_payload) instead of sixteen 32-bit ones."""

    cell: wp.array(dtype=int)
    pay_mv: wp.array(dtype=wp.vec4)
    pay_r0: wp.array(dtype=wp.vec4)
    pay_r1: wp.array(dtype=wp.vec4)
    pay_r2: wp.array(dtype=wp.vec4)


@wp.func
def store_payload(lists: CellLists, p: int, fx: wp.vec3, mv: wp.vec4, A: wp.mat33):
    """Write particle p's payload: offset fx, (momentum, mass) mv, affine matrix A."""
    store_vec4(lists.pay_mv, p, mv)
    store_vec4(lists.pay_r0, p, wp.vec4(A[0, 0], A[0, 1], A[0, 2], fx[0]))
    store_vec4(lists.pay_r1, p, wp.vec4(A[1, 0], A[1, 1], A[1, 2], fx[1]))
    store_vec4(lists.pay_r2, p, wp.vec4(A[2, 0], A[2, 1], A[2, 2], fx[2]))


@wp.func
def load_payload(lists: CellLists, q: int):
    """Particle q's payload (fx, mv, A) as store_payload wrote it."""
    r0 = load_vec4(lists.pay_r0, q)
    r1 = load_vec4(lists.pay_r1, q)
    r2 = load_vec4(lists.pay_r2, q)
    A = wp.mat33(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2])
    return wp.vec3(r0[3], r1[3], r2[3]), load_vec4(lists.pay_mv, q), A


NO_CELL = wp.constant(wp.vec3i(-1, 0, 0))  # the stencil base of a lane that adds nothing (warp_row_sums)


@wp.func
def particle_payload(
    x: wp.vec3,
    v: wp.vec3,
    C: wp.mat33,
    F: wp.mat33,
    E: float,
    vol: float,
    m: float,
    a_ext: wp.vec3,
    step: K.StepParams,
):
    """A particle's stencil base node (i, j, k) and P2G payload: offset fx, (momentum, mass)
    and the MLS affine matrix A (CellLists' layout)."""
    inv_dx = step.inv_dx
    dt = step.dt
    b = K.stencil_base(x, inv_dx, step.nodes)
    lm = E * step.lame_per_E
    tau = K.kirchhoff_stress(F, lm[0], lm[1])
    mv = m * (v + a_ext * dt)
    return (b, x * inv_dx - wp.vec3(float(b[0]), float(b[1]), float(b[2])),
            wp.vec4(mv[0], mv[1], mv[2], m), m * C - (4.0 * inv_dx * inv_dx * dt * vol) * tau)


@wp.func
def particle_values(
    do_g2p: int,
    keep_vc: int,
    live: bool,
    p: int,
    ptcl: K.Particles,
    s_in: K.ParticleVars,
    state: K.ParticleVars,
    step: K.StepParams,
    forces: K.Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    stats: wp.array(dtype=float),
):
    """Particle p's G2P of this substep from s_in, written to `state` (v and C only with
    keep_vc; nothing unless live), or its state read from `state` when do_g2p is 0; then its
    stencil base node and payload for the next substep's P2G at t_frame + t_offset_next
    (particle_payload)."""
    un = wp.vec3(0.0)
    vel = wp.vec3(0.0)
    Cn = wp.mat33(0.0)
    Gn = wp.mat33(0.0)
    if do_g2p != 0:
        un, vel, Cn, Gn = K.g2p_values(p, ptcl, s_in, step, grid_v)
        if live:
            state.u[p] = un
            state.G[p] = Gn
            if keep_vc != 0:
                state.v[p] = vel
                state.C[p] = Cn
            K.g2p_guard(ptcl.base[p] + un, vel, Gn, step, stats)
    else:
        un = state.u[p]
        vel = state.v[p]
        Cn = state.C[p]
        Gn = state.G[p]
    return particle_payload(ptcl.base[p] + un, vel, Cn, K.deformation_gradient(Gn), ptcl.E[p], ptcl.volume[p],
                            ptcl.mass[p], K.external_accel(p, t_offset_next, forces), step)


@wp.kernel(enable_backward=False)
def g2p_bin(
    do_g2p: int,
    keep_vc: int,
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
    """G2P of this substep from s_in (its u and F) into `state` (unless do_g2p is 0: a
    call's first binning), then the payload and binning of `state` for the next substep at
    t_frame + t_offset_next (s). The fast path passes the same arrays as s_in and state (in
    place: each thread owns its particle); the backward's recompute passes the previous
    substep's, keeping every state. Thread t handles particle t (ptcl.order is not read:
    both callers store the particles in cell order).

    keep_vc 0 leaves v and C unwritten: the next substep's G2P makes them from the grid
    alone, so the fast path, which ends a call with a full G2P, stores only u and G between
    substeps, and the binning takes the new values from registers rather than reading them
    back (H100: 26.1 to 20.3 us at 100k particles / 64^3, 28.8 to 20.6 us on the thin
    plant's 118,626)."""
    p = wp.tid()
    b, fx, mv, A = particle_values(do_g2p, keep_vc, True, p, ptcl, s_in, state, step, forces, t_offset_next,
                                   grid_v, stats)
    lists.cell[p] = K.cell_index(b, step.nodes)
    store_payload(lists, p, fx, mv, A)


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
def chunk_row(t: int) -> wp.vec3i:
    """Thread t of a nine-threads-per-chunk launch: (chunk, stencil offsets a, b) of the
    row of nodes (a, b, 0..2) it owns."""
    lane = t // 9
    o = t - 9 * lane
    a = o // 3
    return wp.vec3i(lane, a, o - 3 * a)


@wp.func
def tag_row(blocks: wp.array3d(dtype=int), tag: int, n: wp.vec3i):
    """Tag the activity blocks of the nodes n, n + (0, 0, 1), n + (0, 0, 2) with `tag`. The
    tag is read first: most rows' blocks are tagged already, and a read served by the cache
    costs less than a store to a line that every SM writes."""
    bi = n[0] // BLOCK_W
    bj = n[1] // BLOCK_W
    b0 = n[2] // BLOCK_W
    b1 = (n[2] + 2) // BLOCK_W
    if blocks[bi, bj, b0] != tag:
        blocks[bi, bj, b0] = tag
    if b1 != b0:
        if blocks[bi, bj, b1] != tag:
            blocks[bi, bj, b1] = tag


@wp.func
def row_shares(q: int, a: int, b: int, lists: CellLists, dx: float):
    """Particle q's shares of the three nodes (a, b, 0..2) of its cell's stencil: the masses
    w_n m and the vectors w_n (momentum + A dpos_n) of its payload."""
    fx, pm, A = load_payload(lists, q)
    wab = bspline_at(fx[0], a) * bspline_at(fx[1], b)
    wz = K.bspline_w(fx[2])
    mom = wp.vec3(pm[0], pm[1], pm[2])
    # (off - fx) dx with off = (a, b, c): A times it is linear in c
    d0 = wp.vec3(float(a) - fx[0], float(b) - fx[1], -fx[2]) * dx
    q0 = mom + A * d0
    dq = wp.vec3(A[0, 2], A[1, 2], A[2, 2]) * dx
    w = wab * wz
    return w * pm[3], w[0] * q0, w[1] * (q0 + dq), w[2] * (q0 + 2.0 * dq)


@wp.func
def flush_row(cell: int, a: int, b: int, nodes: wp.vec3i, m: wp.vec3, mv0: wp.vec3, mv1: wp.vec3, mv2: wp.vec3,
              out: wp.array3d(dtype=wp.vec4), blocks: wp.array3d(dtype=int), tag: int):
    """Add the sums of one cell's row of nodes (a, b, 0..2) to `out` (three 128-bit
    reductions) and, unless tag is 0, tag their activity blocks."""
    ck = cell % nodes[2]
    cj = (cell // nodes[2]) % nodes[1]
    ci = cell // (nodes[1] * nodes[2])
    n = wp.vec3i(ci + a, cj + b, ck)
    red_add_vec4(out, n[0], n[1], n[2], wp.vec4(mv0[0], mv0[1], mv0[2], m[0]))
    red_add_vec4(out, n[0], n[1], n[2] + 1, wp.vec4(mv1[0], mv1[1], mv1[2], m[1]))
    red_add_vec4(out, n[0], n[1], n[2] + 2, wp.vec4(mv2[0], mv2[1], mv2[2], m[2]))
    if tag != 0:
        tag_row(blocks, tag, n)


@wp.func
def chunk_row_sums(chunk: int, a: int, b: int, lists: CellLists, dx: float, nodes: wp.vec3i,
                   out: wp.array3d(dtype=wp.vec4), blocks: wp.array3d(dtype=int), tag: int):
    """The shares of particles chunk * CHUNK .. + CHUNK - 1 of the rows (a, b, 0..2) of their
    cells' stencils, summed while the cell stays the same and added to `out` at each change
    (flush_row). Particles of cell -1 add nothing."""
    n = lists.cell.shape[0]
    q = chunk * CHUNK_W
    end = wp.min(q + CHUNK_W, n)
    cur = int(-1)
    m = wp.vec3(0.0)
    mv0 = wp.vec3(0.0)
    mv1 = wp.vec3(0.0)
    mv2 = wp.vec3(0.0)
    while q < end:
        c = lists.cell[q]
        if c != cur:
            if cur >= 0:
                flush_row(cur, a, b, nodes, m, mv0, mv1, mv2, out, blocks, tag)
            cur = c
            m = wp.vec3(0.0)
            mv0 = wp.vec3(0.0)
            mv1 = wp.vec3(0.0)
            mv2 = wp.vec3(0.0)
        if c >= 0:
            dm, d0, d1, d2 = row_shares(q, a, b, lists, dx)
            m += dm
            mv0 += d0
            mv1 += d1
            mv2 += d2
        q += 1
    if cur >= 0:
        flush_row(cur, a, b, nodes, m, mv0, mv1, mv2, out, blocks, tag)


@wp.kernel(enable_backward=False)
def p2g_chunks(lists: CellLists, dx: float, nodes: wp.vec3i, out: wp.array3d(dtype=wp.vec4),
               blocks: wp.array3d(dtype=int), tag: int):
    """Thread (chunk, stencil offsets a, b): chunk_row_sums."""
    t = chunk_row(wp.tid())
    chunk_row_sums(t[0], t[1], t[2], lists, dx, nodes, out, blocks, tag)


def chunk_threads(n_particles: int) -> int:
    """Threads of a p2g_chunks launch: nine per chunk."""
    return 9 * max(1, -(-n_particles // CHUNK))


@wp.func
def block_tagged(blocks: wp.array3d(dtype=int), tag: int, i: int, j: int, k: int) -> bool:
    """Whether node (i, j, k) lies in an activity block tagged `tag`.

    Each substep's chunk sums tag every block that one of their nodes lies in, so a node
    given mass or momentum this substep is in a tagged block, and so is every node a
    particle reads in the G2P that follows (the same stencils). A block whose tag is left
    from an older substep with the same tag is visited for nothing, never skipped wrongly:
    its nodes hold zero mass, so it is written as empty. An untagged node keeps its
    velocity from an older substep, which no particle reads."""
    return blocks[i // BLOCK_W, j // BLOCK_W, k // BLOCK_W] == tag


@wp.kernel(enable_backward=False)
def grid_update_tagged(
    step: K.StepParams,
    grid_mmv: wp.array3d(dtype=wp.vec4),
    grid_v: wp.array3d(dtype=wp.vec3),
    clear_grid: int,
    blocks: wp.array3d(dtype=int),
    tag: int,
):
    """The grid update of the nodes in blocks tagged `tag`, which, with clear_grid (the
    fast path), also zeroes mass and momentum for the next P2G; the backward's recompute
    keeps them (its adjoint reads them). One thread a node over a 1-D launch of
    grid_threads (kernels.node_of)."""
    n = K.node_of(wp.tid(), step.nodes, step.inv_nodes)
    i = n[0]
    j = n[1]
    k = n[2]
    if not block_tagged(blocks, tag, i, j, k):
        return
    grid_v[i, j, k] = K.node_velocity(grid_mmv[i, j, k], i, j, k, step)
    if clear_grid != 0:
        grid_mmv[i, j, k] = wp.vec4(0.0)


def grid_threads(geo) -> int:
    """Threads of a 1-D launch over every node of `geo` (grid_update_tagged, grid_adjoint)."""
    return int(np.prod(geo.nodes))


def block_tag(k0: int, i: int) -> int:
    """The activity tag of substep k0 + i of a run of substeps (block_tagged): its chunk
    sums write it, its grid update and the backward's grid adjoint read it. Unique within a
    frame; a tag reused in a later frame only makes a block be visited for nothing."""
    return k0 + i + 1


def block_shape(nodes: tuple[int, int, int]) -> tuple[int, int, int]:
    """Activity blocks per axis over a grid of `nodes` nodes."""
    return tuple(-(-int(n) // BLOCK) for n in nodes)


def touched_blocks(x: np.ndarray, geo) -> int:
    """Activity blocks the stencils of particles at x [N, 3] (m) reach on grid `geo`: what
    a substep's P2G would tag with the particles there (kernels.stencil_base's clamping)."""
    nodes = np.asarray(geo.nodes, np.int64)
    q = np.nan_to_num(np.asarray(x, np.float64) / float(geo.dx) - 0.5, nan=0.0)
    base = np.clip(np.floor(np.maximum(q, 0.0)), 0, nodes - 3).astype(np.int64)
    nb = np.asarray(block_shape(tuple(nodes)), np.int64)
    ends = (base // BLOCK, (base + 2) // BLOCK)  # a stencil's 3 nodes span 1 or 2 blocks an axis
    ids = [(ends[a][:, 0] * nb[1] + ends[b][:, 1]) * nb[2] + ends[c][:, 2]
           for a in (0, 1) for b in (0, 1) for c in (0, 1)]
    return int(np.unique(np.concatenate(ids)).size) if len(x) else 0


def alloc_cell_lists(n_particles: int, device) -> CellLists:
    """CellLists for n_particles particles (zeroed)."""
    n = max(1, n_particles)
    z = lambda n, t=int: wp.zeros(n, dtype=t, device=device)  # noqa: E731
    lists = CellLists()
    lists.cell = z(n)
    lists.pay_mv, lists.pay_r0, lists.pay_r1, lists.pay_r2 = (z(n, wp.vec4) for _ in range(4))
    return lists


def run_substeps_binned(ctx, n: int, dt: float, st, g, lists: CellLists) -> None:
    """n substeps in place without a tape, with the binned P2G (see module doc).

    Same arguments as solver.run_substeps_fused plus the cell lists; the same result up to
    the order of float sums. Three launches per substep.
    """
    dev, geo = ctx.device, ctx.geo
    ptcl, step, forces, sv = ctx.particles(), ctx.step(dt), ctx.forces_struct(), st.struct
    nodes, dx = geo.nodes_vec, float(geo.dx)
    count = st.u.shape[0]
    g.mmv.zero_()

    def bin_particles(do_g2p: int, t_offset: float) -> None:
        wp.launch(g2p_bin, dim=count, device=dev, block_dim=PARTICLE_BLOCK, inputs=[
            do_g2p, 0, ptcl, sv, sv, step, forces, float(t_offset), g.v, lists, ctx.stats])

    bin_particles(0, 0.0)
    for s in range(n):
        tag = block_tag(0, s)
        wp.launch(p2g_chunks, dim=chunk_threads(count), device=dev, block_dim=CELL_BLOCK,
                  inputs=[lists, dx, nodes, g.mmv, g.blocks, tag])
        wp.launch(grid_update_tagged, dim=grid_threads(geo), device=dev, inputs=[step, g.mmv, g.v, 1, g.blocks, tag])
        if s < n - 1:
            bin_particles(1, (s + 1) * dt)
        else:
            wp.launch(K.g2p, dim=count, device=dev, block_dim=PARTICLE_BLOCK,
                      inputs=[ptcl, sv, step, g.v, sv, ctx.stats])



# p2g_chunks inside one warp, from shared memory, for the one-launch G2P + P2G
# (g2p2g_rows): each lane stashes its particle's payload and stencil cell, as the linear
# index that tells cells apart and as the node indices that the adds address (given, not
# split from the index: an integer division costs about twenty instructions), then 27
# lanes, three groups of nine, each sum one row of three stencil nodes over a third of the
# warp's particles (10, 11, 11), adding at each change of cell. A lane
# a node over all 32 particles (no divergent adds) measured slower: a node's share alone
# costs more arithmetic than in a row of three (docs/simulator.md, tried).
# The payload never goes through global memory and the P2G needs no launch of its own.
# Every lane of a warp must call it (the launch covers whole warps, rows_threads); blocks
# are ROWS_BLOCK threads (the shared arrays' size). The CPU runs one thread at a time and
# scatters its particle.
_WARP_ROW_SUMS = """
    // the stencil's base node, and the cell's linear index that tells cells apart (-1: adds nothing)
    const int ci = base[0], cj = base[1], ck = base[2];
    const int cell = ci >= 0 ? (ci * nodes[1] + cj) * nodes[2] + ck : -1;
#if defined(__CUDA_ARCH__)
    __shared__ float4 pay[PBLOCK][4];
    __shared__ int4 cells[PBLOCK];
    const int t = (int)threadIdx.x;
    const int lane = t & 31;
    const int w0 = t - lane;
    pay[t][0] = make_float4(r0[0], r0[1], r0[2], r0[3]);
    pay[t][1] = make_float4(r1[0], r1[1], r1[2], r1[3]);
    pay[t][2] = make_float4(r2[0], r2[1], r2[2], r2[3]);
    pay[t][3] = make_float4(mv[0], mv[1], mv[2], mv[3]);
    cells[t] = make_int4(cell, ci, cj, ck);
    __syncwarp();
    if (lane < 27) {
        const int g = lane / 9;
        const int o = lane - 9 * g;
        const int a = o / 3;
        const int b = o - 3 * a;
        const int q1 = w0 + ((g + 1) * 32) / 3;
        const long long sk = out.strides[2];
        // the B-spline weight of offset a (b) at fx as k (fx - r)^2 + e: lane constants, no select per particle
        const float ka = a == 1 ? -1.f : 0.5f, ra = a == 0 ? 1.5f : (a == 1 ? 1.f : 0.5f), ea = a == 1 ? 0.75f : 0.f;
        const float kb = b == 1 ? -1.f : 0.5f, rb = b == 0 ? 1.5f : (b == 1 ? 1.f : 0.5f), eb = b == 1 ? 0.75f : 0.f;
        const float oa = (float)a * dx, ob = (float)b * dx;
        int4 cur = make_int4(-1, 0, 0, 0);
        float s[3][4] = {{0.f, 0.f, 0.f, 0.f}, {0.f, 0.f, 0.f, 0.f}, {0.f, 0.f, 0.f, 0.f}};
        for (int q = w0 + (g * 32) / 3; q <= q1; ++q) {
            const int4 c4 = q < q1 ? cells[q] : make_int4(-2, 0, 0, 0);
            const int c = c4.x;
            if (c != cur.x) {
                if (cur.x >= 0) {
                    const int i = cur.y + a, j = cur.z + b, k = cur.w;
                    char* row = reinterpret_cast<char*>(wp::address(out, i, j, k));
                    for (int z = 0; z < 3; ++z) {
                        wp::vec4* p = reinterpret_cast<wp::vec4*>(row + z * sk);
                        RED_V4
                    }
                    if (tag != 0) {
                        // read before written: plain stores of one tag from many SMs to the
                        // same word cost 10% of the substep
                        const int bi = i / BLOCKW, bj = j / BLOCKW;
                        const int k0 = k / BLOCKW, k1 = (k + 2) / BLOCKW;
                        int* t0 = wp::address(blocks, bi, bj, k0);
                        if (*t0 != tag) *t0 = tag;
                        if (k1 != k0) { int* t1 = wp::address(blocks, bi, bj, k1); if (*t1 != tag) *t1 = tag; }
                    }
                }
            }
            // a new cell restarts the sums by this factor: zeroing them in the branch above made
            // the compiler copy all twelve at every step. A non-finite sum (a particle that blew
            // up, which the guard counts) carries into the group's next cell too.
            const float keep = c != cur.x ? 0.f : 1.f;
            cur = c4;
            if (c >= 0) {
                const float4 p0 = pay[q][0], p1 = pay[q][1], p2 = pay[q][2], pm = pay[q][3];
                const float fx = p0.w, fy = p1.w, fz = p2.w;
                // quadratic B-spline weights of offsets a, b (bspline_at) and 0..2 along z
                const float fa = fx - ra, fb = fy - rb;
                const float wab = (ka * fa * fa + ea) * (kb * fb * fb + eb);
                const float w[3] = {wab * 0.5f * (1.5f - fz) * (1.5f - fz), wab * (0.75f - (fz - 1.f) * (fz - 1.f)),
                                    wab * 0.5f * (fz - 0.5f) * (fz - 0.5f)};
                // momentum + A (off - fx) dx at z offset 0, and A's step per z offset (row_shares)
                const float dx0 = oa - fx * dx, dy0 = ob - fy * dx, dz0 = -fz * dx;
                const float qx = pm.x + p0.x * dx0 + p0.y * dy0 + p0.z * dz0;
                const float qy = pm.y + p1.x * dx0 + p1.y * dy0 + p1.z * dz0;
                const float qz = pm.z + p2.x * dx0 + p2.y * dy0 + p2.z * dz0;
                const float ex = p0.z * dx, ey = p1.z * dx, ez = p2.z * dx;
                for (int z = 0; z < 3; ++z) {
                    s[z][0] = s[z][0] * keep + w[z] * (qx + (float)z * ex);
                    s[z][1] = s[z][1] * keep + w[z] * (qy + (float)z * ey);
                    s[z][2] = s[z][2] * keep + w[z] * (qz + (float)z * ez);
                    s[z][3] = s[z][3] * keep + w[z] * pm.w;
                }
            }
        }
    }
#else
    if (cell >= 0) {
        const float f[3] = {r0[3], r1[3], r2[3]};
        float wt[3][3];
        for (int d = 0; d < 3; ++d) {
            wt[d][0] = 0.5f * (1.5f - f[d]) * (1.5f - f[d]);
            wt[d][1] = 0.75f - (f[d] - 1.f) * (f[d] - 1.f);
            wt[d][2] = 0.5f * (f[d] - 0.5f) * (f[d] - 0.5f);
        }
        for (int a = 0; a < 3; ++a) for (int b = 0; b < 3; ++b) {
            for (int z = 0; z < 3; ++z) {
                const float w = wt[0][a] * wt[1][b] * wt[2][z];
                const float d0 = ((float)a - f[0]) * dx, d1 = ((float)b - f[1]) * dx, d2 = ((float)z - f[2]) * dx;
                wp::vec4 v(w * (mv[0] + r0[0] * d0 + r0[1] * d1 + r0[2] * d2),
                           w * (mv[1] + r1[0] * d0 + r1[1] * d1 + r1[2] * d2),
                           w * (mv[2] + r2[0] * d0 + r2[1] * d1 + r2[2] * d2), w * mv[3]);
                wp::atomic_add(wp::address(out, ci + a, cj + b, ck + z), v);
            }
            if (tag != 0) {
                const int bi = (ci + a) / BLOCKW, bj = (cj + b) / BLOCKW;
                *wp::address(blocks, bi, bj, ck / BLOCKW) = tag;
                *wp::address(blocks, bi, bj, (ck + 2) / BLOCKW) = tag;
            }
        }
    }
#endif
""".replace("PBLOCK", str(ROWS_BLOCK)).replace("BLOCKW", str(BLOCK)).replace(
    "RED_V4", _red_v4("p", "s[z][0]", "s[z][1]", "s[z][2]", "s[z][3]"))


@wp.func_native(_WARP_ROW_SUMS)
def warp_row_sums(base: wp.vec3i, r0: wp.vec4, r1: wp.vec4, r2: wp.vec4, mv: wp.vec4, dx: float, nodes: wp.vec3i,
                  out: wp.array3d(dtype=wp.vec4), blocks: wp.array3d(dtype=int), tag: int):
    """Add the P2G shares of the warp's particles to `out` and tag their activity blocks
    (unless tag is 0); each lane gives its particle's stencil base node (NO_CELL: adds
    nothing) and payload (store_payload's four vec4s). Untaped kernels only."""
    ...


@wp.kernel(enable_backward=False)
def g2p2g_rows(
    do_g2p: int,
    keep_vc: int,
    count: int,
    ptcl: K.Particles,
    s_in: K.ParticleVars,
    state: K.ParticleVars,
    step: K.StepParams,
    forces: K.Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    out: wp.array3d(dtype=wp.vec4),
    blocks: wp.array3d(dtype=int),
    tag: int,
    stats: wp.array(dtype=float),
):
    """g2p_bin and the next substep's p2g_chunks in one launch: G2P of this substep from
    s_in into `state` (unless do_g2p is 0: a call's first P2G, from `state`), then the P2G
    of `state` at t_frame + t_offset_next (s) into `out`, tagging the activity blocks with
    `tag` (warp_row_sums). keep_vc as in g2p_bin. Launched over rows_threads(count)
    threads: lanes past the last particle add nothing but take part in their warp's sums."""
    # the body of g2p2g_lane, written out: called through it, this kernel compiles to 11
    # more PTX instructions
    t = wp.tid()
    live = t < count
    b, fx, mv, A = particle_values(do_g2p, keep_vc, live, wp.min(t, count - 1), ptcl, s_in, state, step, forces,
                                   t_offset_next, grid_v, stats)
    if not live:
        b = NO_CELL
    warp_row_sums(b, wp.vec4(A[0, 0], A[0, 1], A[0, 2], fx[0]), wp.vec4(A[1, 0], A[1, 1], A[1, 2], fx[1]),
                  wp.vec4(A[2, 0], A[2, 1], A[2, 2], fx[2]), mv, step.dx, step.nodes, out, blocks, tag)


@wp.kernel(enable_backward=False)
def g2p2g_rows_stored(
    do_g2p: int,
    count: int,
    ptcl: K.Particles,
    states: wp.array(dtype=wp.uint64),
    row: int,
    step: K.StepParams,
    forces: K.Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    out: wp.array3d(dtype=wp.vec4),
    blocks: wp.array3d(dtype=int),
    tag: int,
    stats: wp.array(dtype=float),
):
    """g2p2g_rows over a stored frame's states (K.stored_state), keeping v and C: G2P from
    state row - 1 into state `row` (unless do_g2p is 0), then the P2G of state `row`."""
    g2p2g_lane(wp.tid(), do_g2p, 1, count, ptcl, K.stored_state(states, wp.max(row - 1, 0), count),
               K.stored_state(states, row, count), step, forces, t_offset_next, grid_v, out, blocks, tag, stats)


@wp.func
def g2p2g_lane(
    t: int,
    do_g2p: int,
    keep_vc: int,
    count: int,
    ptcl: K.Particles,
    s_in: K.ParticleVars,
    state: K.ParticleVars,
    step: K.StepParams,
    forces: K.Forces,
    t_offset_next: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    out: wp.array3d(dtype=wp.vec4),
    blocks: wp.array3d(dtype=int),
    tag: int,
    stats: wp.array(dtype=float),
):
    """Lane t of g2p2g_rows (every lane of a warp calls it: the sums are the warp's)."""
    live = t < count
    b, fx, mv, A = particle_values(do_g2p, keep_vc, live, wp.min(t, count - 1), ptcl, s_in, state, step, forces,
                                   t_offset_next, grid_v, stats)
    if not live:
        b = NO_CELL
    warp_row_sums(b, wp.vec4(A[0, 0], A[0, 1], A[0, 2], fx[0]), wp.vec4(A[1, 0], A[1, 1], A[1, 2], fx[1]),
                  wp.vec4(A[2, 0], A[2, 1], A[2, 2], fx[2]), mv, step.dx, step.nodes, out, blocks, tag)


def rows_threads(n_particles: int) -> int:
    """Threads of a g2p2g_rows launch: the particles rounded up to whole warps."""
    return 32 * max(1, -(-n_particles // 32))


def launch_g2p2g_rows(ctx, do_g2p: int, keep_vc: int, s_in, state, step, t_offset: float, grid_v, out,
                      blocks, tag: int) -> None:
    """One g2p2g_rows launch (s_in, state: ParticleVars structs; t_offset in s)."""
    count = state.u.shape[0]
    wp.launch(g2p2g_rows, dim=rows_threads(count), device=ctx.device, block_dim=ROWS_BLOCK, inputs=[
        do_g2p, keep_vc, count, ctx.particles(), s_in, state, step, ctx.forces_struct(), float(t_offset), grid_v,
        out, blocks, tag, ctx.stats])


def launch_g2p2g_stored(ctx, do_g2p: int, states: wp.array, row: int, step, t_offset: float, grid_v, out, blocks,
                        tag: int) -> None:
    """One g2p2g_rows_stored launch (states: a K.state_table; t_offset in s)."""
    count = ctx.base.shape[0]
    wp.launch(g2p2g_rows_stored, dim=rows_threads(count), device=ctx.device, block_dim=ROWS_BLOCK, inputs=[
        do_g2p, count, ctx.particles(), states, row, step, ctx.forces_struct(), float(t_offset), grid_v, out, blocks,
        tag, ctx.stats])


def run_substeps_rows(ctx, n: int, dt: float, st, g) -> None:
    """n substeps in place without a tape, each G2P and the next P2G in one launch
    (g2p2g_rows): two launches per substep. Same arguments as solver.run_substeps_fused;
    the same result up to the order of float sums."""
    dev, geo = ctx.device, ctx.geo
    step, sv = ctx.step(dt), st.struct
    g.mmv.zero_()
    launch_g2p2g_rows(ctx, 0, 0, sv, sv, step, 0.0, g.v, g.mmv, g.blocks, block_tag(0, 0))
    for s in range(n):
        wp.launch(grid_update_tagged, dim=grid_threads(geo), device=dev,
                  inputs=[step, g.mmv, g.v, 1, g.blocks, block_tag(0, s)])
        if s < n - 1:
            launch_g2p2g_rows(ctx, 1, 0, sv, sv, step, (s + 1) * dt, g.v, g.mmv, g.blocks, block_tag(0, s + 1))
        else:
            wp.launch(K.g2p, dim=st.u.shape[0], device=dev, block_dim=PARTICLE_BLOCK,
                      inputs=[ctx.particles(), sv, step, g.v, sv, ctx.stats])
