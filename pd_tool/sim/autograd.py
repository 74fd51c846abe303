"""torch.autograd bridge over the warp MPM: one frame per Function, stored or recomputed.

A frame run with gradients stores each substep's particle state and grid in a slot of
`config.keep_budget_mb`, and its backward runs the adjoint kernels over them in reverse.
With the binned P2G on CUDA a slot keeps each grid only in the blocks its substep's P2G
tagged, packed (_PackedFrame), so that a thin object's frames take a fraction of the memory.
Where the budget is spent (or with the taped reference backward), the forward runs the
substeps in place and saves only the frame's input state; the backward then recomputes the
frame from it, keeping one checkpoint every `config.segment` substeps, and reverses each
segment (the taped reference under a wp.Tape with a separate array per substep: warp's
adjoints read the arrays' current values, so in-place updates under a tape would silently
give wrong gradients). Without slots, peak memory is the frame-boundary states plus one
segment's stores, whatever the number of frames.
"""
from __future__ import annotations

import math
import weakref
from contextlib import contextmanager
from typing import Sequence

import numpy as np
import torch
import warp as wp

from pd_tool.core.device import host_available_bytes
from pd_tool.sim import kernels as K
from pd_tool.sim.adjoint import adjoint_segment, recompute_segment
from pd_tool.sim.cfl import cfl_substeps, wave_speed
from pd_tool.sim.gather import (
    BLOCK,
    BLOCK_W,
    block_shape,
    block_tag,
    run_substeps_rows,
    touched_blocks,
)
from pd_tool.sim.guard import check_stats
from pd_tool.sim.solver import (
    Force,
    ForceArrays,
    GridArrays,
    GridGeometry,
    Materials,
    ParticleState,
    SimConfig,
    SimConfigError,
    SubstepContext,
    fixed_nodes,
    launch_substep,
    run_substeps_fused,
    sort_by_cell,
)

K.lean_launches(__name__)

State = tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]


def _vec3(t: torch.Tensor) -> wp.array:
    return wp.from_torch(t.detach().contiguous(), dtype=wp.vec3)


def _mat33(t: torch.Tensor) -> wp.array:
    return wp.from_torch(t.detach().contiguous(), dtype=wp.mat33)


@contextmanager
def _stream_scope(sim: "DiffSim"):
    """Where the bridge launches its warp work, ordered with torch's CUDA work.

    Without graphs: torch's current stream. With graphs: the simulator's own stream, which
    first waits for torch's and which torch's waits for on exit. Torch's default stream is
    the legacy NULL stream, on which CUDA cannot capture a graph ("unknown stream"). So
    everything torch must see before the frame is enqueued before entering, and the
    frame's results are read by torch only after leaving."""
    dev = wp.get_device(sim.device)
    if not dev.is_cuda:
        with wp.ScopedDevice(dev):
            yield
        return
    torch_stream = wp.stream_from_torch(torch.device(sim.device))
    if not sim.cuda_graph:
        with wp.ScopedStream(torch_stream):
            yield
        return
    if sim._stream is None:
        sim._stream = wp.Stream(dev)
    sim._stream.wait_stream(torch_stream)
    try:
        with wp.ScopedStream(sim._stream):
            yield
    finally:
        torch_stream.wait_stream(sim._stream)


def initial_state(x: torch.Tensor, v: torch.Tensor | None = None) -> State:
    """(x, v, C, F) at rest: C = 0, F = I; x [N, 3] m, v [N, 3] m/s (default 0), float32."""
    n = x.shape[0]
    v = torch.zeros_like(x) if v is None else v
    C = torch.zeros(n, 3, 3, dtype=x.dtype, device=x.device)
    F = torch.eye(3, dtype=x.dtype, device=x.device).expand(n, 3, 3).contiguous()
    return x, v, C, F


class _Substeps:
    """`count` + 1 particle states and `count` grids, one array per field ([count + 1, N] for
    u, v, C, G; [count, *nodes] for the grids' mmv, v and activity blocks), so that a frame's
    substeps copy to or from another set in a few launches. `states[i]` and `grids[i]` are
    views for the kernels, built on first use."""

    def __init__(self, n: int, geo: GridGeometry, count: int, device: str) -> None:
        self.count = count
        self.fields = [wp.zeros((count + 1, n), dtype=t, device=device) for t in (wp.vec3, wp.vec3, wp.mat33, wp.mat33)]
        self.fields += [wp.zeros((count, *geo.nodes), dtype=t, device=device) for t in (wp.vec4, wp.vec3)]
        self.fields.append(wp.zeros((count, *block_shape(geo.nodes)), dtype=int, device=device))
        self._views = None
        self._table = None

    @property
    def table(self) -> wp.array:
        """The states' base addresses, as the differentiable path's kernels reach them
        (kernels.state_table)."""
        if self._table is None:
            self._table = K.state_table(self.fields)
        return self._table

    @property
    def states(self) -> list[ParticleState]:
        return self._split()[0]

    @property
    def grids(self) -> list[GridArrays]:
        return self._split()[1]

    def _split(self):
        if self._views is None:
            u, v, C, G = self.fields[:4]
            states = [ParticleState(u[i], v[i], C[i], G[i]) for i in range(self.count + 1)]
            grids = []
            if len(self.fields) == 7:  # a packed slot keeps its grids elsewhere (_PackedFrame)
                mmv, gv, blocks = self.fields[4:]
                grids = [GridArrays(mmv=mmv[i], v=gv[i], blocks=blocks[i]) for i in range(self.count)]
            self._views = (states, grids)
        return self._views

    def copy_from(self, other: "_Substeps", substeps: int, tagged: bool = False, states: bool = True) -> None:
        """The first `substeps` substeps of `other` (states 0..substeps unless not `states`,
        grids 0..substeps-1).

        tagged: copy only the grid nodes of the activity blocks that each substep's binned
        P2G tagged (gather.block_tagged, substep i's tag being block_tag(0, i) as a frame's
        forward and its single-segment backward number them). The adjoint reads no other node; a block
        that kept an older frame's equal tag is copied for nothing. Copied whole, each
        substep's grid (59 MB at 300k particles on 128^3) cost what storing the frame saves
        (docs/simulator.md, "Speed")."""
        for k, (dst, src) in enumerate(zip(self.fields, other.fields)):
            if (tagged and k in (4, 5)) or (not states and k < 4):
                continue
            rows = substeps + 1 if k < 4 else substeps
            wp.copy(dst[:rows], src[:rows])
        if tagged and substeps > 0:
            wp.launch(_tagged_nodes, dim=(substeps, *self.fields[6].shape[1:]), device=self.fields[4].device,
                      inputs=[1, block_tag(0, 0), other.fields[4], other.fields[5], self.fields[6], self.fields[4],
                              self.fields[5]])

    def zero_mass(self, substeps: int, tagged: bool = False) -> None:
        """Zero the first `substeps` grids' mass and momentum, ready for a recompute to add to;
        tagged: only in the blocks tagged as copy_from says, where a binned P2G can have
        added (everywhere else they are zero already)."""
        if not tagged:
            self.fields[4][:substeps].zero_()
        elif substeps > 0:
            f = self.fields
            wp.launch(_tagged_nodes, dim=(substeps, *f[6].shape[1:]), device=f[4].device,
                      inputs=[0, block_tag(0, 0), f[4], f[5], f[6], f[4], f[5]])


# One thread per activity block and substep, not per node: a thread per node that only
# reads its block's tag and returns costs, over a 128^3 frame's 64 grids, about what copying
# them whole does.
@wp.kernel(enable_backward=False)
def _tagged_nodes(copy: int, tag0: int, src_mmv: wp.array4d(dtype=wp.vec4), src_v: wp.array4d(dtype=wp.vec3),
                  blocks: wp.array4d(dtype=int), dst_mmv: wp.array4d(dtype=wp.vec4),
                  dst_v: wp.array4d(dtype=wp.vec3)):
    """Over the nodes of each block tagged by its substep s (tag tag0 + s): copy != 0
    copies src to dst; copy == 0 zeroes dst_mmv (src unread)."""
    s, bi, bj, bk = wp.tid()
    if blocks[s, bi, bj, bk] != tag0 + s:
        return
    for i in range(bi * BLOCK_W, wp.min((bi + 1) * BLOCK_W, dst_mmv.shape[1])):
        for j in range(bj * BLOCK_W, wp.min((bj + 1) * BLOCK_W, dst_mmv.shape[2])):
            for k in range(bk * BLOCK_W, wp.min((bk + 1) * BLOCK_W, dst_mmv.shape[3])):
                if copy != 0:
                    dst_mmv[s, i, j, k] = src_mmv[s, i, j, k]
                    dst_v[s, i, j, k] = src_v[s, i, j, k]
                else:
                    dst_mmv[s, i, j, k] = wp.vec4(0.0)


# Bytes a stored substep takes: per particle its state (u, v, C, G), per grid node its
# (momentum, mass) and velocity, per activity block its tag.
STATE_BYTES = (3 + 3 + 9 + 9) * 4
NODE_BYTES = (4 + 3) * 4
TAG_BYTES = 4


class _KeptFrame(_Substeps):
    """A slot for one frame's forward values, written by forward_frame and read back by
    backward_frame instead of a recompute. A slot is held by one frame of the autograd graph
    (`owner`, a weak reference to that frame's _Claim), and free again after the frame's
    backward or once the graph that held it is gone. Where CUDA graphs replay, the substeps
    run in the simulator's pool and are copied to and from the slot, so that every frame
    replays the pool's graphs; elsewhere they run on the slot's own arrays."""

    holds = True  # the frame stored last fitted (a packed slot's blocks may not)

    def __init__(self, n: int, geo: GridGeometry, capacity: int, device: str) -> None:
        super().__init__(n, geo, capacity, device)  # `count`: the most substeps it holds
        self.owner: weakref.ref | None = None

    def free(self) -> bool:
        return self.owner is None or self.owner() is None

    @property
    def nbytes(self) -> int:
        """What the budget counts: `count` substeps' particle states and grids (the budget
        leaves the one extra state and the tags, 1/64 of a grid, to its margin)."""
        u, _, _, _, mmv = self.fields[:5]
        return self.count * (u.shape[1] * STATE_BYTES + int(np.prod(mmv.shape[1:])) * NODE_BYTES)

    def fits(self, substeps: int, blocks: int) -> bool:
        """Whether a frame of `substeps` whose P2G tags about `blocks` blocks in all fits."""
        return self.count >= substeps

    def store_from(self, pool: _Substeps, substeps: int, tagged: bool, states: bool = True) -> None:
        """The forward's values of a frame run in `pool` (copy_from): the grids, and the
        particle states unless the forward wrote them here (`states` False)."""
        self.copy_from(pool, substeps, tagged=tagged, states=states)

    def load_into(self, pool: _Substeps, substeps: int, tagged: bool, states: bool = True) -> None:
        """Back into `pool` for the frame's backward: the grids, and the particle states
        unless the adjoint reads them from this slot (`states` False, through `table`)."""
        pool.copy_from(self, substeps, tagged=tagged, states=states)


# A packed slot's blocks over the most a substep tagged so far (or over what the particles'
# stencils touch before any frame has run): the particles move within a frame and over a fit.
PACK_MARGIN = 1.25


class _PackedFrame(_KeptFrame):
    """A slot for the binned pool (DiffSim._pooled with DiffSim.binned) that keeps each
    substep's particle state whole but its grid only in the activity blocks the substep's
    P2G tagged, packed one after another (`packed_mmv`, `packed_v`: [blocks, BLOCK^3] nodes;
    `packed_at`: each block's substep and block index). A thin object tags a few percent of
    its grid's blocks, so a frame takes a fraction of a dense slot's memory and the budget
    holds more frames. The blocks a frame tags are known only once it has run: a frame
    that tags more than `blocks` is not stored (`holds` False after store_from) and its
    backward recomputes."""

    def __init__(self, n: int, geo: GridGeometry, capacity: int, blocks: int, device: str) -> None:
        self.count = capacity
        self.fields = [wp.zeros((capacity + 1, n), dtype=t, device=device) for t in (wp.vec3, wp.vec3, wp.mat33, wp.mat33)]
        self.fields.append(wp.zeros((capacity, *block_shape(geo.nodes)), dtype=int, device=device))
        self.blocks = max(1, int(blocks))
        per = BLOCK_W * BLOCK_W * BLOCK_W
        self.packed_mmv = wp.zeros((self.blocks, per), dtype=wp.vec4, device=device)
        self.packed_v = wp.zeros((self.blocks, per), dtype=wp.vec3, device=device)
        self.packed_at = wp.zeros(self.blocks, dtype=int, device=device)
        self.filled = wp.zeros(1, dtype=int, device=device)
        self.filled_blocks = 0
        self.holds = True
        self._views = None
        self._table = None
        self.owner = None

    @property
    def nbytes(self) -> int:
        u, tags = self.fields[0], self.fields[4]
        return (self.count * (u.shape[1] * STATE_BYTES + int(np.prod(tags.shape[1:])) * TAG_BYTES)
                + self.blocks * BLOCK ** 3 * NODE_BYTES)

    def fits(self, substeps: int, blocks: int) -> bool:
        return self.count >= substeps and self.blocks >= blocks

    def store_from(self, pool: _Substeps, substeps: int, tagged: bool, states: bool = True) -> None:
        """The particle states (unless the forward wrote them here: `states` False) and tags
        of the frame in `pool`, and its tagged blocks packed; reads back how many blocks
        that was (one sync) and sets `holds`."""
        for k in range(4 if states else 0):
            wp.copy(self.fields[k][: substeps + 1], pool.fields[k][: substeps + 1])
        wp.copy(self.fields[4][:substeps], pool.fields[6][:substeps])
        self.filled.zero_()
        if substeps > 0:
            wp.launch(_pack_blocks, dim=(substeps, *self.fields[4].shape[1:]), device=self.filled.device,
                      inputs=[block_tag(0, 0), pool.fields[4], pool.fields[5], pool.fields[6], self.filled,
                              self.packed_at, self.packed_mmv, self.packed_v])
        self.filled_blocks = int(self.filled.numpy()[0])
        self.holds = self.filled_blocks <= self.blocks

    def load_into(self, pool: _Substeps, substeps: int, tagged: bool, states: bool = True) -> None:
        for k in range(4 if states else 0):
            wp.copy(pool.fields[k][: substeps + 1], self.fields[k][: substeps + 1])
        wp.copy(pool.fields[6][:substeps], self.fields[4][:substeps])
        wp.launch(_unpack_blocks, dim=self.blocks, device=self.filled.device,
                  inputs=[self.filled, self.packed_at, self.packed_mmv, self.packed_v, self.fields[4], pool.fields[4],
                          pool.fields[5]])


@wp.func
def _block_node(bi: int, bj: int, bk: int, local: int) -> wp.vec3i:
    """Node `local` (0 .. BLOCK^3 - 1, k fastest) of block (bi, bj, bk)."""
    return wp.vec3i(bi * BLOCK_W + local // (BLOCK_W * BLOCK_W), bj * BLOCK_W + (local // BLOCK_W) % BLOCK_W,
                    bk * BLOCK_W + local % BLOCK_W)


@wp.kernel(enable_backward=False)
def _pack_blocks(tag0: int, src_mmv: wp.array4d(dtype=wp.vec4), src_v: wp.array4d(dtype=wp.vec3),
                 tags: wp.array4d(dtype=int), filled: wp.array(dtype=int), packed_at: wp.array(dtype=int),
                 packed_mmv: wp.array2d(dtype=wp.vec4), packed_v: wp.array2d(dtype=wp.vec3)):
    """Each block tagged by its substep s (tag tag0 + s) takes the next packed place and
    its nodes are copied there; `filled` counts the tagged blocks, those past the packed
    arrays' end included (the frame then does not fit)."""
    s, bi, bj, bk = wp.tid()
    if tags[s, bi, bj, bk] != tag0 + s:
        return
    slot = wp.atomic_add(filled, 0, 1)
    if slot >= packed_at.shape[0]:
        return
    packed_at[slot] = ((s * tags.shape[1] + bi) * tags.shape[2] + bj) * tags.shape[3] + bk
    for local in range(BLOCK_W * BLOCK_W * BLOCK_W):
        n = _block_node(bi, bj, bk, local)
        if n[0] < src_mmv.shape[1] and n[1] < src_mmv.shape[2] and n[2] < src_mmv.shape[3]:
            packed_mmv[slot, local] = src_mmv[s, n[0], n[1], n[2]]
            packed_v[slot, local] = src_v[s, n[0], n[1], n[2]]


@wp.kernel(enable_backward=False)
def _unpack_blocks(filled: wp.array(dtype=int), packed_at: wp.array(dtype=int),
                   packed_mmv: wp.array2d(dtype=wp.vec4), packed_v: wp.array2d(dtype=wp.vec3),
                   tags: wp.array4d(dtype=int), dst_mmv: wp.array4d(dtype=wp.vec4), dst_v: wp.array4d(dtype=wp.vec3)):
    """The packed blocks back to their substeps' grids (the inverse of _pack_blocks, whose
    block index `tags`' shape decodes)."""
    t = wp.tid()
    if t >= filled[0]:
        return
    at = packed_at[t]
    nk = tags.shape[3]
    nj = tags.shape[2]
    bk = at % nk
    bj = (at // nk) % nj
    bi = (at // (nk * nj)) % tags.shape[1]
    s = at // (nk * nj * tags.shape[1])
    for local in range(BLOCK_W * BLOCK_W * BLOCK_W):
        n = _block_node(bi, bj, bk, local)
        if n[0] < dst_mmv.shape[1] and n[1] < dst_mmv.shape[2] and n[2] < dst_mmv.shape[3]:
            dst_mmv[s, n[0], n[1], n[2]] = packed_mmv[t, local]
            dst_v[s, n[0], n[1], n[2]] = packed_v[t, local]


class _Claim:
    """What one autograd frame holds of a slot; the slot is free once this is collected."""

    __slots__ = ("slot", "__weakref__")

    def __init__(self, slot: _KeptFrame) -> None:
        self.slot = slot
        slot.owner = weakref.ref(self)

    def take(self) -> _KeptFrame | None:
        """The slot if it is still this frame's, released for the next forward."""
        slot, self.slot = self.slot, None
        if slot is None or slot.owner is None or slot.owner() is not self:
            return None
        slot.owner = None
        return slot


class DiffSim:
    """Differentiable MPM for a fixed particle set (the fit's simulation).

    Args:
        volume: [N] m^3.  mass: [N] kg.  static: [N] bool (Dirichlet particles); numpy or
            CPU tensors.
        config: SimConfig (grid, gravity, nu, walls; `segment` = substeps stored per pass
            of the backward).
        device: torch device of every tensor passed later ("cpu" or "cuda").
    """

    def __init__(self, volume, mass, static, config: SimConfig | None = None, device: str = "cpu") -> None:
        cfg = config or SimConfig()
        cfg.validate()
        wp.init()
        self.config = cfg
        self.geo = GridGeometry.from_config(cfg)
        self.torch_device = torch.device(device)
        if self.torch_device.type == "cuda" and self.torch_device.index is None:
            # tensors report "cuda:0", never "cuda": compare against the indexed device
            idx = torch.cuda.current_device() if torch.cuda.is_available() else 0
            self.torch_device = torch.device("cuda", idx)
        # warp arrays straight from numpy: the warp-only users (bench) need no CUDA torch build
        self.device = "cpu" if self.torch_device.type == "cpu" else f"cuda:{self.torch_device.index or 0}"
        vol = np.asarray(volume, np.float32).reshape(-1)
        m = np.asarray(mass, np.float32).reshape(-1)
        st = np.asarray(static).astype(np.int32).reshape(-1)
        self.n = vol.shape[0]
        if m.shape != (self.n,) or st.shape != (self.n,):
            raise SimConfigError(f"volume, mass, static must all have shape ({self.n},)")
        self._vol, self._mass, self._static = vol, m, st.astype(bool)
        self.volume = wp.array(vol, dtype=float, device=self.device)
        self.mass = wp.array(m, dtype=float, device=self.device)
        self.static = wp.array(st, dtype=wp.int32, device=self.device)
        # P2G (and the adjoint's grid scatter) summed within each warp before one atomic a
        # node (gather.py): on CUDA, where float atomics bound the substep. Tests switch it
        # on for the CPU too.
        self.binned = wp.get_device(self.device).is_cuda
        # Replay the backward's segments as captured CUDA graphs (CUDA only).
        self.cuda_graph = True
        # Stored frames run in the pool and are copied to their slots where graphs replay
        # (CUDA); elsewhere they run on the slot's own arrays, as the copies cost one CPU
        # thread about what a recompute does. Tests switch the pool on for the CPU.
        self.store_in_pool = False
        self._graphs: dict = {}
        self._seen: set = set()  # graph keys run once without a capture (see _run_graphed)
        self._stream = None  # CUDA stream of graph launches (see _stream_scope)
        self._kept: list[_KeptFrame] = []  # slots of forward values (config.keep_budget_mb)

    def forces(self, forces: Sequence[Force]) -> ForceArrays:
        return ForceArrays.build(list(forces), self.n, self.device)

    def frame(self, state: State, E: torch.Tensor, frame_dt: float, substeps: int,
              forces: Sequence[Force] | ForceArrays = (), t0: float = 0.0, frame_index: int = 0) -> State:
        """Advance (x, v, C, F) by one frame; differentiable in x, v, C, F and E.

        Args:
            state: x [N, 3] m, v [N, 3] m/s, C [N, 3, 3] 1/s, F [N, 3, 3]; float32.
            E: [N] Young's modulus, Pa, float32 (any torch graph may produce it).
            frame_dt: s.  substeps: substeps in this frame.
            forces: accelerations with windows in absolute time (t0 = frame start, s).
        Returns:
            the new (x, v, C, F).
        """
        fa = forces if isinstance(forces, ForceArrays) else self.forces(forces)
        x, v, C, F = state
        n = self.n
        for name, t, shape in (("x", x, (n, 3)), ("v", v, (n, 3)), ("C", C, (n, 3, 3)),
                               ("F", F, (n, 3, 3)), ("E", E, (n,))):
            if tuple(t.shape) != shape or t.dtype != torch.float32 or t.device != self.torch_device:
                raise SimConfigError(f"DiffSim.frame: {name} is {tuple(t.shape)} {t.dtype} on {t.device}, "
                                     f"expected {shape} torch.float32 on {self.torch_device}")
        if substeps < 1:
            raise SimConfigError(f"DiffSim.frame: substeps={substeps}, need >= 1")
        graded = torch.is_grad_enabled() and any(t.requires_grad for t in (x, v, C, F, E))
        claim = self._claim_kept(int(substeps), x) if graded else None
        return _FrameFunction.apply(x, v, C, F, E, self, float(frame_dt), int(substeps), fa,
                                    float(t0), int(frame_index), claim)

    # ------------------------------------------------------------------ internals
    def _grid_cache(self) -> GridArrays:
        # One untaped grid, reused by every substep run without a tape.
        g = getattr(self, "_grid", None)
        if g is None:
            g = self._grid = GridArrays.alloc(self.geo, self.device)
        return g

    def run_untaped(self, sctx: SubstepContext, n: int, dt: float, st: ParticleState) -> None:
        """n substeps in place without a tape: the forward and the backward's recompute.

        With the fast path's one-launch G2P + P2G (gather.g2p2g_rows) when self.binned, else the fused scatter."""
        if self.binned:
            run_substeps_rows(sctx, n, dt, st, self._grid_cache())
        else:
            run_substeps_fused(sctx, n, dt, st, self._grid_cache())

    def _context(self, base: wp.array, E: wp.array, order: wp.array, fixed: wp.array,
                 forces: ForceArrays, t0: float) -> SubstepContext:
        t_frame = wp.array([t0], dtype=float, device=self.device)
        stats = wp.zeros(K.N_STATS, dtype=float, device=self.device)
        mat = Materials(E=E, volume=self.volume, mass=self.mass, static=self.static)
        return SubstepContext(geo=self.geo, cfg=self.config, order=order, base=base, mat=mat,
                              fixed=fixed, forces=forces, t_frame=t_frame, stats=stats,
                              device=self.device)

    def segment_length(self, substeps: int) -> int:
        """Substeps recomputed and stored per backward pass: config.segment, or (None) as
        many as fit in config.segment_budget_mb, at most the frame."""
        if self.config.segment is not None:
            return max(1, int(self.config.segment))
        budget = self.config.segment_budget_mb
        if budget is None:
            budget = max(2048.0, self._free_quarter_mb())
        return int(min(substeps, max(1, budget * 2**20 // self._substep_bytes())))

    def _substep_bytes(self) -> int:
        # one stored substep: a particle state (u, v, C, G) and a grid (mmv, v)
        return self.n * STATE_BYTES + int(np.prod(self.geo.nodes)) * NODE_BYTES

    def _free_quarter_mb(self) -> float:
        free = self._gpu_free_bytes()
        return 0.25 * free / 2**20 if free else 0.0

    def _gpu_free_bytes(self) -> float | None:
        """The GPU's free memory now, in bytes; None on the CPU."""
        dev = wp.get_device(self.device)
        return float(dev.free_memory) if dev.is_cuda and getattr(dev, "free_memory", None) else None

    def _keep_budget_bytes(self) -> float:
        budget = getattr(self, "_keep_budget", None)
        if budget is None:
            budget = self.config.keep_budget_mb
            if budget is None:
                cuda = wp.get_device(self.device).is_cuda
                budget = self._free_quarter_mb() if cuda else min(1024.0, 0.25 * host_available_bytes() / 2**20)
            # fixed at the first frame: the free memory read later would count this sim's own slots
            budget = self._keep_budget = budget * 2**20
            # what the budget leaves free on the GPU, for everything else; a slot is added only
            # while that much stays free, so that fits sharing a GPU leave each other room
            free = self._gpu_free_bytes()
            self._keep_reserve = max(0.0, free - budget) if free is not None else None
        return budget

    def _packed(self) -> bool:
        # frames run in the binned pool are stored packed (_PackedFrame)
        return self.binned and self._pooled()

    def _packed_blocks(self, substeps: int, x: "torch.Tensor | np.ndarray") -> int:
        """The blocks to pack a frame of `substeps` into: the most a substep has tagged so
        far, or before any frame the blocks the particles' stencils touch at x, with a
        margin for motion within the frame."""
        per = getattr(self, "_blocks_per_substep", 0.0)
        if not per:
            pos = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
            per = self._blocks_per_substep = float(touched_blocks(pos, self.geo))
        return int(math.ceil(substeps * per * PACK_MARGIN))

    def note_stored(self, slot: "_KeptFrame", substeps: int) -> None:
        """After a forward stored into `slot`: the blocks its substeps tagged size the next
        packed slots."""
        if isinstance(slot, _PackedFrame) and substeps > 0:
            self._blocks_per_substep = max(getattr(self, "_blocks_per_substep", 0.0), slot.filled_blocks / substeps)

    def _claim_kept(self, substeps: int, x: "torch.Tensor | np.ndarray | None" = None) -> "_Claim | None":
        """A free slot for a frame of `substeps` (starting at positions x, for a packed
        slot's size), growing or adding one within the budget; None when the budget is
        spent, the slot cannot be allocated, or the backward would not read it (the taped
        reference, or a frame longer than one segment)."""
        if self.config.backward != "adjoint" or self.segment_length(substeps) < substeps:
            return None
        packed = self._packed() and x is not None
        blocks = self._packed_blocks(substeps, x) if packed else 0
        free = [k for k in self._kept if k.free()]
        fits = [k for k in free if k.fits(substeps, blocks)]
        if fits:
            return _Claim(min(fits, key=lambda k: k.nbytes))
        # bytes a substep takes in a slot: its particle state, and its grid whole or its
        # tagged blocks packed
        per = self._substep_bytes()
        if packed:
            per = self.n * STATE_BYTES + int(np.prod(block_shape(self.geo.nodes))) * TAG_BYTES + \
                math.ceil(blocks / substeps) * BLOCK ** 3 * NODE_BYTES
        held = sum(k.nbytes for k in self._kept)
        drop = max(free, key=lambda k: k.nbytes) if free else None
        room = self._keep_budget_bytes() - held + (drop.nbytes if drop else 0)
        if substeps * per > room:
            return None
        # a quarter more than asked where the budget allows: the substep count creeps up
        # as a fit stiffens E, and each growth is an allocation
        capacity = int(min(substeps + (substeps + 3) // 4, room // per))
        reserve, free_now = getattr(self, "_keep_reserve", None), self._gpu_free_bytes()
        if reserve is not None and free_now is not None:
            # another process may have taken the room since the budget was read (a dropped
            # slot's memory stays in warp's pool, for this process to reuse)
            spare = free_now + (drop.nbytes if drop else 0) - reserve
            capacity = int(min(capacity, spare // per))
            if capacity < substeps:
                return None
        if drop is not None:
            self._kept.remove(drop)  # grown: a larger slot replaces the largest free one
        try:
            if packed:
                slot = _PackedFrame(self.n, self.geo, capacity, blocks * capacity // substeps, self.device)
            else:
                slot = _KeptFrame(self.n, self.geo, capacity, self.device)
        except RuntimeError:
            # The budget was read from the free memory at the first frame; another process
            # (or this one's renderer) may have taken it since. Storing is only a speed-up:
            # this frame and every later one beyond the slots already held recompute.
            self._keep_budget = float(sum(k.nbytes for k in self._kept))
            return None
        self._kept.append(slot)
        return _Claim(slot)

    def _run_graphed(self, key: tuple, launches) -> None:
        """Run `launches()` (a fixed sequence of kernel launches on kept arrays) on CUDA
        from a graph captured for `key`. A key's first run launches directly and its second
        captures: the substep count and dt change with E, and a key run only once (a
        one-frame pass, an iteration whose E gave a new count) would otherwise pay for a
        capture that is never replayed."""
        graph = self._graphs.get(key)
        if graph is None:
            if key not in self._seen:
                if len(self._seen) > 4096:
                    self._seen.clear()
                self._seen.add(key)
                launches()
                return
            with wp.ScopedCapture(device=self.device) as cap:
                launches()
            graph = self._graphs[key] = cap.graph
        wp.capture_launch(graph)

    def _adjoint_pool(self, count: int) -> _Substeps:
        # at least count substeps of forward values, their grids' mass and momentum zero
        # between uses (the recompute adds to them and the adjoint clears them)
        pool = getattr(self, "_adj_pool", None)
        if pool is None or pool.count < count:
            self._graphs = {}  # captured graphs point into the old pool
            pool = self._adj_pool = _Substeps(self.n, self.geo, count, self.device)
        return pool

    def _slot_table(self, slot: "_KeptFrame") -> wp.array:
        # where the graphs of stored frames reach the frame's states, [4] uint64
        # (kernels.state_table), holding `slot`'s addresses from here on: a device copy,
        # queued behind the graphs that read the previous slot's
        table = getattr(self, "_slot_tab", None)
        if table is None:
            table = self._slot_tab = wp.zeros(4, dtype=wp.uint64, device=self.device)
        wp.copy(table, slot.table)
        return table

    def _adjoint_grid(self) -> tuple[wp.array, wp.array]:
        # the grid cotangents (adj_grid_v, adj_mmv); adj_grid_v starts zeroed and is left zeroed
        grid = getattr(self, "_adj_grid", None)
        if grid is None:
            z = lambda t: wp.zeros(self.geo.nodes, dtype=t, device=self.device)  # noqa: E731
            grid = self._adj_grid = (z(wp.vec4), z(wp.vec4))
        return grid

    def _pooled(self) -> bool:
        # with graphs always: a graph's key does not name the slot whose arrays it captured
        return self.store_in_pool or (wp.get_device(self.device).is_cuda and self.cuda_graph)

    def _tape_pool(self, count: int) -> tuple[list[ParticleState], list[GridArrays]]:
        # count + 1 particle states and count grids with gradients, for one taped segment.
        pool = getattr(self, "_pool", None)
        if pool is None or len(pool[1]) < count:
            pool = self._pool = (
                [ParticleState.zeros(self.n, self.device, requires_grad=True) for _ in range(count + 1)],
                [GridArrays.alloc(self.geo, self.device, requires_grad=True) for _ in range(count)])
        return pool

    def _frame_buffers(self, n_force_rows: int) -> dict:
        # Sorted inputs and cotangents of a frame in arrays that outlive it (see _SortedFrame).
        bufs = getattr(self, "_bufs", None)
        if bufs is None or bufs["mask"].shape[0] != n_force_rows:
            n, dev = self.n, self.device
            z = lambda t, shape=n: wp.zeros(shape, dtype=t, device=dev)  # noqa: E731
            bufs = self._bufs = {
                "base": z(wp.vec3), "E": z(float),
                "gu": z(wp.vec3), "gv": z(wp.vec3), "gC": z(wp.mat33), "gF": z(wp.mat33),
                "fu": z(wp.vec3), "fv": z(wp.vec3), "fC": z(wp.mat33), "fG": z(wp.mat33),
                "adj_u": z(wp.vec3), "adj_E": z(float),
                "volume": z(float), "mass": z(float), "static": z(wp.int32), "fixed": z(int, self.geo.nodes),
                "mask": z(float, (n_force_rows, n)), "accel": z(wp.vec3, n_force_rows),
                "window": z(wp.vec2, n_force_rows), "t_frame": z(float, 1), "stats": z(float, K.N_STATS)}
            # the frame state and the cotangents as ParticleStates, whose kernel structs are
            # then built once per buffer set rather than per frame
            bufs["state"] = ParticleState(bufs["fu"], bufs["fv"], bufs["fC"], bufs["fG"])
            bufs["adj"] = ParticleState(bufs["adj_u"], bufs["gv"], bufs["gC"], bufs["gF"])
            self._graphs = {}
        return bufs

    def _identity(self) -> wp.array:
        ident = getattr(self, "_ident", None)
        if ident is None:
            ident = self._ident = wp.array(np.arange(self.n, dtype=np.int32), dtype=int, device=self.device)
        return ident

    def _sort_into(self, base: wp.array, fixed: wp.array) -> wp.array:
        """Sort the particles by stencil cell at positions `base` (kept sort buffers) and mark
        the Dirichlet nodes in `fixed`; returns the order, a view of a kept array that the
        next sort overwrites."""
        keys = getattr(self, "_sort_keys", None)
        if keys is None:
            keys = self._sort_keys = wp.zeros(2 * self.n, dtype=int, device=self.device)
            self._sort_values = wp.zeros(2 * self.n, dtype=int, device=self.device)
            self._zero_u = wp.zeros(self.n, dtype=wp.vec3, device=self.device)
        sort_by_cell(self.geo, base, self._zero_u, keys, self._sort_values, self.device)
        fixed_nodes(self.geo, base, self._zero_u, self.static, self.device, out=fixed)
        return self._sort_values[: self.n]

    def _order_fixed(self, base: wp.array) -> tuple[wp.array, wp.array]:
        """(order, fixed nodes) in new arrays (the taped path and tests)."""
        fixed = wp.zeros(self.geo.nodes, dtype=int, device=self.device)
        return wp.clone(self._sort_into(base, fixed)), fixed


@wp.kernel(enable_backward=False)
def _gather_state(
    order: wp.array(dtype=int),
    x: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3), C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33), E: wp.array(dtype=float), volume: wp.array(dtype=float),
    mass: wp.array(dtype=float), is_static: wp.array(dtype=wp.int32),
    xs: wp.array(dtype=wp.vec3), vs: wp.array(dtype=wp.vec3), Cs: wp.array(dtype=wp.mat33),
    Gs: wp.array(dtype=wp.mat33), Es: wp.array(dtype=float), volumes: wp.array(dtype=float),
    masses: wp.array(dtype=float), is_static_s: wp.array(dtype=wp.int32), us: wp.array(dtype=wp.vec3),
):
    """A frame's start state and materials in sorted order (one launch instead of eight), u = 0,
    G = F - I."""
    t = wp.tid()
    p = order[t]
    xs[t] = x[p]
    vs[t] = v[p]
    Cs[t] = C[p]
    Gs[t] = F[p] - wp.identity(n=3, dtype=float)
    Es[t] = E[p]
    volumes[t] = volume[p]
    masses[t] = mass[p]
    is_static_s[t] = is_static[p]  # (`static` is a C++ keyword)
    us[t] = wp.vec3(0.0)


@wp.kernel(enable_backward=False)
def _gather_cotangents(
    order: wp.array(dtype=int),
    gu: wp.array(dtype=wp.vec3), gv: wp.array(dtype=wp.vec3), gC: wp.array(dtype=wp.mat33),
    gF: wp.array(dtype=wp.mat33),
    gu_s: wp.array(dtype=wp.vec3), adj_u: wp.array(dtype=wp.vec3), adj_v: wp.array(dtype=wp.vec3),
    adj_C: wp.array(dtype=wp.mat33), adj_F: wp.array(dtype=wp.mat33), adj_E: wp.array(dtype=float),
):
    """The end-state cotangents in sorted order, twice for u (the adjoint consumes one copy),
    and E's cotangent zeroed."""
    t = wp.tid()
    p = order[t]
    gu_s[t] = gu[p]
    adj_u[t] = gu[p]
    adj_v[t] = gv[p]
    adj_C[t] = gC[p]
    adj_F[t] = gF[p]
    adj_E[t] = 0.0


@wp.kernel(enable_backward=False)
def _scatter_gradients(
    order: wp.array(dtype=int),
    adj_u: wp.array(dtype=wp.vec3), gu_s: wp.array(dtype=wp.vec3), adj_v: wp.array(dtype=wp.vec3),
    adj_C: wp.array(dtype=wp.mat33), adj_F: wp.array(dtype=wp.mat33), adj_E: wp.array(dtype=float),
    gx: wp.array(dtype=wp.vec3), gv: wp.array(dtype=wp.vec3), gC: wp.array(dtype=wp.mat33),
    gF: wp.array(dtype=wp.mat33), gE: wp.array(dtype=float),
):
    """The start-state gradients back in input order; x's without the direct term (see
    backward_frame)."""
    t = wp.tid()
    p = order[t]
    gx[p] = adj_u[t] - gu_s[t]
    gv[p] = adj_v[t]
    gC[p] = adj_C[t]
    gF[p] = adj_F[t]
    gE[p] = adj_E[t]


@wp.kernel(enable_backward=False)
def _less_identity(F: wp.array(dtype=wp.mat33), G: wp.array(dtype=wp.mat33)):
    """G = F - I, the state's form of the deformation gradient."""
    p = wp.tid()
    G[p] = F[p] - wp.identity(n=3, dtype=float)


@wp.kernel(enable_backward=False)
def _scatter_state(
    order: wp.array(dtype=int),
    base: wp.array(dtype=wp.vec3), u: wp.array(dtype=wp.vec3), v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33), G: wp.array(dtype=wp.mat33),
    x_out: wp.array(dtype=wp.vec3), v_out: wp.array(dtype=wp.vec3), C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
):
    """The end state back in input order, x = base + u, F = I + G."""
    t = wp.tid()
    p = order[t]
    x_out[p] = base[t] + u[t]
    v_out[p] = v[t]
    C_out[p] = C[t]
    F_out[p] = K.deformation_gradient(G[t])


@wp.kernel(enable_backward=False)
def _gather_columns(src: wp.array2d(dtype=float), order: wp.array(dtype=int), dst: wp.array2d(dtype=float)):
    k, t = wp.tid()
    dst[k, t] = src[k, order[t]]


class _SortedFrame:
    """One frame's particles stored in stencil-cell order (sorted by the frame's start
    positions), so that neighbouring threads read neighbouring particles and grid nodes:
    the adjoint kernels read every particle array by index. Inputs are gathered into that
    order, results scattered back; per frame that is a few copies, against every substep's
    scattered reads without it. Every sorted array lives in buffers the DiffSim keeps (the
    same arrays every frame), which is what lets forward and backward replay captured
    CUDA graphs."""

    def __init__(self, sim: "DiffSim", x: wp.array, forces: ForceArrays) -> None:
        self.sim = sim
        b = self.buffers = sim._frame_buffers(forces.mask.shape[0])
        self.order = sim._sort_into(x, b["fixed"])
        wp.copy(b["accel"], forces.accel)
        wp.copy(b["window"], forces.window)
        wp.launch(_gather_columns, dim=b["mask"].shape, device=sim.device, inputs=[forces.mask, self.order, b["mask"]])
        self.forces = ForceArrays(n=forces.n, mask=b["mask"], accel=b["accel"], window=b["window"])

    def gather_state(self, x: wp.array, v: wp.array, C: wp.array, F: wp.array, E: wp.array,
                     st: ParticleState) -> tuple[wp.array, wp.array]:
        """Start state into st (u = 0) and the kept buffers; returns (base, E) sorted."""
        b, sim = self.buffers, self.sim
        wp.launch(_gather_state, dim=sim.n, device=sim.device, inputs=[
            self.order, x, v, C, F, E, sim.volume, sim.mass, sim.static,
            b["base"], st.v, st.C, st.G, b["E"], b["volume"], b["mass"], b["static"], st.u])
        return b["base"], b["E"]

    def context(self, base: wp.array, E: wp.array, t0: float) -> SubstepContext:
        """The substeps' context over the sorted arrays (identity order, kept clock and stats)."""
        b, sim = self.buffers, self.sim
        b["t_frame"].fill_(t0)
        mat = Materials(E=E, volume=b["volume"], mass=b["mass"], static=b["static"])
        return SubstepContext(geo=sim.geo, cfg=sim.config, order=sim._identity(), base=base, mat=mat,
                              fixed=b["fixed"], forces=self.forces, t_frame=b["t_frame"], stats=b["stats"],
                              device=sim.device)


class _FrameFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, v, C, F, E, sim: DiffSim, frame_dt, substeps, forces, t0, frame_index, claim):
        x_out, v_out, C_out, F_out = (torch.empty_like(t) for t in (x, v, C, F))
        # torch-side copies (contiguous) before the scope: the simulator's stream waits for them
        args = (_vec3(x), _vec3(v), _mat33(C), _mat33(F), wp.from_torch(E.detach().contiguous()))
        outs = (_vec3(x_out), _vec3(v_out), _mat33(C_out), _mat33(F_out))
        kept = claim.slot if claim is not None else None
        with _stream_scope(sim):
            stats = forward_frame(sim, *args, forces, t0, frame_dt, substeps, *outs, kept=kept)
            stats = stats.numpy().copy()  # one sync per frame for the guard
        if kept is not None:
            sim.note_stored(kept, substeps)
            if not kept.holds:  # its blocks did not fit the packed slot: the backward recomputes
                claim.take()
                claim = None
        check_stats(stats, frame_index, t0 + frame_dt, substeps)
        ctx.save_for_backward(x, v, C, F, E)
        ctx.sim, ctx.frame_dt, ctx.substeps, ctx.forces, ctx.t0 = sim, frame_dt, substeps, forces, t0
        ctx.claim = claim
        return x_out, v_out, C_out, F_out

    @staticmethod
    def backward(ctx, gx, gv, gC, gF):
        x, v, C, F, E = ctx.saved_tensors
        sim: DiffSim = ctx.sim
        gx, gv, gC, gF = (torch.zeros_like(t) if g is None else g.contiguous()
                          for g, t in ((gx, x), (gv, v), (gC, C), (gF, F)))
        args = (_vec3(x), _vec3(v), _mat33(C), _mat33(F), wp.from_torch(E.detach().contiguous()))
        cot = (_vec3(gx), _vec3(gv), _mat33(gC), _mat33(gF))
        # the stored forward values are read once: a second backward (retain_graph) recomputes
        kept = ctx.claim.take() if ctx.claim is not None else None
        with _stream_scope(sim):
            grads = backward_frame(sim, *args, ctx.forces, ctx.t0, ctx.frame_dt, ctx.substeps, *cot, kept=kept)
        # after the scope: torch's stream now waits for the simulator's
        grad_x, grad_v, grad_C, grad_F, grad_E = (wp.to_torch(g).clone() for g in grads)
        return grad_x + gx, grad_v, grad_C, grad_F, grad_E, None, None, None, None, None, None, None


def forward_frame(sim: DiffSim, x: wp.array, v: wp.array, C: wp.array, F: wp.array, E: wp.array,
                  forces: ForceArrays, t0: float, frame_dt: float, substeps: int,
                  x_out: wp.array, v_out: wp.array, C_out: wp.array, F_out: wp.array,
                  kept: _KeptFrame | None = None) -> wp.array:
    """One frame without a tape on warp arrays (the bridge's forward; the benchmark's too).

    Writes the end state to the *_out arrays (input order) and returns the guard's stats
    array (read it once, after the frame). With `kept` (a slot of at least `substeps`), each
    substep's state and grid are stored there for backward_frame; without, the substeps run
    in place. On CUDA the substeps replay a captured graph keyed by (substeps, dt, forces,
    stored or not): every array they touch is a kept buffer, the stores running in the
    simulator's pool and copied to the slot after (DiffSim._pooled)."""
    dev, n = sim.device, sim.n
    dt = frame_dt / substeps
    fr = _SortedFrame(sim, x, forces)
    buf = fr.buffers
    pooled = kept is not None and sim._pooled()
    # binned, the kernels write the states straight into the slot, through the table that
    # every stored frame copies its slot's addresses into; the grids stay in the pool
    direct = pooled and sim.binned
    store, table = kept, None if kept is None else kept.table
    if pooled:
        store = sim._adjoint_pool(substeps)
        table = store.table
        if direct:
            table = sim._slot_table(kept)
    elif kept is not None:
        kept.zero_mass(substeps)  # the recompute adds to zero mass and momentum
    states = None if kept is None else (kept if direct else store).states
    st = buf["state"] if kept is None else states[0]
    base, E_sorted = fr.gather_state(x, v, C, F, E, st)
    sctx = fr.context(base, E_sorted, t0)
    buf["stats"].zero_()

    def run() -> None:
        if kept is None:
            sim.run_untaped(sctx, substeps, dt, st)
        else:
            recompute_segment(sctx, dt, 0, store.states[: substeps + 1], store.grids[:substeps], sim.binned, table)

    if wp.get_device(dev).is_cuda and sim.cuda_graph:
        sim._run_graphed(("forward", substeps, dt, forces.n, sim.binned, kept is not None), run)
    else:
        run()
    end = st if kept is None else states[substeps]
    wp.launch(_scatter_state, dim=n, device=dev, inputs=[
        fr.order, base, end.u, end.v, end.C, end.G, x_out, v_out, C_out, F_out])
    if pooled:
        # the binned P2G tags what it touches: only those blocks are copied and cleared
        kept.store_from(store, substeps, tagged=sim.binned, states=not direct)
        store.zero_mass(substeps, tagged=sim.binned)  # the next recompute adds to zero
    return sctx.stats


def backward_frame(sim: DiffSim, x: wp.array, v: wp.array, C: wp.array, F: wp.array, E: wp.array,
                   forces: ForceArrays, t0: float, frame_dt: float, substeps: int,
                   gu: wp.array, gv: wp.array, gC: wp.array, gF: wp.array, kept: _KeptFrame | None = None):
    """Adjoint of one frame on warp arrays (used by the autograd bridge and the benchmark).

    Inputs are the frame's start state and the cotangents of its end state (gu = cotangent
    of the end displacement, i.e. of the end position). Returns warp arrays
    (grad_x through the stencil and stress only, grad_v, grad_C, grad_F, grad_E); the caller
    adds the direct term gx of x_out = x + u to grad_x. The input arrays are not modified.
    `sim.config.backward` picks the hand-written adjoint kernels or the taped replay.
    `kept`: the slot forward_frame stored this frame in (same inputs), read instead of a
    recompute and left ready for another forward.
    """
    if sim.config.backward == "tape":
        return backward_frame_taped(sim, x, v, C, F, E, forces, t0, frame_dt, substeps, gu, gv, gC, gF)
    return backward_frame_adjoint(sim, x, v, C, F, E, forces, t0, frame_dt, substeps, gu, gv, gC, gF, kept)


def _checkpoints(sim: DiffSim, sctx: SubstepContext, v: wp.array, C: wp.array, G: wp.array,
                 t0: float, dt: float, substeps: int, seg: int) -> tuple[list[int], dict]:
    # Recompute the frame without a tape, keeping the state (G = F - I) at every segment start.
    st = ParticleState(wp.zeros(sim.n, dtype=wp.vec3, device=sim.device), wp.clone(v), wp.clone(C), wp.clone(G))
    starts = list(range(0, substeps, seg))
    ckpts = {}
    for k0 in starts:
        ckpts[k0] = st.clone()
        if k0 == starts[-1]:
            break  # the last segment is replayed in reverse anyway
        sctx.t_frame.fill_(t0 + k0 * dt)  # the fused run counts time from its first substep
        sim.run_untaped(sctx, seg, dt, st)
    sctx.t_frame.fill_(t0)
    return starts, ckpts


def backward_frame_adjoint(sim: DiffSim, x: wp.array, v: wp.array, C: wp.array, F: wp.array, E: wp.array,
                           forces: ForceArrays, t0: float, frame_dt: float, substeps: int,
                           gu: wp.array, gv: wp.array, gC: wp.array, gF: wp.array,
                           kept: _KeptFrame | None = None):
    """backward_frame with the hand-written adjoint kernels (adjoint.py): per segment, a
    recompute that stores each substep's particle state and grid, then the substeps'
    adjoints in reverse; with `kept`, the adjoints alone over the forward's stores."""
    dev, n = sim.device, sim.n
    if kept is not None and not kept.holds:
        kept = None  # its forward tagged more blocks than the packed slot holds: recompute
    dt = frame_dt / substeps
    fr = _SortedFrame(sim, x, forces)
    buf = fr.buffers
    seg = substeps if kept is not None else sim.segment_length(substeps)
    adj_grid = sim._adjoint_grid()
    binned = sim.binned
    if kept is not None and not sim._pooled():
        store = kept
        table = kept.table
    else:
        store = sim._adjoint_pool(min(seg, substeps))
        table = store.table
        if kept is not None:
            # the grids go back to the pool, whose arrays the graphs captured; the states
            # are read in the slot, through a table that every slot's frame copies its own
            # addresses into (so one graph serves them all)
            kept.load_into(store, substeps, tagged=binned, states=False)
            table = sim._slot_table(kept)
    states, grids = store.states, store.grids
    single = seg >= substeps
    # one segment recomputed: the start state goes straight into the pool's first state
    st0 = states[0] if single and kept is None else buf["state"]
    base, E_sorted = fr.gather_state(x, v, C, F, E, st0)
    sctx = fr.context(base, E_sorted, t0)
    starts, ckpts = [0], {}
    if not single:
        starts, ckpts = _checkpoints(sim, sctx, st0.v, st0.C, st0.G, t0, dt, substeps, seg)
    gu_sorted = buf["gu"]
    adj_st = buf["adj"]
    adj = (adj_st.u, adj_st.v, adj_st.C, adj_st.G, buf["adj_E"])
    wp.launch(_gather_cotangents, dim=n, device=dev, inputs=[fr.order, gu, gv, gC, gF, gu_sorted, *adj])
    # A frame's launches depend only on the segment's start, length and dt (every array is a
    # kept buffer), so on CUDA each segment replays one captured graph: the host issues one
    # launch instead of ~7 per substep, which otherwise bounds the backward.
    use_graph = wp.get_device(dev).is_cuda and sim.cuda_graph
    for k0 in reversed(starts):
        k1 = min(k0 + seg, substeps)
        if not single:
            ck = ckpts.pop(k0)
            first = states[0]
            for dst, src in zip((first.u, first.v, first.C, first.G), (ck.u, ck.v, ck.C, ck.G)):
                wp.copy(dst, src)
            del ck

        def segment(k0=k0, k1=k1):
            if kept is None:
                recompute_segment(sctx, dt, k0, states[: k1 - k0 + 1], grids[: k1 - k0], binned, table)
            adjoint_segment(sctx, dt, k0, table, grids[: k1 - k0], (adj_st, buf["adj_E"]),
                            adj_grid, binned)

        if not use_graph:
            segment()
            continue
        sim._run_graphed((k0, k1 - k0, dt, forces.n, binned, kept is not None), segment)
    grads = tuple(wp.empty_like(a) for a in (gu,) + adj[1:])
    wp.launch(_scatter_gradients, dim=n, device=dev, inputs=[fr.order, adj[0], gu_sorted, *adj[1:], *grads])
    return grads


def backward_frame_taped(sim: DiffSim, x: wp.array, v: wp.array, C: wp.array, F: wp.array, E: wp.array,
                         forces: ForceArrays, t0: float, frame_dt: float, substeps: int,
                         gu: wp.array, gv: wp.array, gC: wp.array, gF: wp.array):
    """backward_frame replaying each segment under a wp.Tape (warp's generated adjoints)."""
    dt = frame_dt / substeps
    seg = sim.segment_length(substeps)
    base = wp.clone(x)
    base.requires_grad = True
    E_w = wp.clone(E)
    E_w.requires_grad = True
    order, fixed = sim._order_fixed(base)
    sctx = sim._context(base, E_w, order, fixed, forces, t0)
    # 1. recompute without a tape, keeping a checkpoint at every segment start
    G = wp.empty_like(F)
    wp.launch(_less_identity, dim=sim.n, device=sim.device, inputs=[F, G])
    starts, ckpts = _checkpoints(sim, sctx, v, C, G, t0, dt, substeps, seg)
    # 2. replay the segments in reverse under a tape, one array set per substep (a pool
    #    reused by every segment and frame: allocating it per segment costs more than the
    #    adjoint kernels on the CPU)
    pool_states, pool_grids = sim._tape_pool(min(seg, substeps))
    adj = [gu, gv, gC, gF]
    for k0 in reversed(starts):
        k1 = min(k0 + seg, substeps)
        states = pool_states[: k1 - k0 + 1]
        grids = pool_grids[: k1 - k0]
        for a in _arrays(states, grids):
            a.grad.zero_()
        first = states[0]
        ck = ckpts.pop(k0)
        for dst, src in zip((first.u, first.v, first.C, first.G), (ck.u, ck.v, ck.C, ck.G)):
            wp.copy(dst, src)
        tape = wp.Tape()
        with tape:
            for i in range(k1 - k0):
                launch_substep(sctx, dt, (k0 + i) * dt, states[i], states[i + 1], grids[i])
        last = states[-1]
        tape.backward(grads={last.u: adj[0], last.v: adj[1], last.C: adj[2], last.G: adj[3]})
        adj = [wp.clone(first.u.grad), wp.clone(first.v.grad), wp.clone(first.C.grad), wp.clone(first.G.grad)]
        # no tape.reset(): it would zero base.grad and E.grad, which accumulate over segments
        del tape
    return base.grad, adj[1], adj[2], adj[3], E_w.grad


def _arrays(states: list[ParticleState], grids: list[GridArrays]):
    for st in states:
        yield from (st.u, st.v, st.C, st.G)
    for g in grids:
        yield from (g.mmv, g.v)


def simulate_frame(state: State, E: torch.Tensor, static, volume, mass, config: SimConfig,
                   frame_dt: float, substeps: int, forces: Sequence[Force] = (), t0: float = 0.0) -> State:
    """One differentiable frame (functional form of DiffSim.frame; builds a DiffSim per call)."""
    sim = DiffSim(volume, mass, static, config, device=str(state[0].device))
    return sim.frame(state, E, frame_dt, substeps, forces, t0)


def simulate_frames(sim: DiffSim, state: State, E: torch.Tensor, frame_dt: float, substeps: int,
                    n_frames: int, horizon: int | None = None, forces: Sequence[Force] = (),
                    t0: float = 0.0) -> list[State]:
    """Simulate n_frames; returns the state after each frame (list of n_frames tuples).

    horizon: None = full back-propagation through time. k = the state is detached at every
    k-th frame boundary, so a frame's loss reaches back at most k frames through the state
    (E keeps its gradient from every frame). horizon=1 is the paper's material stage.
    """
    if horizon is not None and horizon < 1:
        raise SimConfigError(f"horizon={horizon}: must be >= 1 frames or None (full BPTT)")
    fa = sim.forces(forces)
    out = []
    for f in range(n_frames):
        if horizon is not None and f > 0 and f % horizon == 0:
            state = tuple(t.detach() for t in state)
        state = sim.frame(state, E, frame_dt, substeps, fa, t0 + f * frame_dt, frame_index=f)
        out.append(state)
    return out


def cfl_substeps_for(E: torch.Tensor, sim: DiffSim, frame_dt: float, vmax: float = 0.0, quantile: float = 1.0) -> int:
    """CFL substeps per frame for the current E (stiffest moving particle; with quantile
    < 1, that quantile of the moving particles' wave speeds), at least config.min_substeps."""
    moving = ~sim._static if sim._static.any() and not sim._static.all() else np.ones(sim.n, bool)
    c = wave_speed(E.detach().cpu().numpy()[moving], (sim._mass / sim._vol)[moving], sim.config.nu, quantile)
    return max(cfl_substeps(frame_dt, sim.geo.dx, c, vmax, sim.config.cfl_safety), sim.config.min_substeps or 0)


__all__ = ["DiffSim", "forward_frame", "backward_frame", "initial_state", "simulate_frame", "simulate_frames", "cfl_substeps_for"]
