"""MPM buffers and launches: the configuration, the grid geometry and the fast forward path.

The fast path (MPMSolver) runs without a tape, allocates its buffers once, updates particle
state in place (each G2P thread owns its particle, so aliasing is safe without a tape) and,
on CUDA, replays one captured graph per frame. The differentiable path lives in autograd.py
and reuses `launch_substep` with separate per-substep arrays.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from pd_tool.core.errors import PdToolError
from pd_tool.sim import kernels as K
from pd_tool.sim.cfl import cfl_substeps, wave_speed
from pd_tool.sim.gather import alloc_cell_lists, block_shape, run_substeps_binned, run_substeps_rows
from pd_tool.sim.guard import check_stats, fold_stat_lanes

wp.config.quiet = True


class SimConfigError(PdToolError):
    """A simulator setting or input array is invalid."""


@dataclass
class SimConfig:
    """Simulation settings (SI units).

    Attributes:
        grid_res: cells along the longest axis of `domain`; dx = max(domain) / grid_res.
        domain: (Lx, Ly, Lz) box in metres; particles live in [0,Lx]x[0,Ly]x[0,Lz]. The
            outer `boundary_pad` node layers are walls, so keep the object at least
            boundary_pad + 1 cells away from every face.
        nu: Poisson's ratio, constant (0 <= nu < 0.5).
        gravity: m/s^2; (0, 0, 0) switches it off.
        damping: grid velocity damping rate, 1/s (v *= exp(-damping dt) per substep).
        substeps: substeps per frame; None = chosen by the CFL condition.
        min_substeps: with substeps None, the least the CFL choice may give (None: no floor).
            MPM's numerical damping grows with the substep count, so a floor holds the count,
            and the damping, while E changes below what it allows (the fit's diagnostics).
        cfl_safety: CFL number: dt <= cfl_safety * dx / (wave speed + max speed).
        ground_z: optional ground plane height in metres (nodes below stop falling).
        boundary_pad: wall thickness in nodes (free-slip walls).
        min_det_f: guard threshold: det F below this counts as collapsed/inverted.
        segment: substeps recomputed and stored per pass of the differentiable backward
            (memory knob: one particle state and one grid per substep of a segment); None =
            as many as fit in `segment_budget_mb` (a whole frame avoids recomputing it twice:
            1.5x faster backward at 100k particles, 64 substeps).
        segment_budget_mb: memory for the stored substeps when segment is None; None = a
            quarter of the GPU's free memory on CUDA, 2048 MB on the CPU.
        backward: "adjoint" (hand-written reverse kernels, adjoint.py) or "tape" (warp's
            generated adjoints replayed under a wp.Tape; slower, kept as the reference).
        keep_budget_mb: memory in which the differentiable forward stores each substep's
            state and grid of the frames it runs with gradients, so that their backward
            skips the recompute (with "adjoint" only; a frame that does not fit, or whose
            slot fails to allocate, is recomputed as before); None = a quarter of the GPU's
            free memory on CUDA, on the CPU a quarter of the available RAM up to 1024 MB,
            each read at the first frame; 0 = always recompute.
    """

    grid_res: int = 64
    domain: tuple[float, float, float] = (1.0, 1.0, 1.0)
    nu: float = 0.3
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)
    damping: float = 0.0
    substeps: int | None = None
    min_substeps: int | None = None
    cfl_safety: float = 0.5
    ground_z: float | None = None
    boundary_pad: int = 3
    min_det_f: float = 1e-2
    segment: int | None = None
    segment_budget_mb: float | None = None
    backward: str = "adjoint"
    keep_budget_mb: float | None = None

    def validate(self) -> None:
        if self.grid_res < 4:
            raise SimConfigError(f"SimConfig.grid_res={self.grid_res}: need at least 4 cells")
        if len(self.domain) != 3 or min(self.domain) <= 0:
            raise SimConfigError(f"SimConfig.domain={self.domain}: need three positive lengths in metres")
        if not (0.0 <= self.nu < 0.5):
            raise SimConfigError(f"SimConfig.nu={self.nu}: Poisson's ratio must be in [0, 0.5)")
        if not (0.0 < self.cfl_safety <= 1.0):
            raise SimConfigError(f"SimConfig.cfl_safety={self.cfl_safety}: must be in (0, 1]")
        if self.substeps is not None and self.substeps < 1:
            raise SimConfigError(f"SimConfig.substeps={self.substeps}: must be >= 1 or None (CFL)")
        if self.min_substeps is not None and self.min_substeps < 1:
            raise SimConfigError(f"SimConfig.min_substeps={self.min_substeps}: must be >= 1 or None")
        if self.boundary_pad < 1:
            raise SimConfigError(f"SimConfig.boundary_pad={self.boundary_pad}: must be >= 1")
        if self.segment is not None and self.segment < 1:
            raise SimConfigError(f"SimConfig.segment={self.segment}: must be >= 1 substeps or None (auto)")
        if self.backward not in ("adjoint", "tape"):
            raise SimConfigError(f"SimConfig.backward={self.backward!r}: use 'adjoint' or 'tape'")
        if self.keep_budget_mb is not None and not self.keep_budget_mb >= 0:
            raise SimConfigError(f"SimConfig.keep_budget_mb={self.keep_budget_mb}: must be >= 0 MB or None (auto)")
        if self.damping < 0:
            raise SimConfigError(f"SimConfig.damping={self.damping}: must be >= 0 (1/s)")


@dataclass
class Force:
    """A constant acceleration on a particle set during [t_start, t_end) seconds.

    Attributes:
        mask: [N] bool, the particles pushed.
        accel: (3,) m/s^2.
        t_start, t_end: window in simulation seconds.
    """

    mask: np.ndarray
    accel: tuple[float, float, float]
    t_start: float = 0.0
    t_end: float = math.inf


@dataclass
class GridGeometry:
    """Background grid covering [0, n*dx] per axis; nodes = cells + 1 per axis."""

    dx: float
    cells: tuple[int, int, int]
    pad: int

    @classmethod
    def from_config(cls, cfg: SimConfig) -> "GridGeometry":
        dx = max(cfg.domain) / cfg.grid_res
        cells = tuple(max(4, int(math.ceil(L / dx - 1e-6))) for L in cfg.domain)
        if (cells[0] + 1) * (cells[1] + 1) >= K.MAX_NODE_ROWS:
            raise SimConfigError(f"SimConfig.grid_res={cfg.grid_res} gives {cells[0]} x {cells[1]} cells across x and "
                                 f"y, more than the grid kernels index ({K.MAX_NODE_ROWS:,} nodes in a z layer); "
                                 "use a coarser grid")
        return cls(dx=dx, cells=cells, pad=cfg.boundary_pad)

    @property
    def nodes(self) -> tuple[int, int, int]:
        return tuple(c + 1 for c in self.cells)

    @property
    def nodes_vec(self) -> wp.vec3i:
        return wp.vec3i(*self.nodes)

    @property
    def edge_lo(self) -> wp.vec3:
        # A particle closer than one cell to the grid border has left the walls behind.
        return wp.vec3(self.dx, self.dx, self.dx)

    @property
    def edge_hi(self) -> wp.vec3:
        return wp.vec3(*[(c - 1) * self.dx for c in self.cells])


@dataclass
class ForceArrays:
    """Device copy of the forces: mask [K, N] float, accel [K] vec3, window [K] vec2."""

    n: int
    mask: wp.array
    accel: wp.array
    window: wp.array

    @classmethod
    def build(cls, forces: list[Force], n_particles: int, device) -> "ForceArrays":
        k = max(1, len(forces))  # warp needs a non-empty array even without forces
        mask = np.zeros((k, n_particles), np.float32)
        accel = np.zeros((k, 3), np.float32)
        window = np.zeros((k, 2), np.float32)
        for i, f in enumerate(forces):
            m = np.asarray(f.mask)
            if m.shape != (n_particles,):
                raise SimConfigError(f"force {i}: mask has shape {m.shape}, expected ({n_particles},)")
            mask[i] = m.astype(np.float32)
            accel[i] = np.asarray(f.accel, np.float32).reshape(3)
            window[i] = (f.t_start, min(f.t_end, 3.0e38))
        return cls(
            n=len(forces),
            mask=wp.array(mask, dtype=float, device=device),
            accel=wp.array(accel, dtype=wp.vec3, device=device),
            window=wp.array(window, dtype=wp.vec2, device=device),
        )


@dataclass
class GridArrays:
    """mmv: momentum (kg m/s) and mass (kg) per node, one vec4 so that a CUDA P2G adds both
    with one 128-bit reduction (gather.red_add_vec4); v: node velocity (m/s); blocks: the
    binned P2G's activity tags, one per block of gather.BLOCK^3 nodes (gather.block_tagged)."""

    mmv: wp.array
    v: wp.array
    blocks: wp.array

    @classmethod
    def alloc(cls, geo: GridGeometry, device, requires_grad: bool = False) -> "GridArrays":
        s = geo.nodes
        return cls(
            mmv=wp.zeros(s, dtype=wp.vec4, device=device, requires_grad=requires_grad),
            v=wp.zeros(s, dtype=wp.vec3, device=device, requires_grad=requires_grad),
            blocks=wp.zeros(block_shape(s), dtype=int, device=device),
        )


@dataclass
class ParticleState:
    """u: displacement from `base` [N] vec3 (m); v [N] vec3 (m/s); C [N] mat33 (1/s); G [N]
    mat33 the deformation gradient less the identity, F - I (kernels.py says why)."""

    u: wp.array
    v: wp.array
    C: wp.array
    G: wp.array
    _struct: K.ParticleVars | None = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def zeros(cls, n: int, device, requires_grad: bool = False) -> "ParticleState":
        return cls(*(wp.zeros(n, dtype=t, device=device, requires_grad=requires_grad)
                     for t in (wp.vec3, wp.vec3, wp.mat33, wp.mat33)))

    def clone(self, requires_grad: bool = False) -> "ParticleState":
        out = []
        for a in (self.u, self.v, self.C, self.G):
            c = wp.empty_like(a, requires_grad=requires_grad)
            wp.copy(c, a)
            out.append(c)
        return ParticleState(*out)

    @property
    def struct(self) -> K.ParticleVars:
        """The four arrays as the kernels' ParticleVars, built on first use: states live in
        buffers reused for every substep, so launches never rebuild it."""
        if self._struct is None:
            self._struct = particle_vars(self.u, self.v, self.C, self.G)
        return self._struct


def particle_vars(u: wp.array, v: wp.array, C: wp.array, G: wp.array) -> K.ParticleVars:
    """K.ParticleVars over u, v [N] vec3 and C, G [N] mat33 (a state or its cotangents)."""
    s = K.ParticleVars()
    s.u, s.v, s.C, s.G = u, v, C, G
    return s


@dataclass
class Materials:
    """Per-particle constants on the device: E (Pa), volume (m^3), mass (kg), static (int)."""

    E: wp.array
    volume: wp.array
    mass: wp.array
    static: wp.array


@dataclass
class SubstepContext:
    """Everything a substep launch needs apart from the particle state and the grid.

    The kernels' argument structs (particles(), step(dt), forces_struct()) are built on
    first use and kept, so a context reused across frames builds them once."""

    geo: GridGeometry
    cfg: SimConfig
    order: wp.array
    base: wp.array
    mat: Materials
    fixed: wp.array
    forces: ForceArrays
    t_frame: wp.array
    stats: wp.array
    device: object = field(default=None)
    _structs: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def particles(self) -> K.Particles:
        """order, base and materials [N] as K.Particles."""
        p = self._structs.get("particles")
        if p is None:
            p = self._structs["particles"] = K.Particles()
            p.order, p.base, p.E = self.order, self.base, self.mat.E
            p.volume, p.mass, p.is_static = self.mat.volume, self.mat.mass, self.mat.static
        return p

    def forces_struct(self) -> K.Forces:
        """The forces and the frame clock t_frame [1] (s) as K.Forces."""
        f = self._structs.get("forces")
        if f is None:
            f = self._structs["forces"] = K.Forces()
            fa = self.forces
            f.n, f.mask, f.accel, f.window, f.t_frame = fa.n, fa.mask, fa.accel, fa.window, self.t_frame
        return f

    def step(self, dt: float) -> K.StepParams:
        """K.StepParams for substeps of dt seconds (kept per dt: the CFL count may change)."""
        key = ("step", float(dt))
        sp = self._structs.get(key)
        if sp is None:
            geo, cfg = self.geo, self.cfg
            sp = K.StepParams()
            sp.dx, sp.inv_dx = float(geo.dx), K.reciprocal_f32(geo.dx)
            sp.dt, sp.nodes = float(dt), geo.nodes_vec
            sp.inv_nodes = wp.vec3(*(K.reciprocal_f32(n) for n in geo.nodes))
            sp.lame_per_E, sp.min_det_f = wp.vec2(*K.lame_per_e(float(cfg.nu))), float(cfg.min_det_f)
            sp.edge_lo, sp.edge_hi = geo.edge_lo, geo.edge_hi
            sp.pad, sp.gravity = int(geo.pad), wp.vec3(*cfg.gravity)
            sp.damping_factor = float(math.exp(-cfg.damping * dt))
            sp.use_ground = int(cfg.ground_z is not None)
            sp.ground_z = float(cfg.ground_z if cfg.ground_z is not None else 0.0)
            sp.fixed = self.fixed
            if len(self._structs) > 16:  # a long fit may try many dt: keep the dict small
                self._structs = {k: v for k, v in self._structs.items() if not isinstance(k, tuple)}
            self._structs[key] = sp
        return sp


def launch_substep(ctx: SubstepContext, dt: float, t_offset: float,
                   s_in: ParticleState, s_out: ParticleState, grid: GridArrays) -> None:
    """One MPM substep of dt seconds at t_frame + t_offset: zero grid, P2G, grid update, G2P
    (state s_in -> s_out).

    s_out may alias s_in only without a tape; under a tape give separate arrays (and a
    separate `grid`) per substep so that the adjoints read the values of that substep.
    """
    dev = ctx.device
    n = s_in.u.shape[0]
    ptcl, step = ctx.particles(), ctx.step(dt)
    grid.mmv.zero_()
    wp.launch(K.p2g, dim=n, device=dev,
              inputs=[ptcl, s_in.struct, step, ctx.forces_struct(), float(t_offset), grid.mmv])
    wp.launch(K.grid_update, dim=ctx.geo.nodes, device=dev, inputs=[step, grid.mmv, grid.v])
    wp.launch(K.g2p, dim=n, device=dev, inputs=[ptcl, s_in.struct, step, grid.v, s_out.struct, ctx.stats])


def run_substeps_fused(ctx: SubstepContext, n: int, dt: float, st: ParticleState, g: GridArrays) -> None:
    """n substeps of dt seconds in place without a tape, two launches per substep.

    The grid update also clears mass and momentum, and each G2P is fused with the next
    substep's P2G; the run starts with a plain P2G and ends with a plain G2P. Same result
    as n calls of launch_substep up to the order of float atomics.
    """
    dev = ctx.device
    ptcl, step, forces, sv = ctx.particles(), ctx.step(dt), ctx.forces_struct(), st.struct
    count = st.u.shape[0]
    g.mmv.zero_()
    wp.launch(K.p2g, dim=count, device=dev, inputs=[ptcl, sv, step, forces, 0.0, g.mmv])
    for s in range(n):
        wp.launch(K.grid_update_and_clear, dim=ctx.geo.nodes, device=dev, inputs=[step, g.mmv, g.v])
        if s < n - 1:
            wp.launch(K.g2p_p2g, dim=count, device=dev,
                      inputs=[ptcl, sv, step, forces, float((s + 1) * dt), g.v, g.mmv, ctx.stats])
        else:
            wp.launch(K.g2p, dim=count, device=dev, inputs=[ptcl, sv, step, g.v, sv, ctx.stats])


def sort_by_cell(geo: GridGeometry, base: wp.array, u: wp.array, keys: wp.array,
                 values: wp.array, device) -> None:
    """Fill values[:N] with particle indices sorted by stencil cell (keys/values hold 2N)."""
    n = base.shape[0]
    wp.launch(K.cell_keys, dim=n, device=device,
              inputs=[base, u, 1.0 / geo.dx, geo.nodes_vec, keys, values])
    wp.utils.radix_sort_pairs(keys, values, n)


def cell_order(geo: GridGeometry, x: np.ndarray) -> np.ndarray:
    """[N] permutation that sorts particles by the cell of their stencil base (host, once)."""
    b = np.clip(np.floor(x / geo.dx - 0.5), 0, np.array(geo.nodes) - 3).astype(np.int64)
    key = (b[:, 0] * geo.nodes[1] + b[:, 1]) * geo.nodes[2] + b[:, 2]
    return np.argsort(key, kind="stable")


def fixed_nodes(geo: GridGeometry, base: wp.array, u: wp.array, static: wp.array, device,
                out: wp.array | None = None) -> wp.array:
    """[nodes] int array, 1 where a static particle pins the grid velocity to zero (into
    `out`, zeroed first, when given)."""
    fixed = wp.zeros(geo.nodes, dtype=int, device=device) if out is None else out
    if out is not None:
        fixed.zero_()
    wp.launch(K.mark_fixed_nodes, dim=base.shape[0], device=device,
              inputs=[base, u, static, 1.0 / geo.dx, geo.nodes_vec, fixed])
    return fixed


def check_particles(x0: np.ndarray, volume: np.ndarray, mass: np.ndarray, E: np.ndarray,
                    static: np.ndarray, cfg: SimConfig) -> None:
    """Validate particle arrays at the public boundary, before any launch."""
    n = x0.shape[0]
    if x0.ndim != 2 or x0.shape[1] != 3:
        raise SimConfigError(f"x0 has shape {x0.shape}, expected [N, 3] positions in metres")
    for name, a in (("volume", volume), ("mass", mass), ("E", E), ("static", static)):
        if a.shape != (n,):
            raise SimConfigError(f"{name} has shape {a.shape}, expected ({n},) like x0")
    for name, a in (("volume", volume), ("mass", mass), ("E", E)):
        if not np.all(np.isfinite(a)) or np.any(a <= 0):
            raise SimConfigError(f"{name} must be finite and positive for every particle")
    if not np.all(np.isfinite(x0)):
        raise SimConfigError("x0 holds NaN/inf positions")
    geo = GridGeometry.from_config(cfg)
    lo = (geo.pad + 0.5) * geo.dx
    hi = np.array([(c - geo.pad - 0.5) * geo.dx for c in geo.cells])
    bad = np.any((x0 < lo) | (x0 > hi), axis=1)
    if np.any(bad):
        raise SimConfigError(
            f"{int(bad.sum())} particles lie inside the wall padding or outside the domain "
            f"{tuple(cfg.domain)} m (allowed: [{lo:.4g}, {hi.round(4).tolist()}] m); map the "
            f"object further inside the box or lower boundary_pad")


class MPMSolver:
    """Fast forward MPM: no tape, buffers allocated once, CUDA graph per frame on GPU.

    Args:
        x0: [N, 3] rest positions, m, inside the domain (see SimConfig).
        volume: [N] m^3.  mass: [N] kg.  E: [N] Young's modulus, Pa.
        static: [N] bool, particles that never move (their nodes become Dirichlet cells).
        config: SimConfig.
        device: "cpu" or "cuda" (warp device string).
        optimized: store particles in grid-cell order, fuse G2P with the next P2G and replay
            a CUDA graph per frame (default). False = the obvious implementation (input
            order, three kernels per substep, no graph), the baseline of bench/sim_speed.py.
            Results are always returned in input order.
        sort_particles, fuse_kernels, cuda_graph: override one part of `optimized` (for
            benchmarking each optimisation on its own).
        gather_p2g: P2G by binning particles per cell and summing each cell's share of a
            node before one atomic (gather.py). Default: on CUDA when `optimized` (the
            atomics bound the substep there); off on the CPU, where warp runs threads
            serially and an atomic add costs no more than a plain one.
        warp_sums: with gather_p2g, each G2P and the next P2G in one launch, the chunk sums
            taken within each warp from shared memory (gather.g2p2g_rows; default) rather
            than in a launch of their own from a payload in global memory (False).
    """

    def __init__(self, x0, volume, mass, E, static, config: SimConfig | None = None,
                 device: str = "cpu", optimized: bool = True, *, sort_particles: bool | None = None,
                 fuse_kernels: bool | None = None, cuda_graph: bool | None = None,
                 gather_p2g: bool | None = None, warp_sums: bool = True) -> None:
        cfg = config or SimConfig()
        cfg.validate()
        x0 = np.ascontiguousarray(np.asarray(x0, np.float32))
        volume = np.asarray(volume, np.float32)
        mass = np.asarray(mass, np.float32)
        E = np.asarray(E, np.float32)
        static = np.asarray(static).astype(bool)
        check_particles(x0, volume, mass, E, static, cfg)
        wp.init()
        self.device = wp.get_device(device)
        self.config = cfg
        self.geo = GridGeometry.from_config(cfg)
        self.n = x0.shape[0]
        self.time = 0.0
        self.frame = 0
        moving = ~static if np.any(~static) else np.ones_like(static)
        self._c = wave_speed(E[moving], (mass / volume)[moving], cfg.nu)
        self._vmax = 0.0
        self._kinetic: float | None = 0.0  # of the current state; None = unknown
        self._substeps: int | None = None
        self._forces: list[Force] = []
        self._graphs: dict = {}
        pick = lambda flag: bool(optimized) if flag is None else bool(flag)  # noqa: E731
        self._use_graphs = pick(cuda_graph)
        self._fuse = pick(fuse_kernels)
        self._gather = (bool(optimized) and self.device.is_cuda) if gather_p2g is None else bool(gather_p2g)
        # Particles are stored sorted by grid cell of the rest shape: neighbouring threads then
        # touch neighbouring nodes (cache-friendly atomics) and read contiguous particle data.
        # An elastic body keeps this order coherent while it moves, so it is done once.
        # Inputs are permuted with self._perm, outputs back with self._inv.
        self._perm = cell_order(self.geo, x0) if pick(sort_particles) else np.arange(self.n)
        self._inv = np.empty_like(self._perm)
        self._inv[self._perm] = np.arange(self.n)
        pm = self._perm
        self._static_np = static[pm]
        d = self.device
        self._base = wp.array(x0[pm], dtype=wp.vec3, device=d)
        self.mat = Materials(
            E=wp.array(E[pm], dtype=float, device=d), volume=wp.array(volume[pm], dtype=float, device=d),
            mass=wp.array(mass[pm], dtype=float, device=d),
            static=wp.array(static[pm].astype(np.int32), dtype=int, device=d))
        self.state = ParticleState.zeros(self.n, d)  # at rest: u = 0, v = 0, C = 0, G = 0 (F = I)
        self.grid = GridArrays.alloc(self.geo, d)
        self._order = wp.array(np.arange(self.n, dtype=np.int32), dtype=int, device=d)
        self._x = wp.zeros(self.n, dtype=wp.vec3, device=d)
        self._t_frame = wp.zeros(1, dtype=float, device=d)
        self._stats = wp.zeros(K.N_STATS_WITH_LANES, dtype=float, device=d)
        self._stats_host = (wp.zeros(K.N_STATS_WITH_LANES, dtype=float, device="cpu", pinned=True)
                            if d.is_cuda else None)
        self._fixed = fixed_nodes(self.geo, self._base, self.state.u, self.mat.static, d)
        self._force_arrays = ForceArrays.build([], self.n, d)
        self._rows = self._gather and bool(warp_sums)
        self._bins = alloc_cell_lists(self.n, d) if self._gather and not self._rows else None
        self._ctx: SubstepContext | None = None

    # ---------------------------------------------------------------- inputs
    def set_velocity(self, v) -> None:
        """Set particle velocities [N, 3] m/s (static particles are ignored)."""
        v = np.asarray(v, np.float32)
        if v.shape != (self.n, 3):
            raise SimConfigError(f"set_velocity: shape {v.shape}, expected ({self.n}, 3) m/s")
        v = v[self._perm]
        v[self._static_np] = 0.0  # static particles never move (and must not push in P2G)
        self.state.v.assign(wp.array(v, dtype=wp.vec3, device=self.device))
        self._kinetic = None
        self._vmax = float(np.max(np.linalg.norm(v, axis=1))) if self.n else 0.0

    def add_force(self, mask, accel, t_start: float = 0.0, t_end: float = math.inf) -> None:
        """Push the particles in mask [N] bool with accel (3,) m/s^2 during [t_start, t_end) s."""
        mask = np.asarray(mask).astype(bool)
        if mask.shape != (self.n,):
            raise SimConfigError(f"add_force: mask has shape {mask.shape}, expected ({self.n},) bool")
        self._forces.append(Force(mask[self._perm], tuple(accel), float(t_start), float(t_end)))
        self._force_arrays = ForceArrays.build(self._forces, self.n, self.device)
        self._ctx = None
        self._graphs.clear()  # graphs hold the old force arrays

    # ---------------------------------------------------------------- stepping
    def substeps_per_frame(self, frame_dt: float) -> int:
        """Substeps for one frame: config.substeps, or the CFL choice from the stiffest
        particle's wave speed, the last frame's fastest particle and the speed the active
        forces can add in this frame (never decreases during a run)."""
        if self.config.substeps is not None:
            return int(self.config.substeps)
        # speed term: the fastest particle of the last frame plus what the active forces can
        # add during this frame
        boost = sum(float(np.linalg.norm(f.accel)) * frame_dt for f in self._forces
                    if f.t_start < self.time + frame_dt and f.t_end > self.time)
        n = cfl_substeps(frame_dt, self.geo.dx, self._c, self._vmax + boost, self.config.cfl_safety)
        self._substeps = max(n, self._substeps or 0, self.config.min_substeps or 0)
        return self._substeps

    def _context(self) -> SubstepContext:
        # Kept (with its kernel structs) until add_force replaces the force arrays.
        if self._ctx is None:
            self._ctx = SubstepContext(geo=self.geo, cfg=self.config, order=self._order, base=self._base,
                                       mat=self.mat, fixed=self._fixed, forces=self._force_arrays,
                                       t_frame=self._t_frame, stats=self._stats, device=self.device)
        return self._ctx

    def _frame_launches(self, n: int, dt: float) -> None:
        # A frame's device work between two reads of the guard's stats, in one graph on
        # CUDA: the stats' reset, the substeps and the end-of-frame reduction, so that the
        # host launches one thing a frame. With the reset and the reduction launched around
        # the graph and the stats read through numpy(), a 64-substep frame at 100k / 64^3
        # took 10-27 us longer on an H200 (docs/gpu-runs/sim_speed_frame_graph_h200.json).
        self._stats.zero_()
        self._run_substeps(n, dt)
        K.launch_frame_stats(self.state.v, self.mat.mass, self._stats, self.device)

    def _run_substeps(self, n: int, dt: float) -> None:
        ctx = self._context()
        if self._rows:
            run_substeps_rows(ctx, n, dt, self.state, self.grid)
        elif self._gather:
            run_substeps_binned(ctx, n, dt, self.state, self.grid, self._bins)
        elif self._fuse:
            run_substeps_fused(ctx, n, dt, self.state, self.grid)
        else:
            for s in range(n):
                launch_substep(ctx, dt, s * dt, self.state, self.state, self.grid)

    def step_frame(self, frame_dt: float) -> int:
        """Advance one output frame of frame_dt seconds; return the substeps used.

        Raises SimulationUnstable (naming the frame) if the guard trips; the check reads
        the device counters once per frame, never per substep.
        """
        n = self.substeps_per_frame(frame_dt)
        dt = frame_dt / n
        d = self.device
        self._t_frame.fill_(self.time)
        if d.is_cuda and self._use_graphs:
            key = (n, float(frame_dt))
            graph = self._graphs.get(key)
            if graph is None and self._use_graphs:
                if len(self._graphs) > 8:
                    self._graphs.clear()
                try:
                    with wp.ScopedCapture(device=d) as cap:
                        self._frame_launches(n, dt)
                    graph = self._graphs[key] = cap.graph
                except Exception as e:  # capture unsupported here: plain launches, same result
                    warnings.warn(f"CUDA graph capture failed ({e}); launching kernels directly")
                    self._use_graphs = False
            if graph is not None:
                wp.capture_launch(graph)
            else:
                self._frame_launches(n, dt)
        else:
            self._frame_launches(n, dt)
        if d.is_cuda:
            # into pinned memory: the copy queues behind the frame and the host waits once
            wp.copy(self._stats_host, self._stats)
            wp.synchronize_stream(wp.get_stream(d))
            stats = fold_stat_lanes(self._stats_host.numpy().copy())
        else:
            stats = fold_stat_lanes(self._stats.numpy().copy())
        self.time += frame_dt
        self.frame += 1
        self._kinetic = float(stats[K.STAT_KINETIC])
        self._vmax = float(stats[K.STAT_VMAX])
        check_stats(stats, self.frame - 1, self.time, n)
        return n

    # ---------------------------------------------------------------- outputs
    def positions(self) -> np.ndarray:
        """[N, 3] float32 particle positions, m."""
        wp.launch(K.compose_positions, dim=self.n, device=self.device,
                  inputs=[self._base, self.state.u, self._x])
        return self._x.numpy()[self._inv]

    def displacements(self) -> np.ndarray:
        """[N, 3] float32 displacement from the rest position, m (no rounding from x)."""
        return self.state.u.numpy()[self._inv]

    def velocities(self) -> np.ndarray:
        """[N, 3] float32 particle velocities, m/s."""
        return self.state.v.numpy()[self._inv]

    def deformation_gradients(self) -> np.ndarray:
        """[N, 3, 3] float32 deformation gradients F (rest = identity)."""
        return self.state.G.numpy()[self._inv] + np.eye(3, dtype=np.float32)

    def rotations(self) -> np.ndarray:
        """[N, 3, 3] float32 rotation R of each particle's F = R S (polar decomposition)."""
        R = wp.empty(self.n, dtype=wp.mat33, device=self.device)
        F = wp.array(self.state.G.numpy() + np.eye(3, dtype=np.float32), dtype=wp.mat33, device=self.device)
        wp.launch(K.polar_kernel, dim=self.n, device=self.device, inputs=[F, R])
        return R.numpy()[self._inv]

    def kinetic_energy(self) -> float:
        """Kinetic energy sum 0.5 m |v|^2 of the particles, J.

        Free after step_frame (the guard's reduction computed it); otherwise one device sync.
        """
        if self._kinetic is None:
            stats = wp.zeros(K.N_STATS_WITH_LANES, dtype=float, device=self.device)
            K.launch_frame_stats(self.state.v, self.mat.mass, stats, self.device)
            self._kinetic = float(fold_stat_lanes(stats.numpy().copy())[K.STAT_KINETIC])
        return self._kinetic
