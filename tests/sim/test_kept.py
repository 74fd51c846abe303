"""Frames stored by the differentiable forward (SimConfig.keep_budget_mb): the backward over
them must give exactly what the recompute gives, within the budget, whatever happens to the
autograd graph between forward and backward."""
from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

from pd_tool.io.synthetic import make_block
from pd_tool.sim import DiffSim, Force, SimConfig, SimConfigError, initial_state, simulate_frames

FRAME_DT = 1 / 60


def block(seed: int = 0):
    """bench/sim_speed.py's block: 1,728 particles at random in random order on a 16-cell
    grid, its lowest layer static, E scattered over 2e4-6e4 Pa, one side pushed."""
    x, vol, _, _, static = make_block(1728, 16, seed=seed)
    rng = np.random.default_rng(seed)
    E = torch.tensor(rng.uniform(2e4, 6e4, len(x)), dtype=torch.float32)
    push = Force(mask=x[:, 0] > 0.5, accel=(4.0, 1.0, 2.0), t_start=0.0, t_end=0.02)
    return x, static, vol, E, push


def run(sim: DiffSim, x, E0, push, substeps, frames: int = 3, horizon=None, backward: bool = True):
    """Forward `frames` frames (substeps: an int or one per frame) and the gradients of a
    loss on every frame's positions and velocities: (last state, dE, dv0)."""
    E = E0.clone().requires_grad_()
    v0 = torch.zeros(len(x), 3)
    v0[:, 0] = 0.2
    v0.requires_grad_()
    state = initial_state(torch.tensor(x, dtype=torch.float32), v0)
    per = [substeps] * frames if isinstance(substeps, int) else list(substeps)
    out = []
    for f, n in enumerate(per):
        if horizon is not None and f > 0 and f % horizon == 0:
            state = tuple(t.detach() for t in state)
        state = sim.frame(state, E, FRAME_DT, n, [push], f * FRAME_DT, frame_index=f)
        out.append(state)
    if not backward:
        return out
    loss = sum((s[0] ** 2).sum() + 0.1 * (s[1] ** 2).sum() for s in out)
    dE, dv = torch.autograd.grad(loss, [E, v0], allow_unused=True)
    dv = torch.zeros_like(v0) if dv is None else dv
    return [t.detach() for t in out[-1]], dE, dv


def sim_for(static, vol, budget, binned: bool = False, pooled: bool = False) -> DiffSim:
    sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=16, gravity=(0, 0, -9.81), keep_budget_mb=budget))
    sim.binned = binned
    sim.store_in_pool = pooled  # as on CUDA: run in the pool, copied to the slot
    return sim


def assert_same(a, b) -> None:
    for name, p, q in zip(("end x", "end v", "end C", "end F"), a[0], b[0]):
        assert torch.equal(p, q), name
    assert torch.equal(a[1], b[1]), "dE"
    assert torch.equal(a[2], b[2]), "dv0"


@pytest.mark.parametrize("pooled", [False, True])
@pytest.mark.parametrize("binned", [False, True])
@pytest.mark.parametrize("horizon", [None, 2])
def test_stored_frames_give_the_recompute_s_gradients(binned, horizon, pooled):
    """Every frame stored, against none: the same end state and gradients bit for bit (on
    the CPU the forward and the recompute run the same kernels in the same order), stored
    on the slots' own arrays or run in the pool and copied."""
    x, static, vol, E, push = block()
    ref = run(sim_for(static, vol, 0, binned), x, E, push, 12, horizon=horizon)
    sim = sim_for(static, vol, None, binned, pooled)
    got = run(sim, x, E, push, 12, horizon=horizon)
    assert len(sim._kept) == 3 and all(k.free() for k in sim._kept)
    assert ref[1].abs().max() > 0 and (horizon is not None or ref[2].abs().max() > 0)
    assert_same(got, ref)


def test_the_budget_bounds_the_stored_frames():
    """A budget of two frames' substeps stores two of four frames; the others recompute,
    and the gradients are the same."""
    x, static, vol, E, push = block(1)
    ref = run(sim_for(static, vol, 0), x, E, push, 12, frames=4)
    probe = sim_for(static, vol, 0)
    budget = 2 * 12 * probe._substep_bytes() / 2**20
    sim = sim_for(static, vol, budget * 27 / 24 * 1.01)  # 15 + 12 substeps
    got = run(sim, x, E, push, 12, frames=4)
    assert [k.count for k in sim._kept] == [15, 12]  # a quarter of headroom, then what is left
    assert_same(got, ref)


def test_a_slot_that_cannot_be_allocated_leaves_its_frame_to_the_recompute(monkeypatch):
    """Memory taken by another process after the budget was read: the frame whose slot
    fails to allocate, and every later one, recompute with the same gradients; the budget
    shrinks to the slots held, so no later frame tries again."""
    import pd_tool.sim.autograd as ag

    x, static, vol, E, push = block(5)
    ref = run(sim_for(static, vol, 0), x, E, push, 12, frames=4)
    made = []

    class Scarce(ag._KeptFrame):
        def __init__(self, *args, **kw):
            if len(made) == 2:
                raise RuntimeError("Failed to allocate 425256000 bytes on device 'cuda:0'")
            super().__init__(*args, **kw)
            made.append(self)

    monkeypatch.setattr(ag, "_KeptFrame", Scarce)
    sim = sim_for(static, vol, None)
    assert_same(run(sim, x, E, push, 12, frames=4), ref)
    assert sim._kept == made and len(made) == 2
    assert sim._keep_budget_bytes() == 2 * 15 * sim._substep_bytes()
    assert_same(run(sim, x, E, push, 12, frames=4), ref)  # the two slots again, no new attempt
    assert len(made) == 2


def test_slots_leave_the_gpu_memory_another_process_took(monkeypatch):
    """On a GPU shared with another fit: the budget leaves `reserve` free for everything
    else, and a slot is added only while that much stays free. A process taking two frames'
    worth after the first frame leaves this one two slots, its other frames recompute with
    the same gradients; once it lets go, the slots come back."""
    x, static, vol, E, push = block(6)
    ref = run(sim_for(static, vol, 0), x, E, push, 12, frames=4)
    per = sim_for(static, vol, 0)._substep_bytes()
    budget = 4 * 15 * per * 1.01
    sim = sim_for(static, vol, budget / 2**20)
    other = {"bytes": 0}
    held = lambda: sum(k.count * per for k in sim._kept)  # noqa: E731
    monkeypatch.setattr(sim, "_gpu_free_bytes", lambda: budget + 50 * per - held() - other["bytes"])
    run(sim, x, E, push, 12, frames=1)
    assert sim._keep_reserve == pytest.approx(50 * per) and [k.count for k in sim._kept] == [15]
    other["bytes"] = 2 * 15 * per
    assert_same(run(sim, x, E, push, 12, frames=4), ref)
    assert [k.count for k in sim._kept] == [15, 15]
    other["bytes"] = 0
    assert_same(run(sim, x, E, push, 12, frames=4), ref)
    assert [k.count for k in sim._kept] == [15, 15, 15, 15]


@pytest.mark.parametrize("pooled,binned", [(False, False), (True, False), (True, True)])
def test_a_forward_without_backward_frees_its_slots_and_leaves_them_usable(pooled, binned):
    """A graph dropped before its backward (a fit's measuring pass with gradients on) frees
    its slots, their grids (or the pool's) holding that forward's mass and momentum; the
    next forward must start from zero, or its P2G adds to what the last one left (binned,
    the pool is cleared only in the blocks its P2G tagged)."""
    x, static, vol, E, push = block(2)
    ref = run(sim_for(static, vol, 0, binned), x, E, push, 10)
    sim = sim_for(static, vol, None, binned, pooled)
    dropped = run(sim, x, E * 1.5, push, 10, backward=False)
    assert all(not k.free() for k in sim._kept)
    del dropped
    gc.collect()
    assert len(sim._kept) == 3 and all(k.free() for k in sim._kept)
    assert_same(run(sim, x, E, push, 10), ref)
    assert len(sim._kept) == 3


def test_no_slot_without_gradients_or_for_the_taped_backward():
    x, static, vol, E, push = block(3)
    sim = sim_for(static, vol, None)
    with torch.no_grad():
        run(sim, x, E, push, 8, backward=False)
    assert sim._kept == []
    state = initial_state(torch.tensor(x, dtype=torch.float32))
    sim.frame(state, E, FRAME_DT, 8, [push])  # nothing requires a gradient
    assert sim._kept == []
    taped = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=16, backward="tape"))
    run(taped, x, E, push, 8, frames=1)
    assert taped._kept == []


def test_a_longer_frame_grows_a_slot_and_a_second_backward_recomputes():
    x, static, vol, E, push = block(4)
    per = [8, 14, 8]
    ref = run(sim_for(static, vol, 0), x, E, push, per)
    sim = sim_for(static, vol, None)
    run(sim, x, E, push, [8, 8, 8])
    assert sorted(k.count for k in sim._kept) == [10, 10, 10]
    assert_same(run(sim, x, E, push, per), ref)
    assert sorted(k.count for k in sim._kept) == [10, 10, 18]
    # retain_graph: the second backward finds the slots released and recomputes
    Ei = E.clone().requires_grad_()
    out = simulate_frames(sim, initial_state(torch.tensor(x, dtype=torch.float32)), Ei, FRAME_DT, 10, 2,
                          forces=[push])
    loss = sum((s[0] ** 2).sum() for s in out)
    first = torch.autograd.grad(loss, Ei, retain_graph=True)[0]
    second = torch.autograd.grad(loss, Ei)[0]
    assert first.abs().max() > 0 and torch.equal(first, second)


def test_a_negative_budget_is_refused():
    with pytest.raises(SimConfigError, match="keep_budget_mb"):
        SimConfig(keep_budget_mb=-1).validate()


def test_stored_frames_on_cuda_with_graphs():
    """On CUDA, stored frames run the pool's captured graphs (a key's first run launches
    directly, the second captures, the third replays) after a dropped forward. Float sums
    land in another order each run there, so the two paths agree to rounding, not bit for
    bit."""
    import warp as wp

    if not torch.cuda.is_available() or not wp.is_cuda_available():
        pytest.skip("needs CUDA torch and warp")
    x, static, vol, E, push = block(5)
    results = []
    for budget in (0, None):
        sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=16, gravity=(0, 0, -9.81), keep_budget_mb=budget),
                      device="cuda:0")
        Ec = E.cuda()
        run_cuda(sim, x, Ec * 1.5, push, backward=False)
        gc.collect()
        run_cuda(sim, x, Ec, push)  # captures
        results.append(run_cuda(sim, x, Ec, push))  # replays
        assert len(sim._kept) == (0 if budget == 0 else 3)
    for a, b in zip(results[0], results[1]):
        assert torch.all(torch.isfinite(b))
        assert float((a - b).abs().max() / b.abs().max().clamp_min(1e-30)) < 1e-4


def run_cuda(sim, x, E0, push, backward: bool = True):
    E = E0.clone().requires_grad_()
    v0 = torch.zeros(len(x), 3, device="cuda:0")
    v0[:, 0] = 0.2
    v0.requires_grad_()
    state = initial_state(torch.tensor(x, dtype=torch.float32, device="cuda:0"), v0)
    out = []
    for f in range(3):
        state = sim.frame(state, E, FRAME_DT, 12, [push], f * FRAME_DT, frame_index=f)
        out.append(state)
    if not backward:
        return None
    loss = sum((s[0] ** 2).sum() + 0.1 * (s[1] ** 2).sum() for s in out)
    dE, dv = torch.autograd.grad(loss, [E, v0])
    return [out[-1][0].detach(), out[-1][1].detach(), dE, dv]


def test_packed_slots_keep_the_tagged_blocks_and_take_less_memory_on_a_thin_object():
    """Binned and run in the pool (as on CUDA), a slot keeps each substep's grid only in the
    blocks its P2G tagged: a plate one cell thick on a 32-cell grid gives the recompute's
    gradients bit for bit from a fraction of a dense slot's memory."""
    import pd_tool.sim.autograd as ag

    rng = np.random.default_rng(3)
    n = 1500
    x = np.column_stack([rng.uniform(0.2, 0.8, n), rng.uniform(0.2, 0.8, n), rng.uniform(0.5, 0.53, n)])
    static = x[:, 0] < 0.25
    vol = np.full(n, 1e-6)
    E = torch.tensor(rng.uniform(2e4, 6e4, n), dtype=torch.float32)
    push = Force(mask=x[:, 0] > 0.6, accel=(0.0, 0.0, 3.0), t_start=0.0, t_end=0.02)

    def sim_of(budget, pooled):
        sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=32, gravity=(0, 0, 0), keep_budget_mb=budget))
        sim.binned, sim.store_in_pool = True, pooled
        return sim

    ref = run(sim_of(0, False), x, E, push, 8)
    sim = sim_of(None, True)
    assert_same(run(sim, x, E, push, 8), ref)
    assert sim._kept and all(isinstance(k, ag._PackedFrame) and k.holds for k in sim._kept)
    dense = sim._kept[0].count * sim._substep_bytes()
    assert sim._kept[0].nbytes < 0.5 * dense
    # the blocks a substep tagged, measured, against the estimate from the rest positions
    assert 0 < sim._blocks_per_substep <= sim._kept[0].blocks


def test_a_frame_whose_blocks_overflow_its_packed_slot_recomputes():
    """An estimate far below the blocks a frame tags: that frame is not stored (its backward
    recomputes, same gradients), and the count it measured sizes the next slots, which
    then hold their frames."""
    import pd_tool.sim.autograd as ag

    x, static, vol, E, push = block(7)
    ref = run(sim_for(static, vol, 0, binned=True), x, E, push, 12)
    sim = sim_for(static, vol, None, binned=True, pooled=True)
    sim._blocks_per_substep = 0.05  # about one block for the whole first frame
    held = []
    note = sim.note_stored

    def spy(slot, substeps):
        held.append(slot.holds)
        note(slot, substeps)

    sim.note_stored = spy
    assert_same(run(sim, x, E, push, 12), ref)
    assert held[0] is False and all(held[1:]) and len(held) == 3
    assert sim._blocks_per_substep > 1
    assert all(isinstance(k, ag._PackedFrame) for k in sim._kept)


def test_touched_blocks_against_every_stencil_node():
    """gather.touched_blocks against a per-particle walk over the 27 stencil nodes, with
    particles at the grid's edges and outside it (clamped as stencil_base clamps)."""
    from pd_tool.sim.gather import BLOCK, touched_blocks
    from pd_tool.sim.solver import GridGeometry

    geo = GridGeometry.from_config(SimConfig(grid_res=20))
    rng = np.random.default_rng(4)
    x = np.concatenate([rng.uniform(-0.1, 1.1, (400, 3)), rng.uniform(0.4, 0.45, (100, 3))])
    nodes = np.asarray(geo.nodes)
    want = set()
    for p in x:
        q = p / geo.dx - 0.5
        b = np.where(q >= 0, np.minimum(np.floor(np.maximum(q, 0)), nodes - 3), 0).astype(int)
        for o in np.ndindex(3, 3, 3):
            want.add(tuple((b + np.array(o)) // BLOCK))
    assert touched_blocks(x, geo) == len(want)
    assert touched_blocks(x[400:], geo) < len(want)
    assert touched_blocks(np.zeros((0, 3)), geo) == 0
