"""Bake: simulate a prepared object under a force and stream the animation to USD and the
splat formats of `--format`.

Data flow: scene -> prepare (foreground, static, simulation box) -> driving particles ->
(a fitted material on another discretisation than its fit's: E matched to the fit's
motion, pd_tool.bake.transfer) -> fast MPM (no tape) -> per frame: rigid interpolation to
every Gaussian -> scene units -> every output (pd_tool.bake.outputs: usd_export and pd_tool.io's writers; streamed, atomic). Frames after the object is at rest again are held (no
simulation, no new samples), see REST_*.
"""
from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from pd_tool.bake.animate import GaussianAnimator
from pd_tool.bake.outputs import FrameOutputs, open_splat_writers
from pd_tool.bake.transfer import MAX_RUNS, Discretisation, MotionMatch, match_fit_motion, window_frames
from pd_tool.core.arrays import bounds, extent
from pd_tool.core.atomic import check_destination, check_own_file, check_outputs, check_replaceable_folder
from pd_tool.core.cameras import Camera
from pd_tool.core.errors import OutputError, PdToolError, PreparationError
from pd_tool.core.quaternion import matrix_to_quat
from pd_tool.core.scene import GaussianScene
from pd_tool.io.formats import FORMATS, output_paths
from pd_tool.materials.file import MaterialFile
from pd_tool.materials.presets import Material, load_preset
from pd_tool.prepare import work
from pd_tool.prepare.memory import PREVIEW_PIXELS, InsufficientMemory, check_memory, estimate_bake_memory
from pd_tool.prepare.preparation import (MIN_DRIVERS_PER_CELL, WALL_CELLS, Box, PreparedScene, PrepareOptions,
                                         prepare_scene, refine_for_thin, up_rotation)
from pd_tool.prepare.work import WorkTooLarge
from pd_tool.render.preview import PREVIEW_SUFFIXES, PreviewError, write_preview
from pd_tool.render.views import render_image, scene_camera
from pd_tool.sim import MPMSolver, SimConfig
from pd_tool.sim.guard import check_force
from pd_tool.video.folder import write_video_folder

# The fitted-material match measures at most this many of the moving Gaussians, each moved by
# its drivers as the bake moves it: a seeded sample, the same Gaussians on both
# discretisations. 2,000 of them above the 99th percentile hold it steady; a run keeps
# their displacements (25 MB for 1 s at 30 fps).
MATCH_GAUSSIANS = 200_000

# usd_export is imported where it is used: pxr takes seconds to load, and pd_tool.app imports
# this module for fits too, which never write USD.

# The object is at rest again when its kinetic energy has stayed below REST_FRACTION of
# the peak (after the force ended) for REST_FRAMES frames in a row.
REST_FRACTION = 1e-4
REST_FRAMES = 10
FORCE_UNITS = ("size", "g", "scene")
STANDARD_GRAVITY = 9.80665  # m/s^2: one g of --force
DEFAULT_DURATION_S = 0.25  # force duration when neither --duration nor an interaction says


class ForceRegionError(PdToolError):
    """The force's region selects no free particle."""


@dataclass
class ForceSpec:
    """An acceleration applied to a region for a time window.

    accel: (3,) along the scene's axes, in `units`: "size" (the object's longest side per s^2:
    a free object pushed for 0.25 s travels 3% of its size per unit, on any capture), "g"
    (9.80665 m/s^2 at the simulated size: --meters-per-unit, or the longest side 1 m), or
    "scene" (scene units / s^2, which depend on the capture's scale). at: a point (scene units), "top" (the free particle
    highest along up) or None (every free particle). radius: scene units (with a point or
    "top"); radius_fraction: the radius as a fraction of the object's longest side, used
    when radius is None. box: x0,y0,z0,x1,y1,z1 in scene units instead of at/radius.
    start, duration: seconds.
    """

    accel: tuple[float, float, float]
    at: tuple[float, float, float] | str | None = None
    radius: float | None = None
    radius_fraction: float = 0.15
    box: tuple[float, ...] | None = None
    start: float = 0.0
    duration: float = DEFAULT_DURATION_S
    magnitude: float = 1.0  # accel / --force: a force preset's factor, to quote limits in --force's units
    units: str = "scene"  # the library's numbers are scene units; the CLI's --force defaults to g

    def __post_init__(self) -> None:
        if self.units not in FORCE_UNITS:
            raise ValueError(f"force units must be one of {', '.join(FORCE_UNITS)}, not {self.units!r}")

    def unit_m_s2(self, prep: PreparedScene) -> float:
        """m/s^2 of one unit of accel in the simulation of `prep`."""
        if self.units == "size":
            return prep.object_size_m
        return STANDARD_GRAVITY if self.units == "g" else float(prep.transform.scale)

    def accel_sim(self, prep: PreparedScene) -> np.ndarray:
        """The acceleration [3] in m/s^2 along the simulation's axes."""
        return self.unit_m_s2(prep) * (np.asarray(self.accel, np.float64) @ prep.transform.R.T)

    def unit_name(self) -> str:
        return {"size": "object sizes/s^2", "g": "g", "scene": "scene units/s^2"}[self.units]

    @classmethod
    def from_interaction(cls, name_or_path: str | Path, accel: tuple[float, float, float], units: str = "scene",
                         **overrides: Any) -> "ForceSpec":
        """A force preset (poke, gust, drag or a TOML file) scaled by accel, then overrides."""
        p = load_preset("forces", name_or_path)
        at = None if p["at"] == "all" else p["at"]
        spec = cls(accel=tuple(float(a) * p["magnitude"] for a in accel), at=at,
                   radius_fraction=p["radius"], start=p["start"], duration=p["duration"],
                   magnitude=float(p["magnitude"]) or 1.0, units=units)
        for k, v in overrides.items():
            if v is not None:
                setattr(spec, k, v)
        return spec


@dataclass
class BakeSettings:
    """How to bake. seconds and fps set the frame count (frames = round(seconds * fps) + 1,
    frame 0 being the rest state)."""

    seconds: float = 2.0
    fps: float = 30.0
    # Quality preset (grid, CFL safety, driver ratio). None: with a fitted material, simulate
    # as the fit did (its E is calibrated to that grid and driver count: at the plant's scale
    # a 16-cell grid moves the true E about as far from its 32-cell motion as the uniform
    # baseline is; docs/benchmarks.md); with a preset material, "default".
    quality: str | Path | None = None
    fmt: str | None = "both"  # the USD file's content: instancer | splat | both; None: no USD file
    splat_formats: tuple[str, ...] = ()  # ply-seq, spz-seq, gltf (pd_tool.bake.outputs), in the same pass
    device: str = "cpu"
    gravity: bool = False  # the scan is already in equilibrium under gravity
    substeps: int | None = None  # None: CFL
    driver_ratio: float | None = None  # None: from the quality preset
    seed: int = 0
    stop_at_rest: bool = True
    # raise the grid, up to the quality's thin_grid_res, when moving parts are thinner than
    # its grid resolves (pd_tool.prepare.preparation.refine_for_thin); never for a fitted material
    # simulated as its fit was
    refine_thin: bool = True
    # a fitted material baked on another discretisation than its fit's (--quality): scale its
    # E by one factor so that the bake swings as the fit did under this force
    # (pd_tool.bake.transfer); off: the fitted E as it is, which moves differently where
    # parts are thin
    match_fit: bool = True

    @property
    def frames(self) -> int:
        return int(round(self.seconds * self.fps)) + 1


@dataclass
class BakeResult:
    out: Path  # the first output: the USD file, or the one splat output
    frames: int
    simulated_frames: int
    substeps_per_frame: int
    gaussians: int
    drivers: int
    seconds_elapsed: float
    bytes_written: int
    peak_displacement: float  # scene units, over all Gaussians and frames
    object_size: float  # the simulated Gaussians' longest extent, scene units
    displacement_per_frame: list[float] = field(default_factory=list)  # max |x - x0| per frame, scene units
    # seconds: setup, simulate, interpolate, write (close included), close (the last save,
    # the validation, the move into place), total
    timings: dict[str, float] = field(default_factory=dict)
    # seconds of setup by part: prepare (cleaning, volumes, the grid), grid (thin parts and
    # the cost checks), match (a fitted E carried to this discretisation), drivers (K-Means
    # and nearest drivers), solver, outputs (the animator and the writers)
    setup_parts: dict[str, float] = field(default_factory=dict)
    report: list[str] = field(default_factory=list)
    outputs: dict[str, Path] = field(default_factory=dict)  # format ('usd', 'ply-seq', ...) -> path
    output_bytes: dict[str, int] = field(default_factory=dict)  # format -> bytes written
    output_seconds: dict[str, float] = field(default_factory=dict)  # format -> seconds spent writing it
    work_estimate: work.WorkEstimate | None = None  # the whole run's, the match's runs included
    memory_estimate: Any = None  # pd_tool.prepare.memory.MemoryEstimate of the discretisation baked


def _with_match(before: work.WorkEstimate, after: work.WorkEstimate, frames: int,
                match_frames: int) -> work.WorkEstimate:
    """The whole bake's estimate: the match's runs as estimated before it (at the fitted E,
    their share of `before`'s simulated frames), then the frames at the matched E (`after`)."""
    match_s = before.terms.get("simulate", 0.0) * match_frames / max(frames + match_frames - 1, 1)
    return replace(after, seconds=after.seconds + match_s, terms={**after.terms, "match": match_s})


def force_mask(prep: PreparedScene, drivers_rest: np.ndarray, drivers_static: np.ndarray, spec: ForceSpec) -> np.ndarray:
    """Which driving particles [Q] the force pushes."""
    free = ~drivers_static
    tr = prep.transform
    if spec.box is not None:
        box = Box.parse(spec.box, "--box")
        mask = box.contains(tr.to_scene(drivers_rest)) & free
        where = f"box {spec.box}"
    elif spec.at is None:
        mask = free.copy()
        where = "the whole object"
    else:
        if isinstance(spec.at, str):
            if spec.at != "top":
                raise ForceRegionError(f"force position '{spec.at}' is not a point x,y,z or 'top'")
            if not free.any():
                raise ForceRegionError("every particle is static, so nothing can move; shrink the static region")
            centre = drivers_rest[free][np.argmax(drivers_rest[free][:, 2])]
        else:
            centre = tr.to_sim(np.asarray(spec.at, np.float64)[None])[0]
        radius_m = (spec.radius * tr.scale) if spec.radius is not None else spec.radius_fraction * prep.object_size_m
        mask = (np.linalg.norm(drivers_rest - centre, axis=1) <= radius_m) & free
        where = f"within {radius_m / tr.scale:.3g} scene units of {np.round(tr.to_scene(centre[None])[0], 4).tolist()}"
    if not mask.any():
        raise ForceRegionError(
            f"the force region ({where}) holds no free particle; move --at onto the object, "
            f"enlarge --radius, or check the static region"
        )
    return mask


def _free_space(prep: PreparedScene) -> float:
    """Least distance, m, between the simulated particles' bounding box and the grid cells
    the solver keeps for its walls, over the three axes."""
    p_lo, p_hi = bounds(prep.positions_sim)
    lo = p_lo - WALL_CELLS * prep.dx
    hi = np.asarray(prep.domain) - WALL_CELLS * prep.dx - p_hi
    return float(max(min(lo.min(), hi.min()), prep.dx))


def usd_frame(up: str) -> tuple[np.ndarray, str]:
    """Rotation [3, 3] from scene axes to the USD file's axes (x_usd = R @ x_scene) for a
    scene whose up axis is `up`, and the file's upAxis. +y and +z scenes are written as
    they are; other up axes are rotated so that up is +Z (USD knows only Y, Z)."""
    if up == "+z":
        return np.eye(3), "Z"
    if up == "+y":
        return np.eye(3), "Y"
    return up_rotation(up), "Z"


def check_bake_outputs(
    out: str | Path,
    *,
    preview: str | Path | None = None,
    frames_dir: str | Path | None = None,
    inputs: Mapping[str, str | Path | None] | None = None,
    fmt: str | None = "both",
    splat_formats: tuple[str, ...] = (),
) -> dict[str, Path]:
    """Refuse, before any work, a bake whose outputs cannot be written or would destroy
    something: OUT (and the splat outputs beside it, pd_tool.bake.outputs), --preview and
    --frames-out with names the file system takes, in writable folders; folder outputs
    new, empty or pdtool-made, holding neither another output, an input nor the current
    folder; no output that is an input. Returns {format: path} of the animation outputs.
    inputs: {option: path} of the files the bake reads (--scene, --material, --camera).
    Raises OutputError / PreviewError (one line each)."""
    out = Path(out)
    if fmt is None and not splat_formats:
        raise OutputError("--format names no output; choose from " + ", ".join(FORMATS))
    paths = output_paths(out, fmt, tuple(splat_formats))
    if preview is not None and Path(preview).suffix.lower() not in PREVIEW_SUFFIXES:
        raise PreviewError(f"--preview {preview}: must end in .mp4 or .gif, not '{Path(preview).suffix}'")
    label = {"usd": "OUT"} | {f: ("OUT" if p == out else f"--format {f} output") for f, p in paths.items() if f != "usd"}
    folders = {label[f]: p for f, p in paths.items() if f in ("ply-seq", "spz-seq")}
    files = {label[f]: p for f, p in paths.items() if f not in ("ply-seq", "spz-seq")}
    check_outputs({**files, "--preview": preview}, {**folders, "--frames-out": frames_dir}, inputs or {})
    for name, p in files.items():
        check_destination(p, name)
        if p != out:  # beside OUT, not named by the user: never over someone else's file
            check_own_file(p, f"the {name}")
        if not os.path.isdir(p.parent):
            raise OutputError(f"{p}: folder {p.parent} does not exist; create it or choose another output path",
                              path=p)
    for name, p in folders.items():
        check_destination(p, name, folder=True)
        check_replaceable_folder(p, name)
    if preview is not None:
        check_destination(preview, "--preview")
    if frames_dir is not None:
        check_destination(frames_dir, "--frames-out", folder=True)
        check_replaceable_folder(frames_dir, "--frames-out")
    return paths


class Baker:
    """One bake, in warp's example shape: the constructor prepares everything and opens the
    writers, `step()` writes one frame until `done`, `finish()` publishes the outputs.

    Use it as a context manager: an error or Ctrl-C before `finish()` returns deletes the
    temporaries, so no half-written file ever appears at `out` or beside it. Arguments as
    for `bake`.

    After setup: n_frames, frame_dt (s), substeps (per frame), prep (the PreparedScene that
    is simulated), solver, outputs (pd_tool.bake.outputs.FrameOutputs), paths (format ->
    path). While stepping: frame (the next one step() writes),
    simulated (frames simulated so far), disp (max |x - x0| per written frame, scene
    units), preview_images ([H, W, 3] each) and timings (seconds per stage).
    """

    def __init__(
        self,
        scene: GaussianScene,
        out: str | Path,
        *,
        force: ForceSpec,
        material: Material | None = None,
        material_file: MaterialFile | None = None,
        prepare_options: PrepareOptions | None = None,
        settings: BakeSettings | None = None,
        progress: Callable[[int, int], None] | None = None,
        preview: str | Path | None = None,
        frames_dir: str | Path | None = None,
        camera: Camera | None = None,
        inputs: Mapping[str, str | Path | None] | None = None,
        match_progress: Callable[[int, int], None] | None = None,
    ) -> None:
        self.t_start = time.perf_counter()
        self.scene, self.out, self.force = scene, Path(out), force
        self.settings = settings or BakeSettings()
        self.progress, self.preview, self.frames_dir = progress, preview, frames_dir
        self.match_progress = match_progress  # (runs done, at most) while a fitted E is matched
        self.rendering = preview is not None or frames_dir is not None
        self.frame = 0  # the next frame step() writes
        self.simulated = 0
        self.disp: list[float] = []  # max |x - x0| per frame, scene units
        self.preview_images: list[np.ndarray] = []
        self._peak_ke = 0.0
        self._calm = 0
        self._closed = False
        self.setup(material, material_file, prepare_options, camera, inputs)

    # ---- setup

    def setup(self, material: Material | None, material_file: MaterialFile | None,
              prepare_options: PrepareOptions | None, camera: Camera | None,
              inputs: Mapping[str, str | Path | None] | None) -> None:
        """Check the outputs, prepare the scene, pick its grid (finer for thin parts when
        time and memory allow), build drivers, solver and force, then open the writers."""
        read = {"--scene": getattr(self.scene, "source", None), **(inputs or {})}
        self.paths = check_bake_outputs(self.out, preview=self.preview, frames_dir=self.frames_dir, inputs=read,
                                        fmt=self.settings.fmt, splat_formats=self.settings.splat_formats)
        self.setup_parts: dict[str, float] = {}
        with self._part("prepare"):
            self._prepare(material, material_file, prepare_options, camera)
        with self._part("grid"):
            self._choose_grid()
        self._build_simulation(material, material_file)
        with self._part("outputs"):
            self._open_outputs(camera)
        self.timings = {"setup": time.perf_counter() - self.t_start, "simulate": 0.0, "interpolate": 0.0,
                        "write": 0.0}

    @contextmanager
    def _part(self, name: str):
        """Add the block's seconds to setup_parts[name]; on CUDA the queued work is waited
        for first, so that each part is charged its own kernels."""
        t = time.perf_counter()
        yield
        if str(getattr(self, "dev", "cpu")).startswith("cuda"):  # dev is set within the first part
            torch.cuda.synchronize()
        self.setup_parts[name] = self.setup_parts.get(name, 0.0) + time.perf_counter() - t

    def _prepare(self, material: Material | None, material_file: MaterialFile | None,
                 prepare_options: PrepareOptions | None, camera: Camera | None) -> None:
        """Material constants, discretisation and the prepared scene (simulation box, m)."""
        s, scene = self.settings, self.scene
        if material is None and material_file is None:
            raise PreparationError("bake needs a material: pass --preset NAME or --material FILE")
        opts = prepare_options or PrepareOptions()
        (grid, self.thin_grid, self.cfl_safety, quality_ratio, self.seed, self.follows_fit,
         self.sim_note) = _discretisation(s, material_file)
        opts.grid_res = grid
        self.fit_sim = material_file.fit_simulation() if material_file is not None else None
        mat = material if material is not None else material_file
        self.nu, self.damping = mat.nu, mat.damping
        opts.density_kg_m3 = mat.density
        flat = ~(scene.scales > 0).all(dim=1).cpu().numpy()
        if flat.any():  # USD needs a positive size; found here, the message can name the user's file
            raise PreparationError(
                f"{scene.source or 'the scene'}: {int(flat.sum())} Gaussians have a size of 0 (a scale_* log-scale "
                f"below about -100), first at index {int(np.flatnonzero(flat)[0])}; remove them in your splat "
                f"editor or export the scene again")
        self.opts = opts
        self.prep = prepare_scene(scene, opts)
        self.dev = s.device
        self.frame_dt = 1.0 / s.fps
        self.n_frames = s.frames
        self.ratio = s.driver_ratio if s.driver_ratio is not None else quality_ratio
        # a floor of drivers a cell: the fit's when the bake simulates as its fit did, none when the
        # ratio is given, else the quality's
        if self.follows_fit:
            self.min_per_cell = float(self.fit_sim["min_per_cell"])
        else:
            self.min_per_cell = 0.0 if s.driver_ratio is not None else float(
                load_preset("quality", s.quality or "default").get("min_drivers_per_cell", MIN_DRIVERS_PER_CELL))
        self.preview_pixels = 0 if not self.rendering else (
            camera.width * camera.height if camera is not None else PREVIEW_PIXELS)
        self.E_top = float(material.E) if material is not None else float(np.max(material_file.driver_E))
        self.push_s = min(self.force.duration, max(s.seconds - self.force.start, 0.0))
        self.match: MotionMatch | None = None  # the fitted material's match, once made
        self.drivers_note = ""  # why the drivers were clustered from sub-particles, when they were
        self.work_estimate: work.WorkEstimate | None = None  # the chosen discretisation's, once checked

    def _choose_grid(self) -> None:
        """Raise the grid for thin parts unless the finer run would not fit in memory or
        time; then the quality's own grid is baked, and the report says why."""
        prep, ratio = self.prep, self.ratio
        finer = refine_for_thin(prep, self.thin_grid) if self.settings.refine_thin and self.thin_grid else None
        if finer is not None:
            why = None
            try:
                self._check_cost(finer, ratio)
            except InsufficientMemory:
                why = "need more memory than is available"
            except WorkTooLarge:
                why = "take longer than --max-minutes allows"
            if why is None:
                prep = finer
            else:
                prep.report.append(f"thin parts: kept the {max(prep.grid_dims)}-cell grid; {max(finer.grid_dims)} "
                                   f"cells would {why} (raise --max-minutes, or use --device cuda)")
        if prep is not finer:
            self._check_cost(prep, ratio)
        self.prep = prep

    def _check_cost(self, p: PreparedScene, ratio: float) -> None:
        """Refuse before drivers and simulator a run that cannot fit in memory or would take
        longer than allowed (substeps from the CFL rule at the stiffest material and the
        speed the force can give); keep the estimate as `work_estimate`. Raises
        InsufficientMemory / WorkTooLarge."""
        s, scene, dev = self.settings, self.scene, self.dev
        drivers = p.floor_ratio(ratio, self.min_per_cell)  # per particle; above 1 where sub-particles drive
        self.memory_estimate = estimate_bake_memory(
            n_gaussians=scene.count, n_simulated=len(p.positions_sim), driver_ratio=drivers, grid_dims=p.grid_dims,
            frames=self.n_frames, preview_pixels=self.preview_pixels, sh_coeffs=int(scene.sh.shape[1]), device=dev)
        check_memory(self.memory_estimate,
            what="bake", quality=str(s.quality or "the fit's"), driver_ratio=ratio, device=dev,
            resolution=f"grid {'x'.join(map(str, p.grid_dims))} cells, set by "
                       f"{'the fit (a coarser --quality overrides it)' if self.follows_fit else '--quality'}")
        speed = float(np.linalg.norm(self.force.accel_sim(p))) * self.push_s
        # through the module, so that a test can stand in for the estimate
        self.work_estimate = work.check_bake_work(p, n_gaussians=scene.count, n_particles=max(1, int(np.ceil(drivers * len(p.positions_sim)))),
                             frames=self.n_frames + self._match_frames(p, ratio), frame_dt=self.frame_dt, E_max=self.E_top,
                             density=self.opts.density_kg_m3, nu=self.nu, speed=speed, cfl_safety=self.cfl_safety,
                             substeps=s.substeps, preview_pixels=self.preview_pixels, device=dev)

    def _matches(self, p: PreparedScene, ratio: float) -> bool:
        """Whether a fitted material is matched to this discretisation (pd_tool.bake.transfer):
        asked for, and the grid, driver ratio or CFL safety differ from the fit's."""
        fit = self.fit_sim
        if fit is None or self.follows_fit or not self.settings.match_fit:
            return False
        floors_differ = (not np.isclose(self.min_per_cell, fit["min_per_cell"])
                         and (p.splits(ratio, self.min_per_cell) or p.splits(ratio, fit["min_per_cell"])))
        return (max(p.grid_dims) != fit["grid_res"] or not np.isclose(ratio, fit["driver_ratio"]) or floors_differ
                or not np.isclose(self.cfl_safety, self._fit_cfl()))

    def _fit_cfl(self) -> float:
        """The fit's CFL safety; a material file that does not record it was fitted at the
        bake's."""
        cfl = self.fit_sim["cfl_safety"]
        return float(cfl) if cfl is not None else self.cfl_safety

    def _match_window(self) -> int:
        """Frames each of the match's runs simulates (pd_tool.bake.transfer.window_frames)."""
        return window_frames(self.settings.seconds, self.force.start + self.force.duration, self.settings.fps)

    def _match_frames(self, p: PreparedScene, ratio: float) -> int:
        """Frames the match adds to the bake's work: its runs on this discretisation and
        one on the fit's (an upper bound; the fit's grid is coarser); none once it is made."""
        if self.match is not None or not self._matches(p, ratio):
            return 0
        return (MAX_RUNS + 1) * self._match_window()

    def _new_solver(self, prep: PreparedScene, drivers, E: np.ndarray, cfl_safety: float) -> tuple[MPMSolver, np.ndarray]:
        """A solver for `drivers` of `prep` with per-driver E [Q] (Pa), the bake's force on its
        region; and that region's mask [Q]."""
        s, force = self.settings, self.force
        d_rest = drivers.positions.double().cpu().numpy()
        d_static = drivers.static.cpu().numpy().astype(bool)
        cfg = SimConfig(
            grid_res=max(prep.grid_dims), domain=prep.domain, nu=self.nu,
            gravity=(0.0, 0.0, -9.81) if s.gravity else (0.0, 0.0, 0.0), damping=self.damping,
            substeps=s.substeps, cfl_safety=cfl_safety,
        )
        solver = MPMSolver(d_rest, drivers.volume.cpu().numpy(), drivers.mass.cpu().numpy(), E, d_static, cfg,
                           device=self.dev)
        mask = force_mask(prep, d_rest, d_static, force)
        solver.add_force(mask, force.accel_sim(prep), force.start, force.start + force.duration)
        return solver, mask

    def _discretisation_of(self, prep: PreparedScene, drivers, E: np.ndarray, cfl_safety: float,
                           sample: np.ndarray) -> Discretisation:
        """`prep`'s drivers as pd_tool.bake.transfer sees them: its runs measure the scene's
        Gaussians `sample` [P] (scene indices, moving in `prep`), each moved by its drivers
        as the bake moves it (rigidly, pd_tool.drivers.DriverInterpolator)."""
        from pd_tool.drivers import DriverInterpolator

        local = np.full(self.scene.count, -1, np.int64)
        local[prep.foreground] = np.arange(prep.count)
        idx = local[sample]
        rest = torch.as_tensor(prep.positions_sim[idx], dtype=torch.float32, device=self.dev)
        identity = torch.zeros((len(sample), 4), dtype=torch.float32, device=self.dev)
        identity[:, 0] = 1.0  # positions are all the match reads
        interp = DriverInterpolator(rest, identity, drivers.positions.to(self.dev, torch.float32),
                                    drivers.neighbors[torch.as_tensor(idx)].to(self.dev))

        def run(E_run: np.ndarray, frames: int) -> np.ndarray:
            solver, _ = self._new_solver(prep, drivers, E_run, cfl_safety)
            sq = np.empty((frames, len(sample)), np.float32)
            for f in range(frames):
                solver.step_frame(self.frame_dt)
                now = interp(torch.as_tensor(solver.positions(), device=self.dev))[0]
                sq[f] = ((now - rest) ** 2).sum(-1).cpu().numpy()
            return sq

        return Discretisation(static=np.zeros(len(sample), bool), weight=np.ones(len(sample)), E=E, run=run,
                              scale=float(prep.transform.scale))

    def _match_sample(self, fit_prep: PreparedScene) -> np.ndarray:
        """Scene indices [P] of the Gaussians the match measures: at most MATCH_GAUSSIANS,
        seeded, of those that move in both the fit's preparation and the bake's."""
        def moving(p: PreparedScene) -> np.ndarray:
            return np.asarray(p.foreground)[~np.asarray(p.static[:p.count], bool)]

        both = np.intersect1d(moving(fit_prep), moving(self.prep))
        if len(both) > MATCH_GAUSSIANS:
            both = np.sort(np.random.default_rng(0).choice(both, MATCH_GAUSSIANS, replace=False))
        return both

    def _match_fit(self, material_file: MaterialFile, E: np.ndarray) -> np.ndarray:
        """E [Q] for this bake's drivers that moves as the fit's discretisation moved the
        fitted E under this force (pd_tool.bake.transfer)."""
        fit = self.fit_sim
        fit_prep = prepare_scene(self.scene, self.opts.updated(grid_res=int(fit["grid_res"])))
        fit_drivers = fit_prep.build_drivers(ratio=float(fit["driver_ratio"]), seed=int(fit["driver_seed"]),
                                             device=self.dev, min_per_cell=fit["min_per_cell"])
        fit_E = material_file.E_at(fit_prep.transform.to_scene(fit_drivers.positions.double().cpu().numpy()))
        frames = self._match_window()
        sample = self._match_sample(fit_prep)
        self.match = match_fit_motion(self._discretisation_of(fit_prep, fit_drivers, fit_E, self._fit_cfl(), sample),
                                      self._discretisation_of(self.prep, self.drivers, E, self.cfl_safety, sample),
                                      frames, window_s=frames / self.settings.fps, progress=self.match_progress)
        self.sim_note = self.match.line(int(fit["grid_res"]), max(self.prep.grid_dims))
        return self.match.E

    def _build_simulation(self, material: Material | None, material_file: MaterialFile | None) -> None:
        """Driving particles [Q] with their E (Pa), the solver, and the force on its region."""
        with self._part("drivers"):
            self.drivers = self.prep.build_drivers(ratio=self.ratio, seed=self.seed, device=self.dev,
                                                   min_per_cell=self.min_per_cell)
        if self.prep.splits(self.ratio, self.min_per_cell):
            self.drivers_note = (
                f"drivers: {self.min_per_cell:g} in each moving cell, clustered from points spread over each "
                f"Gaussian's extent: {self.prep.count:,} Gaussians at the quality's {self.ratio:g} drivers per "
                f"Gaussian give fewer on the {max(self.prep.grid_dims)}-cell grid, and parts a cell apart would "
                f"separate under a push " + ("(as the fit did)" if self.follows_fit else
                                             "(min_drivers_per_cell = 0 in a --quality file turns this off)"))
        with self._part("solver"):  # a fitted E's match inside is its own part
            self._build_solver(material, material_file)
        self.setup_parts["solver"] -= self.setup_parts.get("match", 0.0)

    def _build_solver(self, material: Material | None, material_file: MaterialFile | None) -> None:
        """The drivers' E (a fitted one matched to this discretisation), the solver and the
        force on its region, checked against the stability guard."""
        prep, force = self.prep, self.force
        d_rest = self.drivers.positions.double().cpu().numpy()
        d_static = self.drivers.static.cpu().numpy().astype(bool)
        if material_file is not None:
            E = material_file.E_at(prep.transform.to_scene(d_rest))
            if self._matches(prep, self.ratio):
                before, match_frames = self.work_estimate, self._match_frames(prep, self.ratio)
                with self._part("match"):
                    E = self._match_fit(material_file, E)
                self.E_top = float(E.max())
                self._check_cost(prep, self.ratio)  # a stiffer E takes more substeps
                self.work_estimate = _with_match(before, self.work_estimate, self.n_frames, match_frames)
        else:
            E = np.full(len(d_rest), material.E, np.float64)
        self.solver, mask = self._new_solver(prep, self.drivers, E, self.cfl_safety)
        accel_sim = force.accel_sim(prep)
        free_E = E[~d_static] if (~d_static).any() else E
        check_force(float(np.linalg.norm(accel_sim)), self.push_s,
                    float(extent(d_rest[mask]).max()) if mask.sum() > 1 else prep.dx,
                    self.opts.density_kg_m3, float(free_E.max()), float(max(prep.domain)),
                    force.unit_m_s2(prep), nu=self.nu, gap_m=_free_space(prep), magnitude=force.magnitude,
                    unit=force.unit_name())
        self.force_end = force.start + force.duration
        self.n_drivers = len(d_rest)
        self.substeps = self.solver.substeps_per_frame(self.frame_dt)

    def _open_outputs(self, camera: Camera | None) -> None:
        """Every Gaussian follows its drivers; the writers are opened last, so that no
        later step can leave their temporary outputs behind. The USD file may be rotated
        from the scene's axes (usd_frame); the splat outputs keep them or convert them."""
        from usd_export import UsdBakeWriter

        scene, prep, dev = self.scene, self.prep, self.dev
        self.animator = GaussianAnimator(scene, prep, self.drivers, device=dev)
        if self.rendering:
            self.preview_cam = camera or scene_camera(scene, width=480, height=270, up_axis=prep.options.up_axis)
        # Gaussians that keep their rest pose (GaussianAnimator): the unsimulated ones and the
        # static region. The writers put them where they are written once, not every frame.
        static = np.ones(scene.count, bool)
        static[prep.foreground] = np.asarray(prep.static[:prep.count], bool)
        R_usd, up_axis = usd_frame(prep.options.up_axis)
        usd = None
        if "usd" in self.paths:
            usd = UsdBakeWriter(
                self.paths["usd"], n_points=scene.count, fps=self.settings.fps, start_frame=0, up_axis=up_axis,
                meters_per_unit=float(prep.transform.scale), fmt=self.settings.fmt, colors=scene.colors.cpu().numpy(),
                opacities=scene.opacities.cpu().numpy(), sh=scene.sh.cpu().numpy(), static=static,
                threaded=True,  # USD work overlaps the next frame's simulation (GPU waits release the GIL)
            )
        try:
            splat = open_splat_writers(self.paths, scene.to("cpu"), static=static, up_axis=prep.options.up_axis,
                                       fps=self.settings.fps, named=self.out)
        except BaseException:
            if usd is not None:
                usd.abort()
            raise
        self.outputs = FrameOutputs(usd, R_usd, matrix_to_quat(torch.as_tensor(R_usd)).float(),
                                    scene.scales.detach().cpu().numpy(), splat)

    # ---- frames

    @property
    def done(self) -> bool:
        """Whether every frame is written (simulated or held)."""
        return self.frame >= self.n_frames

    def step(self) -> None:
        """Write the next frame: frame 0 is the rest pose, each later one simulates
        1 / fps s first. Once the object has been at rest after the force for REST_FRAMES
        frames, the remaining frames are held (no simulation, no new samples) and `done`."""
        f = self.frame
        if f == 0:
            pos, q, _ = self._frame_arrays(None)
            self.outputs.write_frame(0, pos, q)
            self.disp.append(0.0)
        else:
            pos, q = self._simulate_frame(f)
        if self.rendering:
            self._snap(pos, q)
        self.frame = f + 1
        if self.progress:
            self.progress(self.frame, self.n_frames)
        if f > 0 and self._came_to_rest() and not self.done:
            self._hold_rest()

    def _simulate_frame(self, f: int) -> tuple[np.ndarray, np.ndarray]:
        t = time.perf_counter()
        self.substeps = self.solver.step_frame(self.frame_dt)
        self.simulated += 1
        d_now = self.solver.positions()  # the host copy synchronises, so the timing is honest
        self.timings["simulate"] += time.perf_counter() - t
        t = time.perf_counter()
        pos, q, disp = self._frame_arrays(d_now)
        self.disp.append(disp)
        self.timings["interpolate"] += time.perf_counter() - t
        t = time.perf_counter()
        self.outputs.write_frame(f, pos, q)
        self.timings["write"] += time.perf_counter() - t
        return pos, q

    def _frame_arrays(self, d_now: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, float]:
        """Positions [N, 3] (scene units) and quaternions [N, 4] (w, x, y, z) in the
        scene's axes for drivers at d_now [Q, 3] (m, simulation box), and the largest
        distance from the rest pose (scene units); None: the rest pose."""
        with torch.no_grad():
            if d_now is None:
                pos, q = self.animator.scene_positions, self.animator.scene_quats
                disp = 0.0
            else:
                pos, q = self.animator(d_now)
                # on the scene's device: numpy's norm along the rows of [N, 3] took 17 ms a
                # frame at 300k Gaussians on the bake's own thread
                disp = float((pos - self.animator.scene_positions).square().sum(1).max().sqrt()) if len(pos) else 0.0
        return pos.cpu().numpy(), q.cpu().numpy(), disp

    def _snap(self, pos: np.ndarray, q: np.ndarray) -> None:
        scene = self.scene
        self.preview_images.append(render_image(scene, self.preview_cam, positions=torch.as_tensor(pos, device=scene.device),
                                                quats=torch.as_tensor(q, device=scene.device)))

    def _came_to_rest(self) -> bool:
        """Whether kinetic energy has stayed below REST_FRACTION of its peak for REST_FRAMES
        frames since the force ended (never with stop_at_rest off)."""
        ke = self.solver.kinetic_energy()
        self._peak_ke = max(self._peak_ke, ke)
        if self.settings.stop_at_rest and self.solver.time >= self.force_end:
            self._calm = self._calm + 1 if ke <= REST_FRACTION * self._peak_ke else 0
        return self._calm >= REST_FRAMES

    def _hold_rest(self) -> None:
        held = self.n_frames - self.frame
        self.outputs.hold_frames(self.n_frames - 1)
        self.disp.extend([self.disp[-1]] * held)
        self.preview_images.extend(self.preview_images[-1:] * held)
        self.frame = self.n_frames
        if self.progress:
            self.progress(self.n_frames, self.n_frames)

    # ---- outputs

    def finish(self) -> BakeResult:
        """Validate the USD and move it and the splat outputs into place, then write the
        preview and frames folder (each atomic). Call once `done`."""
        self._closed = True  # close() deletes its temporaries itself when it fails
        t = time.perf_counter()
        written = self.outputs.close()
        self.timings["close"] = time.perf_counter() - t  # counted in write too
        self.timings["write"] += self.timings["close"]
        self.timings["total"] = time.perf_counter() - self.t_start
        paths = {f: p for f, (p, _) in written.items()}
        sizes = {f: n for f, (_, n) in written.items()}
        result = BakeResult(
            out=next(iter(paths.values())), frames=self.n_frames, simulated_frames=self.simulated,
            substeps_per_frame=self.substeps, gaussians=self.scene.count, drivers=self.n_drivers,
            seconds_elapsed=time.perf_counter() - self.t_start, bytes_written=sum(sizes.values()),
            peak_displacement=max(self.disp), object_size=self.prep.object_size_m / float(self.prep.transform.scale),
            displacement_per_frame=self.disp, report=self._report(), timings=self.timings,
            setup_parts=dict(self.setup_parts), outputs=paths,
            output_bytes=sizes, output_seconds=dict(self.outputs.seconds),
            work_estimate=self.work_estimate, memory_estimate=self.memory_estimate,
        )
        if self.preview is not None:
            write_preview(self.preview_images, self.preview, self.settings.fps)
            result.report.append(f"preview {self.preview}")
        if self.frames_dir is not None:
            write_video_folder(self.frames_dir, np.stack(self.preview_images), self.preview_cam, self.settings.fps,
                               overwrite=True, what="--frames-out")
            result.report.append(f"frames {self.frames_dir}/ ({len(self.preview_images)} PNG + camera.json)")
        return result

    def _report(self) -> list[str]:
        lines = list(self.prep.report) + [note for note in (self.drivers_note, self.sim_note) if note]
        held = self.n_frames - 1 - self.simulated
        if held > 0:
            lines.append(f"at rest after frame {self.simulated}: {held} frames held, not simulated")
        return lines

    def __enter__(self) -> "Baker":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._closed and hasattr(self, "outputs"):  # left before finish(): publish nothing
            self.outputs.abort()


def bake(
    scene: GaussianScene,
    out: str | Path,
    *,
    force: ForceSpec,
    material: Material | None = None,
    material_file: MaterialFile | None = None,
    prepare_options: PrepareOptions | None = None,
    settings: BakeSettings | None = None,
    progress: Callable[[int, int], None] | None = None,
    preview: str | Path | None = None,
    frames_dir: str | Path | None = None,
    camera: Camera | None = None,
    inputs: Mapping[str, str | Path | None] | None = None,
    match_progress: Callable[[int, int], None] | None = None,
) -> BakeResult:
    """Simulate `scene` under `force` and write the animation to `out` (atomic): the USD
    file and the splat formats of settings.fmt / settings.splat_formats
    (pd_tool.io.formats names the outputs beside `out`).

    Give either a homogeneous `material` (a preset) or a fitted `material_file`
    (pd_tool.materials.file.MaterialFile). `progress(done, total)` is called once per frame;
    `match_progress(runs, at most)` once per run while a fitted E is matched to the bake's
    discretisation (pd_tool.bake.transfer), before the first frame.
    preview: also render the animation to this .mp4/.gif; frames_dir: also write the
    rendered frames with their camera.json as a reference-video folder (what `pdtool fit`
    reads); camera: the pd_tool.core.cameras.Camera for both (default: an automatic view).
    inputs: {option: path} of the files read for this bake (the scene's own file is
    added); outputs are checked against them and against each other before any work
    (`check_bake_outputs`).
    """
    with Baker(scene, out, force=force, material=material, material_file=material_file,
               prepare_options=prepare_options, settings=settings, progress=progress, preview=preview,
               frames_dir=frames_dir, camera=camera, inputs=inputs, match_progress=match_progress) as baker:
        while not baker.done:
            baker.step()
        return baker.finish()


def _discretisation(settings: BakeSettings, material_file) -> tuple[int, int | None, float, float, int, bool,
                                                                    str | None]:
    """(grid cells along the longest side, the most cells for thin parts (None: never
    raised), CFL safety, driver ratio, driver seed, whether these are the fit's, a note for
    the report) of a bake: the fit's for a fitted material
    unless a quality is named, else the quality preset's."""
    fit = material_file.fit_simulation() if material_file is not None else None
    if settings.quality is None and fit is not None:
        default = load_preset("quality", "default")
        cfl = fit["cfl_safety"] if fit["cfl_safety"] is not None else float(default["cfl_safety"])
        floor = f" (at least {fit['min_per_cell']:g} a moving cell)" if fit["min_per_cell"] else ""
        note = (f"simulating as the fit did: {fit['grid_res']}-cell grid, {fit['driver_ratio']:g} driving particles "
                f"per Gaussian{floor}, CFL safety {cfl:g} (the fitted E is calibrated to them; --quality overrides)")
        return fit["grid_res"], None, cfl, fit["driver_ratio"], fit["driver_seed"], True, note
    q = load_preset("quality", settings.quality or "default")
    thin = int(q.get("thin_grid_res", q["grid_res"]))
    note = None
    if fit is not None and (int(q["grid_res"]) != fit["grid_res"] or float(q["driver_ratio"]) != fit["driver_ratio"]):
        note = (f"note: the material was fitted on a {fit['grid_res']}-cell grid with {fit['driver_ratio']:g} driving "
                f"particles per Gaussian; --quality {settings.quality} simulates on {int(q['grid_res'])} cells with "
                f"{float(q['driver_ratio']):g}, which moves differently where parts are thin (leave --quality out to "
                f"simulate as the fit did)")
    return int(q["grid_res"]), thin, float(q["cfl_safety"]), float(q["driver_ratio"]), settings.seed, False, note
