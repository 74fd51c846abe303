"""Scene preparation: which Gaussians move, which stay fixed, and where they sit in the
simulation box.

Coordinates: the simulation works in SI metres inside the box [0, Lx] x [0, Ly] x [0, Lz]
with +z up. `SimTransform` maps scene units to that box (axis permutation for the up
axis, uniform scale by metres-per-unit, shift) and back, in float64, so results map back
to scene units exactly up to float64 rounding.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Sequence

import numpy as np
import torch

from pd_tool.core.arrays import bounds, extent
from pd_tool.core.errors import PreparationError
from pd_tool.core.scene import GaussianScene
from pd_tool.drivers import build_drivers
from pd_tool.drivers.build import MIN_PER_CELL, driver_count
from pd_tool.prepare.cells import Device, block_sums, cell_components, unique_cells, unique_rows
from pd_tool.prepare.fill import PARTICLES_PER_CELL_AXIS, fill_interior, resample_fill
from pd_tool.prepare.orient import direction, find_base, resolve_up, up_line
from pd_tool.prepare.outliers import select_outliers
from pd_tool.prepare.split import SubParticles, split_driver_count, split_drivers, sub_particles
from pd_tool.prepare.thickness import describe_refinement, thin_parts

UP_AXES = ("+x", "-x", "+y", "-y", "+z", "-z")
DEFAULT_OBJECT_SIZE_M = 1.0  # longest object extent when no --meters-per-unit is given
# Longest object extent, m, that the float32 simulation can hold: its squared distances,
# cell volumes and masses stay normal numbers (a micrometre to a thousand kilometres).
OBJECT_SIZE_RANGE_M = (1e-6, 1e6)
WALL_CELLS = 3  # grid cells at each face that the solver reserves for domain walls


# ----------------------------------------------------------------------------- boxes
@dataclass(frozen=True)
class Box:
    """An axis-aligned box in scene units: lo [3], hi [3]."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @classmethod
    def parse(cls, text: str | Sequence[float], what: str = "box") -> "Box":
        """From 'x0,y0,z0,x1,y1,z1' (or six numbers); corners in any order."""
        try:
            vals = [float(v) for v in (text.split(",") if isinstance(text, str) else text)]
        except ValueError:
            raise PreparationError(f"{what} '{text}' is not six numbers; write x0,y0,z0,x1,y1,z1") from None
        if len(vals) != 6 or not all(math.isfinite(v) for v in vals):
            raise PreparationError(f"{what} '{text}' needs six finite numbers: x0,y0,z0,x1,y1,z1")
        a, b = np.array(vals[:3]), np.array(vals[3:])
        if np.any(a == b):
            # a flat box holds (almost) nothing, and what it holds depends on rounding
            raise PreparationError(f"{what} '{text}' has no volume: give two corners that differ on every axis")
        return cls(tuple(np.minimum(a, b).tolist()), tuple(np.maximum(a, b).tolist()))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask [N] of points [N, 3] inside the box (faces included)."""
        return np.all((points >= np.array(self.lo)) & (points <= np.array(self.hi)), axis=1)


def up_rotation(up_axis: str) -> np.ndarray:
    """A proper rotation (3x3, float64) that takes the scene's up axis to +z."""
    if up_axis not in UP_AXES:
        raise PreparationError(f"up axis '{up_axis}' is not one of {', '.join(UP_AXES)}")
    sign = 1.0 if up_axis[0] == "+" else -1.0
    axis = "xyz".index(up_axis[1])
    up = np.zeros(3)
    up[axis] = sign
    # choose the two other rows as a right-handed frame with z = up
    if axis == 2:
        x = np.array([1.0, 0.0, 0.0])
    else:
        x = np.zeros(3)
        x[(axis + 1) % 3] = 1.0
    y = np.cross(up, x)
    return np.stack([x, y, up])


# ----------------------------------------------------------------------------- transform
@dataclass(frozen=True)
class SimTransform:
    """x_sim = scale * (R @ x_scene) + shift, x_sim in metres inside the simulation box.

    rotation [3, 3] (scene axes -> simulation axes, +z up), scale (metres per scene unit),
    shift [3] metres. All float64.
    """

    rotation: tuple[tuple[float, float, float], ...]
    scale: float
    shift: tuple[float, float, float]

    @property
    def R(self) -> np.ndarray:
        return np.asarray(self.rotation, dtype=np.float64)

    def to_sim(self, x: np.ndarray) -> np.ndarray:
        """Scene units [N, 3] -> simulation metres [N, 3] (float64)."""
        return self.scale * (np.asarray(x, np.float64) @ self.R.T) + np.asarray(self.shift)

    def to_scene(self, x: np.ndarray) -> np.ndarray:
        """Simulation metres [N, 3] -> scene units [N, 3] (float64)."""
        return ((np.asarray(x, np.float64) - np.asarray(self.shift)) / self.scale) @ self.R

    def vector_to_sim(self, v: np.ndarray) -> np.ndarray:
        """A direction or acceleration in scene units -> metres in simulation axes."""
        return self.scale * (np.asarray(v, np.float64) @ self.R.T)

    def vector_to_scene(self, v: np.ndarray) -> np.ndarray:
        return (np.asarray(v, np.float64) / self.scale) @ self.R

    def to_dict(self) -> dict[str, Any]:
        return {"rotation": [list(r) for r in self.rotation], "scale": self.scale, "shift": list(self.shift)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "SimTransform":
        return cls(tuple(tuple(float(v) for v in r) for r in d["rotation"]), float(d["scale"]),
                   tuple(float(v) for v in d["shift"]))


# ----------------------------------------------------------------------------- options
@dataclass
class PrepareOptions:
    """Everything that decides how a scene becomes simulation particles (saved with a fit).

    Lengths are in scene units unless named _m (metres). density_kg_m3 in kg/m^3.
    """

    foreground_box: tuple[float, ...] | None = None  # x0,y0,z0,x1,y1,z1; None = everything
    min_opacity: float = 0.02  # nearly invisible Gaussians do not carry the object
    remove_outliers: bool = True
    outlier_min_neighbors: int = 3  # points in the 3x3x3 voxel neighbourhood, self included
    static_box: tuple[float, ...] | None = None  # Gaussians in this box stay fixed
    # ... or everything below this height along up: a signed coordinate along the up axis
    # (with up -y, the coordinate is -y), or "15%": that fraction of the object's height
    # above its bottom
    static_below: float | str | None = None
    pin: str | None = None  # "auto": the base the object stands on (pd_tool.prepare.orient.find_base)
    up_axis: str = "+z"  # or "auto": guessed from the splats by prepare_scene
    meters_per_unit: float | None = None  # None: scale the object to DEFAULT_OBJECT_SIZE_M
    padding: float = 0.25  # free space around the object, as a fraction of its longest extent
    grid_res: int = 32  # cells along the longest axis of the simulation box
    density_kg_m3: float = 1000.0
    fill: str = "auto"  # interior filling of closed shells: auto | on | off (pd_tool/prepare/fill.py)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "PrepareOptions":
        known = {f for f in cls.__dataclass_fields__}
        kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in known}
        return cls(**kw)

    def updated(self, **changes: Any) -> "PrepareOptions":
        """A copy with the options that are not None in `changes` replaced (a user's options
        over a fit's). Boxes are six numbers, low corner first, already checked."""
        known = set(self.__dataclass_fields__)
        bad = sorted(set(changes) - known)
        if bad:
            raise TypeError(f"unknown preparation options: {', '.join(bad)}")
        return replace(self, **{k: (tuple(v) if isinstance(v, list) else v)
                                for k, v in changes.items() if v is not None})


@dataclass
class PreparedScene:
    """A scene ready to simulate.

    foreground: indices [F] into scene of the simulated Gaussians; static [F] bool;
    positions_sim [F, 3] float64 metres; volumes [F] m^3; masses [F] kg;
    dx metres (grid spacing); grid_dims (nx, ny, nz) cells; domain (Lx, Ly, Lz) metres.
    """

    scene: GaussianScene
    options: PrepareOptions
    foreground: np.ndarray
    static: np.ndarray
    transform: SimTransform
    positions_sim: np.ndarray
    volumes: np.ndarray
    masses: np.ndarray
    dx: float
    grid_dims: tuple[int, int, int]
    report: list[str] = field(default_factory=list)
    fill_source: np.ndarray | None = None  # [M] index into the foreground of each filled particle's source
    thin: Any = None  # pd_tool.prepare.thickness.ThinParts of the moving particles at this grid, or None
    grid_free: Any = None  # GridFree: what another grid's preparation takes over (prepare_scene(reuse=))
    # what the floor of drivers a cell derives once: splits()' answers by (ratio, min_per_cell),
    # split_count()'s by ("count", min_per_cell) and the sub-particles by "sub". A bake asks
    # for its cost estimate, its drivers and its report, and each answer is a pass or two over
    # every particle's (or sub-particle's) cell
    _floor: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    # positions_sim/static/volumes/masses hold the F simulated Gaussians first, then the M
    # interior particles added by filling (simulated, never rendered).
    @property
    def n_filled(self) -> int:
        return 0 if self.fill_source is None else int(len(self.fill_source))

    @property
    def n_particles(self) -> int:
        return int(len(self.positions_sim))

    @property
    def domain(self) -> tuple[float, float, float]:
        return tuple(float(n * self.dx) for n in self.grid_dims)

    @property
    def count(self) -> int:
        return int(len(self.foreground))

    def occupied_cells(self, dx: float | None = None) -> int:
        """Grid cells (of edge `dx` m, default this grid's) that hold a simulated particle."""
        return int(len(unique_cells(np.floor(self.positions_sim / (dx or self.dx)), device=self.scene.device)[0]))

    def detached(self, dx: float | None = None) -> np.ndarray:
        """Which simulated particles [P] a grid of cell `dx` m (default this grid's) holds
        apart from the static ones: moving particles in groups of touching occupied cells
        with no static particle (without static particles, outside the group holding the
        most). MPM particles a whole empty cell apart hardly interact, so such a part flies
        off under a push."""
        dev = self.scene.device
        cells, inverse, _ = unique_cells(np.floor(self.positions_sim / (dx or self.dx)), device=dev)
        group = cell_components(cells, device=dev)[inverse]
        static = np.asarray(self.static, bool)
        if static.any():
            anchored = np.isin(group, np.unique(group[static]))
        else:
            anchored = group == np.bincount(group).argmax()
        return ~anchored & ~static

    def detached_share(self, dx: float | None = None) -> float:
        """The share of the moving particles that `detached(dx)` holds apart."""
        moving = int((~np.asarray(self.static, bool)).sum())
        return float(self.detached(dx).sum() / max(moving, 1))

    def moving_cells(self) -> int:
        """Grid cells of this grid that hold a moving (not static) particle."""
        free = np.asarray(self.positions_sim)[~np.asarray(self.static, bool)]
        return int(len(unique_cells(np.floor(free / self.dx), device=self.scene.device)[0])) if len(free) else 0

    def floor_ratio(self, ratio: float | None, min_per_cell: float) -> float:
        """Drivers per simulated particle that build_drivers(ratio=ratio,
        min_per_cell=min_per_cell) makes, about: the ratio's, or, where the ratio gives
        fewer than the floor, the moving drivers split_drivers clusters (then above 1
        where the particles themselves are fewer). For memory and run-time estimates."""
        n = max(self.n_particles, 1)
        base = ratio if ratio is not None else MIN_PER_CELL * self.occupied_cells() / n
        if not self.splits(ratio, min_per_cell):
            return float(base)
        return float(max(base, self.split_count(min_per_cell) / n))

    def split_count(self, min_per_cell: float) -> int:
        """Moving drivers split_drivers clusters for a floor of min_per_cell a cell: that
        many in each cell the moving sub-particles occupy. They spread over each Gaussian's
        extent, so a thin part's sub-particles cross 2-3 times the cells of its centres."""
        key = ("count", float(min_per_cell))
        if key not in self._floor:
            self._floor[key] = split_driver_count(self.sub_particles(), self.dx, int(math.ceil(min_per_cell))) or 0
        return int(self._floor[key])

    def sub_particles(self) -> SubParticles:
        """Every simulated particle as sub-particles over its Gaussian's extent
        (pd_tool.prepare.split.sub_particles), on the CPU; made once, for the estimates'
        count and the drivers clustered from them."""
        if "sub" not in self._floor:
            self._floor["sub"] = sub_particles(self.scene, self)
        return self._floor["sub"]

    def splits(self, ratio: float | None, min_per_cell: float) -> bool:
        """Whether build_drivers clusters its moving drivers from sub-particles: the ratio
        gives fewer than min_per_cell drivers a cell the moving particles occupy."""
        free = ~np.asarray(self.static, bool)
        if min_per_cell <= 0 or not free.any():
            return False
        key = (ratio, float(min_per_cell))
        if key not in self._floor:
            have = driver_count(torch.as_tensor(np.asarray(self.positions_sim)[free]), self.dx, ratio=ratio)
            self._floor[key] = have < min_per_cell * self.moving_cells()
        return self._floor[key]

    def build_drivers(self, *, ratio: float | None, seed: int = 0, device: str | torch.device = "cpu",
                      min_per_cell: float = 0.0):
        """Driving particles (pd_tool.drivers.DriverSet) over every simulated particle,
        clustered on `device` (K-Means with a driver per Gaussian is slow on a CPU).

        ratio: drivers per particle (None: MIN_PER_CELL a cell). min_per_cell: a floor of
        moving drivers a cell the moving particles occupy; where the ratio gives fewer,
        the drivers are clustered from sub-particles sampling each Gaussian's extent
        (pd_tool.prepare.split.split_drivers), since MPM particles a cell apart separate
        under a push. 0: no floor (the fit's own discretisation).
        """
        if self.splits(ratio, min_per_cell):
            return split_drivers(self.scene, self, per_cell=int(math.ceil(min_per_cell)), seed=seed, device=device,
                                 sub=self.sub_particles())

        def t(a, dtype=torch.float32):
            return torch.as_tensor(a, dtype=dtype, device=device)

        return build_drivers(t(self.positions_sim), t(self.volumes), t(self.masses), t(self.static, torch.bool),
                             self.dx, ratio=ratio, seed=seed)

    @property
    def object_size_m(self) -> float:
        """Longest extent of the simulated Gaussians in metres."""
        return float(extent(self.positions_sim).max())


# ----------------------------------------------------------------------------- steps
def select_foreground(scene: GaussianScene, options: PrepareOptions) -> tuple[np.ndarray, list[str]]:
    """Indices [F] of the Gaussians to simulate, and report lines saying why others were left out."""
    pos = scene.positions.detach().cpu().double().numpy()
    keep = np.ones(len(pos), bool)
    report = []
    if options.foreground_box is not None:
        keep &= Box.parse(options.foreground_box, "--foreground-box").contains(pos)
        report.append(f"foreground box keeps {int(keep.sum()):,} of {len(pos):,} Gaussians")
    if options.min_opacity > 0:
        opaque = scene.opacities.detach().cpu().numpy() >= options.min_opacity
        report.append(f"opacity >= {options.min_opacity:g} drops {int((keep & ~opaque).sum()):,}")
        keep &= opaque
    if options.remove_outliers and keep.sum() > 0:
        idx = np.flatnonzero(keep)
        out = select_outliers(pos[idx], options.outlier_min_neighbors, device=scene.device)
        keep[idx[out]] = False
        report.append(f"outlier removal drops {int(out.sum()):,}")
    if not keep.any():
        raise PreparationError(
            "the foreground selection keeps no Gaussians; widen --foreground-box or lower --min-opacity "
            "(see `pdtool info` for the scene's bounding box)"
        )
    return np.flatnonzero(keep), report


PIN_MOST = 0.9  # pinning more of the object than this leaves nothing to move: warn


def parse_fraction(value: float | str) -> float | None:
    """0.15 for "15%", None for a coordinate."""
    if isinstance(value, str) and value.strip().endswith("%"):
        return float(value.strip()[:-1]) / 100.0
    return None


def static_selection(positions_scene: np.ndarray, options: PrepareOptions) -> tuple[np.ndarray, list[str]]:
    """Mask [F] of the Gaussians that stay fixed (Dirichlet cells in the simulator), and
    report lines: what --pin auto found, and a `warning:` line when a pin option pins
    nothing or more than PIN_MOST of the object. options.up_axis is resolved (not auto)."""

    static = np.zeros(len(positions_scene), bool)
    lines: list[str] = []
    flags = []
    if options.static_box is not None:
        static |= Box.parse(options.static_box, "--static-box").contains(positions_scene)
        flags.append("--static-box " + ",".join(f"{v:g}" for v in options.static_box))
    h = positions_scene @ direction(options.up_axis) if len(positions_scene) else np.zeros(0)
    bottom, top = (float(h.min()), float(h.max())) if len(h) else (0.0, 0.0)
    if options.static_below is not None:
        frac = parse_fraction(options.static_below)
        below = bottom + frac * (top - bottom) if frac is not None else float(options.static_below)
        static |= h < below
        flags.append(f"--static-below {options.static_below}")
    if options.pin == "auto" and len(h):
        horiz = positions_scene[:, [b for b in range(3) if b != "xyz".index(options.up_axis[1])]]
        base = find_base(h, horiz)
        pinned = h < base.top
        static |= pinned
        flags.append("--pin auto")
        what = (f"the base below where the shape narrows to {100 * base.narrow_to:.0f}% of its width"
                if base.kind == "base" else "the contact slab (no narrowing above the bottom)")
        lines.append(f"pin auto: {int(pinned.sum()):,} Gaussians ({100 * pinned.mean():.1f}%), heights "
                     f"{base.bottom:.4g} to {base.top:.4g} along {options.up_axis} (bottom +0 to "
                     f"+{base.top - base.bottom:.4g}, {100 * (base.top - base.bottom) / max(top - bottom, 1e-300):.0f}% "
                     f"of the height): {what}")
    elif options.pin is not None and options.pin != "auto":
        raise PreparationError(f"--pin {options.pin!r}: the only value is auto")
    if flags and len(h):
        n, share = int(static.sum()), float(static.mean())
        named = " with ".join(flags)
        span = f"the object spans heights {bottom:.4g} to {top:.4g} along {options.up_axis}"
        if n == 0:
            lines.append(f"warning: {named} pins nothing: {span}; a height is a coordinate along the up axis "
                         f"(or give a percentage, --static-below 15%, or --pin auto)")
        elif share > PIN_MOST:
            lines.append(f"warning: {named} pins {100 * share:.1f}% of the object ({n:,} of {len(h):,} Gaussians), "
                         f"which leaves little to move: {span}; give a lower height, a percentage "
                         f"(--static-below 15%) or --pin auto")
    return static, lines


def select_static(positions_scene: np.ndarray, options: PrepareOptions) -> np.ndarray:
    """Mask [F] of Gaussians that stay fixed (Dirichlet cells in the simulator)."""
    return static_selection(positions_scene, options)[0]


def cell_size(longest_m: float, padding: float, grid_res: int) -> tuple[float, float]:
    """(dx, padding) in metres of a grid of `grid_res` cells along the longest side around
    an object `longest_m` long, `padding` of it free on each side."""
    pad_m = padding * longest_m
    dx = (longest_m + 2 * pad_m) / (grid_res - 2 * WALL_CELLS)
    if pad_m < dx:
        # The solver keeps particles half a cell off its walls; with (nearly) no padding the
        # object's faces would sit on them. Keep at least one free cell around the object.
        dx = longest_m / (grid_res - 2 * WALL_CELLS - 2)
        pad_m = dx
    return dx, pad_m


def fit_transform(positions_scene: np.ndarray, options: PrepareOptions) -> tuple[SimTransform, float, tuple[int, int, int]]:
    """Map the object into a simulation box that covers only its bounds plus padding.

    Returns the transform, the grid spacing dx (metres) and the grid size in cells.
    The longest axis gets options.grid_res cells; WALL_CELLS of them at each face are
    kept free for the solver's walls.
    """
    R = up_rotation(options.up_axis)
    rotated = positions_scene @ R.T
    lo, hi = bounds(rotated)
    sides = hi - lo
    longest = float(sides.max())
    if not math.isfinite(longest) or longest <= 0:
        raise PreparationError("the foreground has zero extent (a single point?); select more Gaussians")
    mpu = options.meters_per_unit or DEFAULT_OBJECT_SIZE_M / longest
    if not (mpu > 0 and math.isfinite(mpu)):
        raise PreparationError(f"--meters-per-unit {options.meters_per_unit} must be a positive number")
    lo_m, hi_m = OBJECT_SIZE_RANGE_M
    if not lo_m <= longest * mpu <= hi_m:
        raise PreparationError(
            f"--meters-per-unit {mpu:g} makes the object {longest * mpu:.3g} m long; pdtool simulates objects "
            f"of {lo_m:g} m to {hi_m:g} m: give --meters-per-unit between {lo_m / longest:.3g} and "
            f"{hi_m / longest:.3g}, or leave it out (the object is then 1 m long)")
    res = int(options.grid_res)
    if res < 2 * WALL_CELLS + 4:
        raise PreparationError(f"grid resolution {res} is too small; use at least {2 * WALL_CELLS + 4}")
    longest_m = longest * mpu
    dx, pad_m = cell_size(longest_m, options.padding, res)
    dims = tuple(int(math.ceil((e * mpu + 2 * pad_m) / dx - 1e-9)) + 2 * WALL_CELLS for e in sides)
    dims = tuple(max(d, 2 * WALL_CELLS + 2) for d in dims)
    # centre the object in the box
    box = np.array(dims, np.float64) * dx
    shift = box / 2 - mpu * (lo + hi) / 2
    return SimTransform(tuple(map(tuple, R.tolist())), float(mpu), tuple(shift.tolist())), float(dx), dims


# Scanned Gaussians stand for a surface: each weighs its share of a shell SHELL_GRID-th of
# the object's longest side thick, whatever the simulation grid (192: the convergence
# benchmark's reference grid, where the shell is about a cell thick). Shared out per grid
# cell instead, a scan weighs one cell thick, so its mass and stiffness move with the grid
# (the tree: 36 kg at 64 cells, 21 kg at 192) and coarse grids miss the reference by 17-25%.
SHELL_GRID = 192
# The shell's area is counted on cells (a^2 per occupied cell) coarse enough that all but
# SPARSE_SHARE of the scanned Gaussians share their cell with SURFACE_PER_CELL - 1 others, so
# that a patch's mass follows its area rather than how densely the capture sampled it. An
# average instead would let a crowded patch pick cells so fine that a sparse one leaves
# holes between its samples, and lose their area (a sheet 8x as dense in one corner: 7%).
SURFACE_PER_CELL = 4
SPARSE_SHARE = 0.1
AREA_CELL_STEP = 1.25  # the area cell grows by this factor until it is coarse enough


def surface_volumes(positions: np.ndarray, device: Device = "cpu") -> np.ndarray:
    """Per-Gaussian volume [N] m^3 of scanned Gaussians at `positions` [N, 3] m: a shell of
    thickness t = longest side / SHELL_GRID over the area their cells of edge a cover, a^2
    per occupied cell; a >= t is the finest that SURFACE_PER_CELL and SPARSE_SHARE allow.
    Each Gaussian weighs t a^2 times its cell's 3x3x3 block's occupied cells over the
    Gaussians in that block, so a partly full cell at a part's edge or face weighs its
    Gaussians like its neighbours do. The cells sit on the Gaussians' own bounding box, so
    the volumes do not depend on the simulation grid. The cells are sorted on `device`."""
    x = np.asarray(positions, np.float64)
    if len(x) == 0:
        return np.zeros(0)
    x = x - bounds(x)[0]
    longest = float(x.max())
    if not longest > 0.0:  # a single point: nothing to spread over
        return np.full(len(x), 1.0 / len(x))
    t = a = longest / SHELL_GRID
    xt = torch.as_tensor(x, device=device)
    while True:
        cells, inverse, counts, _ = unique_rows(torch.floor(xt / a).long())
        if np.quantile(counts[inverse].cpu().numpy(), SPARSE_SHARE) >= SURFACE_PER_CELL or a >= longest:
            break
        a *= AREA_CELL_STEP
    block = block_sums(cells, torch.stack([torch.ones_like(counts), counts], 1).double())
    return (t * a * a * (block[:, 0] / block[:, 1])[inverse]).cpu().numpy()


# The interior of a closed scan is found on the cells of a grid this fine, whatever the
# simulation's grid: found on the simulation's own cells, the tree was hollow at 32 and 48
# cells and filled from 64, and its filled volume moved by a quarter between grids.
FILL_GRID = 128


@dataclass
class GridFree:
    """What a preparation finds that does not depend on its grid, so that a preparation of
    the same scene on another grid takes it over (prepare_scene(reuse=)): the foreground
    [F] and static mask [F] with their report lines, the interior fill as found and the
    object's corner [3] m it was found from (None with --fill off), and the scanned
    Gaussians' volumes [F] m^3 (surface_volumes works on the Gaussians' own box)."""

    options: PrepareOptions  # up axis resolved; the grid is not compared
    foreground: np.ndarray
    static: np.ndarray
    report: list[str]
    fill: Any
    corner: np.ndarray | None
    scanned_volumes: np.ndarray

    def serves(self, scene: GaussianScene, options: PrepareOptions, prep: PreparedScene) -> bool:
        return prep.scene is scene and replace(self.options, grid_res=options.grid_res) == options


def prepare_scene(scene: GaussianScene, options: PrepareOptions | None = None, *,
                  reuse: PreparedScene | None = None) -> PreparedScene:
    """Select, fix, map and weigh the Gaussians of `scene` for simulation. reuse: a
    preparation of the same scene with the same options on another grid, whose
    grid-independent parts (GridFree: foreground, pins, interior fill, scanned volumes)
    are taken over instead of found again: at 300k Gaussians, two thirds of the time."""
    options = options or PrepareOptions()
    if options.density_kg_m3 <= 0 or not math.isfinite(options.density_kg_m3):
        raise PreparationError(f"density {options.density_kg_m3} must be a positive number of kg/m^3")
    if options.fill not in ("auto", "on", "off"):
        raise PreparationError(f"--fill {options.fill!r} must be auto, on or off")
    if options.up_axis == "auto" and reuse is not None:
        options = replace(options, up_axis=reuse.options.up_axis)  # resolved there
    free = reuse.grid_free if reuse is not None and reuse.grid_free is not None else None
    if free is not None and not free.serves(scene, options, reuse):
        free = None
    if free is None:
        free = _grid_free(scene, options)
    options = free.options.updated(grid_res=options.grid_res)
    fg, static, report = free.foreground, free.static, list(free.report)
    pos_scene = scene.positions.detach().cpu().double().numpy()[fg]
    transform, dx, dims = fit_transform(pos_scene, options)
    pos_sim = transform.to_sim(pos_scene)
    fill_source, filled = None, np.zeros(0)
    res = free.fill
    if res is not None:
        # found on FILL_GRID's cells, set on the object's own corner, whatever this grid;
        # then moved to this grid's corner and sampled at its density
        corner, far = bounds(pos_sim)
        cell = cell_size(float((far - corner).max()), options.padding, FILL_GRID)[0]
        if res.decision and len(res.points):
            points, fill_source, filled = resample_fill(res.points - free.corner + corner, res.source,
                                                        res.interior_volume, cell / PARTICLES_PER_CELL_AXIS,
                                                        dx / PARTICLES_PER_CELL_AXIS, device=scene.device)
            pos_sim = np.concatenate([pos_sim, points])
            static = np.concatenate([static, static[fill_source]])
            report.append(f"fill ({options.fill}): filled {len(points):,} interior particles "
                          f"({res.interior_volume:.3g} m^3): {res.reason.partition('): ')[2]}")
        else:
            report.append(f"fill ({options.fill}): {res.reason}")
    volumes = np.concatenate([free.scanned_volumes, filled])
    report.append(
        f"{len(fg):,} Gaussians simulated ({int(static.sum()):,} static) in a "
        f"{dims[0]}x{dims[1]}x{dims[2]} grid, dx {dx * 100:.3g} cm, object {extent(pos_sim).max():.3g} m"
    )

    thin = thin_parts(pos_sim, ~static, dx, max(dims), volumes, device=scene.device)
    if thin is not None and thin.thin:
        report.append(thin.line(max(dims)))
    prep = PreparedScene(
        scene=scene, options=options, foreground=fg, static=static, transform=transform,
        positions_sim=pos_sim, volumes=volumes, masses=volumes * options.density_kg_m3,
        dx=dx, grid_dims=dims, report=report, fill_source=fill_source, thin=thin, grid_free=free,
    )
    if static.any() and (~static).any():
        apart = prep.detached_share()
        if apart >= DETACHED_NOTE:
            report.append(f"loose parts: {apart:.0%} of the moving particles are a cell or more apart from the "
                          f"pinned ones on this grid, so a push carries them off as loose pieces; pin them "
                          f"(--static-box) or leave them out (--foreground-box)")
    if scene.device.type == "cuda":
        # the passes' blocks go back to the device: the solver allocates through warp, outside
        # torch's cache
        torch.cuda.empty_cache()
    return prep


def _warp_device(device: torch.device) -> str:
    """Where warp runs a scene's preparation kernels: its CUDA device, else the CPU."""
    return str(device) if device.type == "cuda" else "cpu"


def _grid_free(scene: GaussianScene, options: PrepareOptions) -> GridFree:
    """The grid-independent parts of preparing `scene` (GridFree), found."""
    if options.up_axis == "auto":
        up, guess = resolve_up(scene.positions.detach().cpu().double().numpy(),
                               "auto", scene.scales.detach().cpu().double().numpy(),
                               scene.opacities.detach().cpu().double().numpy())
        # resolved here, so that a fit stores the axis it simulated with
        options = replace(options, up_axis=up)
        up_report = [up_line(guess)]
    else:
        up_report = []
    fg, report = select_foreground(scene, options)
    report = up_report + report
    pos_scene = scene.positions.detach().cpu().double().numpy()[fg]
    static, static_report = static_selection(pos_scene, options)
    report += static_report
    transform = fit_transform(pos_scene, options)[0]
    pos_sim = transform.to_sim(pos_scene)
    res, corner = None, None
    scanned = surface_volumes(pos_sim, scene.device)
    if options.fill != "off":
        fg_t = torch.as_tensor(fg, device=scene.device)
        corner, far = bounds(pos_sim)
        cell = cell_size(float((far - corner).max()), options.padding, FILL_GRID)[0]
        res = fill_interior(pos_sim, scene.quats[fg_t].detach().cpu().numpy(),
                            scene.scales[fg_t].detach().cpu().numpy() * transform.scale,
                            scene.opacities[fg_t].detach().cpu().numpy(), cell=cell, mode=options.fill,
                            grid_origin=corner, device=_warp_device(scene.device))
    return GridFree(options=options, foreground=fg, static=static, report=report, fill=res, corner=corner,
                    scanned_volumes=scanned)


# the share of the moving particles held apart from the static ones
# (PreparedScene.detached_share) from which preparation says so
DETACHED_NOTE = 0.02


# A finer grid for thin parts only where the particles still fill it: the convergence
# benchmark's 192- and 256-cell runs of the thin plant agree within 2% at 9.8 and 5.2
# particles per occupied cell, and differ by 14% at 4.2 and 2.8; a 3,000-Gaussian plant on
# 64 cells (2.8) moved a third further than on 48 (4.8).
MIN_PARTICLES_PER_CELL = 4.0
# A bake's floor of moving drivers in each cell its moving particles occupy
# (PreparedScene.build_drivers): the paper's 8. Against a converged reference, a
# 3,000-Gaussian plant on 48 cells moved 2.4% of its size off with 2.6 drivers a cell
# clustered from its Gaussians and 0.17% with 8 a cell clustered from sub-particles.
MIN_DRIVERS_PER_CELL = 8.0
# a finer grid may hold at most this much more of the moving particles apart from the static
# ones than the quality's grid does (PreparedScene.detached_share)
MAX_MORE_DETACHED = 0.01


def refine_for_thin(prep: PreparedScene, max_grid_res: int) -> PreparedScene | None:
    """`prep` prepared again on a finer grid that resolves its thin moving parts, at most
    `max_grid_res` cells along the longest side; None when it has no thin parts or the grid
    cannot grow.

    The grid is the one ThinParts.grid_needed asks for, rounded up to a multiple of 16 (the
    benchmark's plant with 3 mm leaves asks for 123-135 cells and moves as the converged
    reference does at 128: docs/benchmarks.md, "Convergence against a fine reference").
    The grid stops where fewer than MIN_PARTICLES_PER_CELL particles fill an occupied cell,
    and where its cells would hold more of the moving particles apart from the static ones
    than the quality's grid does (a gap wider than a cell between a part and its support:
    PreparedScene.detached_share). The new preparation's report ends with one line that
    says what was raised and why; a scene that no finer grid suits gets a line in
    `prep.report` saying why.
    """

    thin, grid = prep.thin, int(prep.options.grid_res)
    if thin is None or not thin.thin or max_grid_res <= grid:
        return None
    asked = min(int(max_grid_res), 16 * math.ceil(thin.grid_needed / 16))
    target = asked
    # a grid finer than the particles fill resolves nothing: keep MIN_PARTICLES_PER_CELL;
    # and one whose cells open gaps between parts that the quality's grid holds together
    # would let those parts fly off
    longest = float(extent(prep.positions_sim[: prep.count]).max())
    most_apart = prep.detached_share() + MAX_MORE_DETACHED
    stop, apart, finer = "", 0.0, None  # stop: why the last grid tried was refused
    while target > grid:
        dx = cell_size(longest, prep.options.padding, target)[0]
        if prep.n_particles < MIN_PARTICLES_PER_CELL * prep.occupied_cells(dx):
            stop = "sparse"
        else:
            stop, apart = "apart", prep.detached_share(dx)  # on cells of dx, not yet the finer box's
            if apart <= most_apart:
                finer = prepare_scene(prep.scene, replace(prep.options, grid_res=target), reuse=prep)
                apart = finer.detached_share()  # where its own cells fall
                if apart <= most_apart:
                    break
                finer = None
        target -= 16
    if finer is None:
        if stop == "sparse":
            prep.report.append(f"thin parts: kept the {grid}-cell grid: {prep.n_particles:,} particles are too few "
                               f"to fill a finer one ({MIN_PARTICLES_PER_CELL:g} per occupied cell), so only a "
                               f"denser capture would resolve them")
        elif stop == "apart":
            prep.report.append(f"thin parts: kept the {grid}-cell grid: a finer one leaves {apart:.0%} of the moving "
                               f"particles a cell or more apart from the pinned ones, and they would fly off; close "
                               f"the gap in the scene, or pin or crop the floating part (--static-box, "
                               f"--foreground-box)")
        return None
    still = finer.thin is not None and finer.thin.thin
    if still:  # one line says it all: drop the finer grid's own notice
        finer.report.remove(finer.thin.line(max(finer.grid_dims)))
    finer.report.append(describe_refinement(thin, grid, finer.thin if still else None, max(finer.grid_dims),
                                            finer.dx))
    return finer

