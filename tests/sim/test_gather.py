"""The atomic-free gather P2G (pd_tool/sim/gather.py) against the scatter P2G it replaces.

Both are the same sums in a different order, so every particle output must agree to float32
rounding: with forces, a static layer, ground, damping, gravity, with cells so crowded
that their particles span many chunks, and with particles out of cell order (a change of
cell at every particle).
"""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from pd_tool.sim import MPMSolver, SimConfig
from pd_tool.sim import kernels as K
from pd_tool.sim.gather import CHUNK, red_add_vec4


def block(n: int, side: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    x = (0.5 + (rng.random((n, 3)) - 0.5) * side).astype(np.float32)
    vol = np.full(n, side**3 / n)
    static = x[:, 2] < 0.5 - 0.42 * side
    return x, vol, vol * 1000.0, np.full(n, 2e5), static


def run(x, vol, mass, E, static, cfg, device, gather, frames=3, sort=True, warp_sums=True):
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, gather_p2g=gather, sort_particles=sort,
                    warp_sums=warp_sums)
    v = np.zeros_like(x)
    v[:, 0] = np.sin(40.0 * x[:, 2])
    v[:, 1] = 0.3 * np.cos(30.0 * x[:, 0])
    sim.set_velocity(v)
    sim.add_force(x[:, 2] > 0.52, (0.0, 5.0, 1.0), 0.0, 1.5e-3)
    for _ in range(frames):
        sim.step_frame(1e-3)
    return sim.displacements(), sim.velocities(), sim.deformation_gradients()


@pytest.mark.parametrize("warp_sums", [True, False], ids=["warp_sums", "chunks"])
@pytest.mark.parametrize("side,label", [(0.3, "normal"), (0.06, "crowded"), (0.3, "unsorted")])
def test_gather_matches_scatter(device: str, side: float, label: str, warp_sums: bool) -> None:
    """3,000 particles: the last warp of the one-launch G2P + P2G is part empty."""
    x, vol, mass, E, static = block(3000, side)
    cfg = SimConfig(grid_res=32, substeps=8, damping=2.0, ground_z=0.3)
    if label == "crowded":
        # The block spans ~2 cells: far more particles per cell than a chunk holds.
        cells = np.floor(x / (1.0 / 32) - 0.5).astype(int)
        _, per_cell = np.unique(cells, axis=0, return_counts=True)
        assert per_cell.max() > 4 * CHUNK
    sort = label != "unsorted"  # random order: the cell changes at nearly every particle
    ref = run(x, vol, mass, E, static, cfg, device, gather=False, sort=sort)
    got = run(x, vol, mass, E, static, cfg, device, gather=True, sort=sort, warp_sums=warp_sums)
    for name, a, b in zip(("u", "v", "F"), ref, got):
        assert np.all(np.isfinite(b)), name
        scale = max(float(np.abs(a).max()), 1e-3)
        assert np.abs(a - b).max() <= 2e-5 * scale + 1e-7, (name, float(np.abs(a - b).max()), scale)
    # the motion is real: a broken gather that dropped momentum would not move like this
    assert float(np.abs(ref[1]).max()) > 0.1


def test_gather_is_reusable_across_frames_and_configs(device: str) -> None:
    """Activity tags left by one frame (odd or even substep counts) never leak into the next."""
    x, vol, mass, E, static = block(2000, 0.3, seed=3)
    outs = []
    for substeps in (7, 8):
        cfg = SimConfig(grid_res=24, substeps=substeps)
        outs.append([run(x, vol, mass, E, static, cfg, device, gather=g, frames=4)[0] for g in (False, True)])
    for ref, got in outs:
        assert np.abs(ref - got).max() <= 2e-5 * np.abs(ref).max() + 1e-7


@wp.kernel
def _add_many(idx: wp.array(dtype=wp.vec3i), vals: wp.array(dtype=wp.vec4), out: wp.array3d(dtype=wp.vec4)):
    t = wp.tid()
    red_add_vec4(out, idx[t][0], idx[t][1], idx[t][2], vals[t])


def test_red_add_vec4_sums_every_contribution(device: str) -> None:
    """The 128-bit reduction (inline PTX on sm_90+, per component elsewhere) loses no
    contribution when many threads hit the same few nodes, in every component."""
    rng = np.random.default_rng(3)
    n = 20000
    idx = rng.integers(0, 3, (n, 3)).astype(np.int32)
    vals = rng.normal(size=(n, 4)).astype(np.float32)
    out = wp.zeros((3, 3, 3), dtype=wp.vec4, device=device)
    wp.launch(_add_many, dim=n, device=device, inputs=[
        wp.array(idx, dtype=wp.vec3i, device=device), wp.array(vals, dtype=wp.vec4, device=device), out])
    ref = np.zeros((3, 3, 3, 4))
    np.add.at(ref, (idx[:, 0], idx[:, 1], idx[:, 2]), vals.astype(np.float64))
    np.testing.assert_allclose(out.numpy(), ref, atol=2e-3)


def test_gather_follows_a_block_across_activity_blocks(device: str) -> None:
    """A block flying through the grid leaves activity blocks behind and enters new ones
    every few substeps: nodes it left keep old velocities, which no particle may read, and
    nodes it enters must be updated and cleared."""
    from pd_tool.sim import gather

    x, vol, mass, E, static = block(1500, 0.12, seed=7)
    x[:, 0] -= 0.25
    static[:] = False
    cfg = SimConfig(grid_res=24, substeps=6)
    outs = []
    for g in (False, True):
        sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, gather_p2g=g)
        v = np.zeros_like(x)
        v[:, 0] = 25.0
        v[:, 2] = 4.0 * np.sin(30.0 * x[:, 1])
        sim.set_velocity(v)
        for _ in range(8):
            sim.step_frame(2e-3)
        outs.append((sim.displacements(), sim.velocities(), sim.deformation_gradients()))
    # the block crossed several activity blocks
    cell = 1.0 / 24
    assert float(np.median(outs[0][0][:, 0])) > 2 * gather.BLOCK * cell
    for a, b in zip(*outs):
        assert np.all(np.isfinite(b))
        assert np.abs(a - b).max() <= 2e-5 * max(float(np.abs(a).max()), 1e-3) + 1e-7


@wp.kernel
def _nodes_of(t: wp.array(dtype=int), nodes: wp.vec3i, inv_nodes: wp.vec3, out: wp.array(dtype=wp.vec3i)):
    p = wp.tid()
    out[p] = K.node_of(t[p], nodes, inv_nodes)


@pytest.mark.parametrize("nodes", [(5, 7, 3), (65, 65, 65), (129, 97, 1), (3, 2047, 2049), (2047, 2047, 3),
                                   (1, 1, 4_000_000)])
def test_node_of_unravels_every_index_the_grid_kernels_launch(nodes: tuple[int, int, int]) -> None:
    """kernels.node_of (the grid kernels' 1-D launch) against numpy's unravel_index: every
    index of small grids; on large ones the first and last indices, both sides of every
    multiple of nodes[2] and nodes[1] nodes[2] sampled, and random ones, up to the widest
    x-y layer GridGeometry allows."""
    nx, ny, nz = nodes
    total = nx * ny * nz
    rng = np.random.default_rng(1)
    if total <= 300_000:
        t = np.arange(total)
    else:
        rows = rng.integers(0, nx * ny, 4000) + 1
        layers = (rng.integers(0, nx, 1000) + 1) * ny
        t = np.concatenate([[0, 1, total - 2, total - 1], rows * nz - 1, rows * nz, layers * nz - 1, layers * nz,
                            rng.integers(0, total, 20_000)])
    t = np.unique(np.clip(t, 0, total - 1)).astype(np.int32)
    inv = wp.vec3(*(K.reciprocal_f32(n) for n in nodes))
    out = wp.zeros(len(t), dtype=wp.vec3i)
    wp.launch(_nodes_of, dim=len(t), inputs=[wp.array(t, dtype=int), wp.vec3i(*nodes), inv, out])
    np.testing.assert_array_equal(out.numpy(), np.stack(np.unravel_index(t, nodes), axis=1))


def test_a_grid_wider_than_the_node_index_allows_is_refused() -> None:
    from pd_tool.sim import SimConfigError
    from pd_tool.sim.solver import GridGeometry

    with pytest.raises(SimConfigError, match="coarser grid"):
        GridGeometry.from_config(SimConfig(grid_res=2048, domain=(1.0, 1.0, 0.01)))
    assert GridGeometry.from_config(SimConfig(grid_res=2040, domain=(1.0, 1.0, 0.01))).nodes[:2] == (2041, 2041)


def test_stored_state_kernels_match_the_bound_state_kernels(device: str) -> None:
    """g2p2g_rows_stored and g2p_stored, which reach their states through a table of
    addresses (K.stored_state), give bit for bit what g2p2g_rows and g2p give on the same
    states bound at launch on the CPU (on CUDA to rounding: the grid's sums come in a
    varying order).
    The rows are of a frame's substep arrays (_Substeps), from a moving, deformed state."""
    from pd_tool.sim.autograd import _Substeps
    from pd_tool.sim.gather import block_shape, block_tag, launch_g2p2g_rows, launch_g2p2g_stored

    x, vol, mass, E, static = block(3000, 0.3)
    cfg = SimConfig(grid_res=32, substeps=8, damping=2.0, ground_z=0.3)
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device, gather_p2g=True, warp_sums=True)
    v = np.zeros_like(x)
    v[:, 0] = np.sin(40.0 * x[:, 2])
    sim.set_velocity(v)
    sim.add_force(x[:, 2] > 0.52, (0.0, 5.0, 1.0), 0.0, 1.5e-3)
    for _ in range(2):
        sim.step_frame(1e-3)
    ctx, step, n = sim._context(), sim._context().step(1e-4), sim.n
    grid_v = sim.grid.v
    results = []
    for stored in (False, True):
        pool = _Substeps(n, sim.geo, 2, device)
        for dst, src in zip(pool.fields[:4], (sim.state.u, sim.state.v, sim.state.C, sim.state.G)):
            wp.copy(dst[0], src)
        out = wp.zeros(sim.geo.nodes, dtype=wp.vec4, device=device)
        blocks = wp.zeros(block_shape(sim.geo.nodes), dtype=int, device=device)
        if stored:
            launch_g2p2g_stored(ctx, 1, pool.table, 1, step, 2e-4, grid_v, out, blocks, block_tag(0, 1))
            wp.launch(K.g2p_stored, dim=n, device=device, inputs=[ctx.particles(), pool.table, 1, step, grid_v,
                                                                    ctx.stats])
        else:
            st = pool.states
            launch_g2p2g_rows(ctx, 1, 1, st[0].struct, st[1].struct, step, 2e-4, grid_v, out, blocks, block_tag(0, 1))
            wp.launch(K.g2p, dim=n, device=device, inputs=[ctx.particles(), st[1].struct, step, grid_v,
                                                           st[2].struct, ctx.stats])
        results.append([f.numpy()[1:3].copy() for f in pool.fields[:4]] + [out.numpy(), blocks.numpy()])
    for name, a, b in zip(("u", "v", "C", "G", "grid", "tags"), *results):
        if device == "cpu" or name == "tags":
            assert np.array_equal(a, b), name
        else:  # CUDA: the grid's atomics from many SMs sum in a varying order
            assert np.abs(a - b).max() <= 1e-6 * np.abs(a).max(), name
    moved = results[0][0][1] - sim.state.u.numpy()
    assert float(np.abs(moved).max()) > 0.0 and float(np.abs(results[0][4]).max()) > 0.0
