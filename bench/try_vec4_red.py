"""Experiment (CUDA): do 128-bit vector reductions (sm_90 `red.global.add.v4.f32`) into a
vec4 (momentum, mass) grid speed up the binned P2G's cell sums and the adjoint's cotangent
scatter, and does skipping empty nodes speed up the grid adjoint on stored (cold) grids?

    python bench/try_vec4_red.py --n 100000 --res 64 --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402
from pd_tool.sim import adjoint as A  # noqa: E402
from pd_tool.sim import gather as G  # noqa: E402
from pd_tool.sim import kernels as K  # noqa: E402
from sim_speed import make_block  # noqa: E402

RED4 = """
#if defined(__CUDA_ARCH__) && (__CUDA_ARCH__ >= 900)
    wp::vec4* p = wp::address(grid, i, j, k);
    asm volatile("{ .reg .u64 ga; cvta.to.global.u64 ga, %0; red.global.add.v4.f32 [ga], {%1, %2, %3, %4}; }"
                 :: "l"(p), "f"(val[0]), "f"(val[1]), "f"(val[2]), "f"(val[3]) : "memory");
#else
    wp::atomic_add(wp::address(grid, i, j, k), val);
#endif
"""


@wp.func_native(RED4)
def red_add4(grid: wp.array3d(dtype=wp.vec4), i: int, j: int, k: int, val: wp.vec4):
    ...


@wp.kernel(enable_backward=False)
def p2g_cells_v4_generic(lists: G.CellLists, dx: float, nodes: wp.vec3i, cells_per_pass: int,
                         grid: wp.array3d(dtype=wp.vec4)):
    lane_row = G.cell_lane_row(wp.tid())
    n = lists.n_occupied[0]
    slot = lane_row[0]
    while slot < n:
        nn, m, mv0, mv1, mv2 = G.cell_row_terms(lists.occupied[slot], lane_row[1], lane_row[2], lists, dx, nodes)
        wp.atomic_add(grid, nn[0], nn[1], nn[2], wp.vec4(mv0[0], mv0[1], mv0[2], m[0]))
        wp.atomic_add(grid, nn[0], nn[1], nn[2] + 1, wp.vec4(mv1[0], mv1[1], mv1[2], m[1]))
        wp.atomic_add(grid, nn[0], nn[1], nn[2] + 2, wp.vec4(mv2[0], mv2[1], mv2[2], m[2]))
        slot += cells_per_pass


@wp.kernel(enable_backward=False)
def p2g_cells_v4_red(lists: G.CellLists, dx: float, nodes: wp.vec3i, cells_per_pass: int,
                     grid: wp.array3d(dtype=wp.vec4)):
    lane_row = G.cell_lane_row(wp.tid())
    n = lists.n_occupied[0]
    slot = lane_row[0]
    while slot < n:
        nn, m, mv0, mv1, mv2 = G.cell_row_terms(lists.occupied[slot], lane_row[1], lane_row[2], lists, dx, nodes)
        red_add4(grid, nn[0], nn[1], nn[2], wp.vec4(mv0[0], mv0[1], mv0[2], m[0]))
        red_add4(grid, nn[0], nn[1], nn[2] + 1, wp.vec4(mv1[0], mv1[1], mv1[2], m[1]))
        red_add4(grid, nn[0], nn[1], nn[2] + 2, wp.vec4(mv2[0], mv2[1], mv2[2], m[2]))
        slot += cells_per_pass


@wp.kernel(enable_backward=False)
def scatter_cells_v4_red(lists: G.CellLists, dx: float, nodes: wp.vec3i, cells_per_pass: int,
                         out: wp.array3d(dtype=wp.vec4)):
    lane_row = G.cell_lane_row(wp.tid())
    n = lists.n_occupied[0]
    slot = lane_row[0]
    while slot < n:
        nn, _m, s0, s1, s2 = G.cell_row_terms(lists.occupied[slot], lane_row[1], lane_row[2], lists, dx, nodes)
        red_add4(out, nn[0], nn[1], nn[2], wp.vec4(s0[0], s0[1], s0[2], 0.0))
        red_add4(out, nn[0], nn[1], nn[2] + 1, wp.vec4(s1[0], s1[1], s1[2], 0.0))
        red_add4(out, nn[0], nn[1], nn[2] + 2, wp.vec4(s2[0], s2[1], s2[2], 0.0))
        slot += cells_per_pass


@wp.kernel(enable_backward=False)
def grid_adjoint_sparse(
    grid_m: wp.array3d(dtype=float), grid_mv: wp.array3d(dtype=wp.vec3), fixed: wp.array3d(dtype=int),
    dx: float, dt: float, gravity: wp.vec3, damping_factor: float, pad: int, nodes: wp.vec3i,
    use_ground: int, ground_z: float, adj_grid_v: wp.array3d(dtype=wp.vec3), adj_m: wp.array3d(dtype=float),
    adj_mv: wp.array3d(dtype=wp.vec3), binned: int, lists: G.CellLists,
):
    i, j, k = wp.tid()
    if binned != 0:
        lists.counts[(i * nodes[1] + j) * nodes[2] + k] = 0
        if i == 0 and j == 0 and k == 0:
            lists.n_occupied[0] = 0
    m = grid_m[i, j, k]
    if m == 0.0:
        adj_m[i, j, k] = 0.0
        adj_mv[i, j, k] = wp.vec3(0.0)
        return
    g = adj_grid_v[i, j, k]
    adj_grid_v[i, j, k] = wp.vec3(0.0)
    mv = grid_mv[i, j, k]
    grid_m[i, j, k] = 0.0
    grid_mv[i, j, k] = wp.vec3(0.0)
    gm = float(0.0)
    gmv = wp.vec3(0.0)
    if m > K.MIN_NODE_MASS and fixed[i, j, k] == 0:
        vel = (mv / m + dt * gravity) * damping_factor
        if (i < pad and vel[0] < 0.0) or (i >= nodes[0] - pad and vel[0] > 0.0):
            g = wp.vec3(0.0, g[1], g[2])
        if (j < pad and vel[1] < 0.0) or (j >= nodes[1] - pad and vel[1] > 0.0):
            g = wp.vec3(g[0], 0.0, g[2])
        if (k < pad and vel[2] < 0.0) or (k >= nodes[2] - pad and vel[2] > 0.0):
            g = wp.vec3(g[0], g[1], 0.0)
        if use_ground != 0:
            if float(k) * dx <= ground_z and vel[2] < 0.0:
                g = wp.vec3(g[0], g[1], 0.0)
        gq = g * damping_factor
        gmv = gq / m
        gm = -wp.dot(gq, mv) / (m * m)
    adj_m[i, j, k] = gm
    adj_mv[i, j, k] = gmv


def timed(fn, reps: int, device) -> float:
    """us per call of fn, replayed from a CUDA graph of `reps` calls (3 replays, best)."""
    with wp.ScopedCapture(device=device) as cap:
        for _ in range(reps):
            fn()
    best = 1e9
    for _ in range(3):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        wp.capture_launch(cap.graph)
        wp.synchronize_device(device)
        best = min(best, (time.perf_counter() - t0) / reps * 1e6)
    return best


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--grids", type=int, default=64, help="stored grids cycled by the grid adjoint")
    ap.add_argument("--json")
    a = ap.parse_args()
    dev = wp.get_device("cuda:0")
    x, vol, mass, E, static = make_block(a.n, a.res)
    sim = MPMSolver(x, vol, mass, E, static, SimConfig(grid_res=a.res, substeps=16), device=dev, cuda_graph=False)
    sim.set_velocity(np.random.default_rng(0).normal(0, 0.1, (a.n, 3)) * (~static[:, None]))
    sim.step_frame(1e-3)
    ctx, st, g, lists = sim._context(), sim.state, sim.grid, sim._bins
    geo, cfg, mat, fa = ctx.geo, ctx.cfg, ctx.mat, ctx.forces
    nodes = geo.nodes_vec
    dt = 1e-3 / 16

    # fill the cell lists as the first binning of a run does
    g.m.zero_(); g.mv.zero_(); lists.counts.zero_(); lists.n_occupied.zero_()  # noqa: E702
    wp.launch(G.g2p_bin, dim=a.n, device=dev, block_dim=G.PARTICLE_BLOCK, inputs=[
        0, ctx.base, st.u, st.F, st.u, st.v, st.C, st.F, mat.E, mat.volume, mat.mass, mat.static, g.v,
        float(cfg.nu), float(geo.dx), float(dt), nodes, float(cfg.min_det_f), geo.edge_lo, geo.edge_hi,
        ctx.t_frame, 0.0, fa.n, fa.mask, fa.accel, fa.window, lists, g.m, g.mv, ctx.stats])
    per_pass = min(G.CELLS_PER_PASS, lists.occupied.shape[0])
    dim = 9 * per_pass
    g4 = wp.zeros(geo.nodes, dtype=wp.vec4, device=dev)
    out = {"n": a.n, "res": a.res, "occupied": int(lists.n_occupied.numpy()[0]),
           "gpu": wp.get_device(dev).name}

    # correctness: one launch each from zero
    g.m.zero_(); g.mv.zero_()  # noqa: E702
    wp.launch(G.p2g_cells, dim=dim, device=dev, block_dim=G.CELL_BLOCK, inputs=[lists, float(geo.dx), nodes, per_pass, g.m, g.mv])
    ref = np.concatenate([g.mv.numpy(), g.m.numpy()[..., None]], axis=-1)
    for name, kern in (("generic", p2g_cells_v4_generic), ("red", p2g_cells_v4_red)):
        g4.zero_()
        wp.launch(kern, dim=dim, device=dev, block_dim=G.CELL_BLOCK, inputs=[lists, float(geo.dx), nodes, per_pass, g4])
        out[f"p2g_max_abs_diff_{name}"] = float(np.max(np.abs(g4.numpy() - ref)))
    out["p2g_max_abs"] = float(np.max(np.abs(ref)))

    L = lambda kern, args: (lambda: wp.launch(kern, dim=dim, device=dev, block_dim=G.CELL_BLOCK, inputs=args))  # noqa: E731
    out["cell_sums_us"] = {
        "current (float + vec3 atomics)": timed(L(G.p2g_cells, [lists, float(geo.dx), nodes, per_pass, g.m, g.mv]), 50, dev),
        "vec4 grid, warp atomic_add": timed(L(p2g_cells_v4_generic, [lists, float(geo.dx), nodes, per_pass, g4]), 50, dev),
        "vec4 grid, red.v4": timed(L(p2g_cells_v4_red, [lists, float(geo.dx), nodes, per_pass, g4]), 50, dev),
    }
    adj3 = wp.zeros(geo.nodes, dtype=wp.vec3, device=dev)
    out["adjoint_scatter_us"] = {
        "current (vec3 atomics)": timed(L(A.scatter_cells, [lists, float(geo.dx), nodes, per_pass, adj3]), 50, dev),
        "vec4 padded, red.v4": timed(L(scatter_cells_v4_red, [lists, float(geo.dx), nodes, per_pass, g4]), 50, dev),
    }

    # grid adjoint over `grids` stored grids (cold in L2), newest first, as the backward reads them
    g.m.zero_(); g.mv.zero_()  # noqa: E702
    wp.launch(G.p2g_cells, dim=dim, device=dev, block_dim=G.CELL_BLOCK, inputs=[lists, float(geo.dx), nodes, per_pass, g.m, g.mv])
    m_np, mv_np = g.m.numpy(), g.mv.numpy()
    stored = [(wp.array(m_np, dtype=float, device=dev), wp.array(mv_np, dtype=wp.vec3, device=dev)) for _ in range(a.grids)]
    out["active_node_fraction"] = float(np.mean(m_np > 0))
    adj_m = wp.zeros(geo.nodes, dtype=float, device=dev)
    adj_mv = wp.zeros(geo.nodes, dtype=wp.vec3, device=dev)
    bc = A._grid_bc_args(ctx, dt)
    res = {}
    for name, kern in (("current", A.grid_adjoint), ("skip empty nodes", grid_adjoint_sparse)):
        def run_all(kern=kern):
            for sm, smv in reversed(stored):
                wp.launch(kern, dim=geo.nodes, device=dev, inputs=[sm, smv] + bc + [adj3, adj_m, adj_mv, 1, lists])
        # the kernels zero the stored grids: refill before each timing
        def refill():
            for sm, smv in stored:
                sm.assign(m_np); smv.assign(mv_np)  # noqa: E702
        refill()
        wp.synchronize_device(dev)
        with wp.ScopedCapture(device=dev) as cap:
            run_all()
        best = 1e9
        for _ in range(3):
            refill()
            wp.synchronize_device(dev)
            t0 = time.perf_counter()
            wp.capture_launch(cap.graph)
            wp.synchronize_device(dev)
            best = min(best, (time.perf_counter() - t0) / a.grids * 1e6)
        res[name] = best
        # the same grids hot in L2 (the stored grid written just before)
        refill()
        one = stored[0]
        def hot(kern=kern, one=one):
            wp.launch(kern, dim=geo.nodes, device=dev, inputs=[one[0], one[1]] + bc + [adj3, adj_m, adj_mv, 1, lists])
        res[name + " (same grid every call)"] = timed(hot, 50, dev)
    # check: both variants give the same adjoint on one grid
    outs = []
    for kern in (A.grid_adjoint, grid_adjoint_sparse):
        sm = wp.array(m_np, dtype=float, device=dev); smv = wp.array(mv_np, dtype=wp.vec3, device=dev)  # noqa: E702
        gv = wp.array(np.random.default_rng(1).normal(size=mv_np.shape).astype(np.float32) * (m_np[..., None] > 0),
                      dtype=wp.vec3, device=dev)
        wp.launch(kern, dim=geo.nodes, device=dev, inputs=[sm, smv] + bc + [gv, adj_m, adj_mv, 1, lists])
        outs.append((adj_m.numpy().copy(), adj_mv.numpy().copy(), gv.numpy().copy(), sm.numpy().copy()))
    out["grid_adjoint_us"] = res
    out["grid_adjoint_same"] = all(np.array_equal(u, v) for u, v in zip(outs[0], outs[1]))
    print(json.dumps(out, indent=1))
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
