"""Run-time estimates for a bake and a fit, and the check that refuses a run that would
take longer than the user allows, before any heavy work starts.

An estimate is a sum of terms, each a count of work units times a measured cost:

- simulation: frames x substeps x (a substep's fixed cost + particles x a particle's cost
  + grid nodes x a node's cost), forward only for a bake, forward + backward for a fit;
- rendering: per rendered frame, Gaussians x a Gaussian's cost + pixels x a pixel's cost
  (forward + backward for a fit, forward for a bake's preview);
- the bake's per-frame work on every Gaussian (interpolation from the drivers, USD write).

The substep count is the one the CFL rule chooses: the stiffest moving material's wave
speed plus the speed the force can give (|a| x its duration; bake), or the starting E
(fit; a fit whose E rises takes longer). A bake that comes to rest holds its last frames
without simulating them, so its estimate is an upper bound.

The costs: CPU from `bench/work_estimate.py` on the 2-core development machine
(docs/runs/work_estimate_cpu.json); CUDA from docs/benchmarks.md (H200 runs of
`bench/sim_speed.py` and `bench/render_speed.py`, slowed by 1.2 for an H100: about 2e9
particle-substeps/s forward at 100k particles on a 64^3 grid), with a per-frame cost
of the fit's autograd bridge fitted to the whole-fit timings there.

The check refuses above `max_minutes` (DEFAULT_MAX_MINUTES, or the CLI's --max-minutes);
PDTOOL_SKIP_WORK_CHECK=1 turns the refusal off (the estimate is still shown).
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from typing import Callable, Iterator

import contextvars

from pd_tool.core.errors import PdToolError
from pd_tool.sim.cfl import cfl_substeps, wave_speed

DEFAULT_MAX_MINUTES = 60.0


@dataclass(frozen=True)
class DeviceCosts:
    """Seconds per unit of work on one kind of device (see the module docstring)."""

    substep: float  # forward substep: fixed cost
    particle: float  # ... per particle
    node: float  # ... per grid node
    substep_fb: float  # forward + backward substep (the fit's differentiable path)
    particle_fb: float
    node_fb: float
    render_call: float  # one render call, forward
    render_gaussian: float
    render_pixel: float
    render_call_fb: float  # forward + backward
    render_gaussian_fb: float
    render_pixel_fb: float
    gaussian_frame: float  # bake: interpolation + USD write, per Gaussian and frame
    fit_frame: float  # fit: autograd bridge, animator and loss per simulated frame (fixed)
    setup_gaussian: float  # preparation, k-means, nearest drivers, per Gaussian
    setup: float  # fixed: first kernel launches, the writer's validation


# Measured by bench/work_estimate.py on the 2-core AMD EPYC (OMP_NUM_THREADS=1, machine
# otherwise idle), rounded up; a loaded machine is up to 2x slower.
CPU = DeviceCosts(
    substep=8e-5, particle=2.9e-7, node=9.2e-9,
    substep_fb=3.8e-4, particle_fb=1.1e-6, node_fb=2.6e-8,
    render_call=1e-3, render_gaussian=2.5e-6, render_pixel=1.7e-7,
    render_call_fb=2e-3, render_gaussian_fb=5.0e-6, render_pixel_fb=4.0e-7,
    gaussian_frame=1.0e-6, fit_frame=5e-2, setup_gaussian=2e-5, setup=1.0,
)
# H200 figures of docs/benchmarks.md fitted to t0 + a P + b N (20k/32^3, 100k/64^3,
# 300k/128^3), times 1.2 for an H100; the render from its 1024x576 / 300k timings.
CUDA = DeviceCosts(
    substep=2.9e-5, particle=1.0e-10, node=4.2e-11,
    substep_fb=1.25e-4, particle_fb=7.0e-10, node_fb=9.7e-11,
    render_call=3e-4, render_gaussian=3e-9, render_pixel=1e-9,
    render_call_fb=1e-3, render_gaussian_fb=8e-9, render_pixel_fb=1.2e-9,
    gaussian_frame=1.0e-7, fit_frame=3e-2, setup_gaussian=1e-5, setup=2.0,
)


def costs_for(device: str) -> DeviceCosts:
    return CUDA if str(device).startswith("cuda") else CPU


class WorkTooLarge(PdToolError):
    """The run's estimated time exceeds the limit the user allows."""


@dataclass
class WorkEstimate:
    """Seconds a run is expected to take, and where they come from."""

    seconds: float
    what: str  # "bake" or "fit"
    device: str
    terms: dict[str, float] = field(default_factory=dict)  # name -> seconds
    summary: str = ""  # the counts behind the largest term, for the message

    def describe(self) -> str:
        return format_duration(self.seconds)


def format_duration(seconds: float) -> str:
    """'40 s', '12 min', '3.5 h', '41 days'."""
    if not math.isfinite(seconds):
        return "forever"
    if seconds < 90:
        return f"{max(seconds, 1):.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:,.0f} days"


def cfl_substeps_estimate(frame_dt: float, dx: float, E_max: float, density: float, nu: float,
                          speed: float, safety: float, fixed: int | None = None, floor: int | None = None) -> int:
    """Substeps per frame the CFL rule chooses (pd_tool.sim.cfl) for the stiffest moving
    material E_max (Pa) at `speed` (m/s); `fixed` wins when given, `floor` is a least count."""
    if fixed is not None:
        return int(fixed)

    n = cfl_substeps(frame_dt, dx, wave_speed(E_max, density, nu), speed, safety)
    return max(n, int(floor or 0))


def estimate_bake_work(*, n_gaussians: int, n_particles: int, grid_nodes: int, frames: int, substeps: int,
                       preview_pixels: int = 0, device: str = "cpu") -> WorkEstimate:
    """Seconds of `pd_tool.bake.baker.bake`.

    Args:
        n_gaussians: Gaussians animated and written per frame.
        n_particles: driving particles simulated.
        grid_nodes: nodes of the simulation grid.
        frames: frames in the animation (frame 0 included; it is not simulated).
        substeps: substeps per frame.
        preview_pixels: width * height of the preview / frames-out renders (0: none).
        device: "cpu" or "cuda[:i]".
    """
    k = costs_for(device)
    sim_frames = max(frames - 1, 0)
    per_substep = k.substep + k.particle * n_particles + k.node * grid_nodes
    terms = {
        "setup": k.setup + k.setup_gaussian * n_gaussians,
        "simulate": float(sim_frames) * substeps * per_substep,
        "write": float(frames) * k.gaussian_frame * n_gaussians,
        "preview": (float(frames) * (k.render_call + k.render_gaussian * n_gaussians + k.render_pixel * preview_pixels)
                    if preview_pixels else 0.0),
    }
    summary = (f"{sim_frames:,} frames x {substeps:,} substeps x {n_particles:,} particles "
               f"on a {grid_nodes:,}-node grid, {n_gaussians:,} Gaussians")
    return WorkEstimate(sum(terms.values()), "bake", str(device), terms, summary)


def estimate_fit_work(*, n_gaussians: int, n_particles: int, grid_nodes: int, frames: list[int], image_pixels: int,
                      substeps: int, velocity_iters: int, material_iters: int, rounds: int = 1,
                      stage1_frames: int = 3, calibrate_iters: int = 0, whole_clips: int = 0,
                      device: str = "cpu") -> WorkEstimate:
    """Seconds of `pd_tool.fit.run.run_fit`.

    Each iteration of stage 1 simulates and renders the first `stage1_frames` frames of
    every video, forward and backward; each of stage 2 (and of calibration) every frame;
    each of the `whole_clips` whole-clip measures every frame, forward only (counted at the
    forward-and-backward cost, an upper bound).

    Args:
        n_gaussians: Gaussians rendered per frame.
        n_particles: driving particles simulated.
        grid_nodes: nodes of the fit's simulation grid.
        frames: frames per reference video (frame 0, the rest state, is not simulated).
        image_pixels: width * height of the resized reference frames.
        substeps: substeps per frame.
        velocity_iters, material_iters, rounds, stage1_frames, calibrate_iters: FitSettings'.
        whole_clips: whole-clip losses measured (stage 2's start and keep-best measures, the result).
        device: "cpu" or "cuda[:i]".
    """
    k = costs_for(device)
    per_frame = (substeps * (k.substep_fb + k.particle_fb * n_particles + k.node_fb * grid_nodes)
                 + k.render_call_fb + k.render_gaussian_fb * n_gaussians + k.render_pixel_fb * image_pixels
                 + k.fit_frame)
    s1 = sum(min(stage1_frames, max(t - 1, 0)) for t in frames)
    s2 = sum(max(t - 1, 0) for t in frames)
    frame_evals = rounds * (velocity_iters * s1 + material_iters * s2) + (calibrate_iters + whole_clips) * s2
    terms = {"setup": k.setup + k.setup_gaussian * n_gaussians, "iterate": float(frame_evals) * per_frame}
    summary = (f"{frame_evals:,} simulated frames (forward and backward) x {substeps:,} substeps x "
               f"{n_particles:,} particles, {n_gaussians:,} Gaussians rendered at {image_pixels:,} px")
    return WorkEstimate(sum(terms.values()), "fit", str(device), terms, summary)


@dataclass
class WorkPolicy:
    """What the caller allows and wants to hear: max_minutes (None: no limit) and a
    callback that receives every estimate (the CLI shows it with the progress bar)."""

    max_minutes: float | None = DEFAULT_MAX_MINUTES
    on_estimate: Callable[[WorkEstimate], None] | None = None


_POLICY: contextvars.ContextVar[WorkPolicy] = contextvars.ContextVar("pdtool_work_policy", default=WorkPolicy())


@contextlib.contextmanager
def work_policy(max_minutes: float | None = DEFAULT_MAX_MINUTES,
                on_estimate: Callable[[WorkEstimate], None] | None = None) -> Iterator[WorkPolicy]:
    """Set the limit and the estimate callback for the bakes and fits run inside."""
    token = _POLICY.set(WorkPolicy(max_minutes, on_estimate))
    try:
        yield _POLICY.get()
    finally:
        _POLICY.reset(token)


def check_work(estimate: WorkEstimate, *, fixes: str) -> None:
    """Report `estimate` to the policy's callback, then raise WorkTooLarge (one line) when
    it exceeds the policy's max_minutes. fixes: the options that shorten this run, for the
    message. PDTOOL_SKIP_WORK_CHECK=1 disables the refusal."""
    policy = _POLICY.get()
    if policy.on_estimate is not None:
        policy.on_estimate(estimate)
    if os.environ.get("PDTOOL_SKIP_WORK_CHECK") == "1" or policy.max_minutes is None:
        return
    if estimate.seconds > policy.max_minutes * 60.0:
        raise WorkTooLarge(
            f"this {estimate.what} would take about {estimate.describe()} on {estimate.device} "
            f"({estimate.summary}), over the {policy.max_minutes:g}-minute limit; {fixes}, "
            f"or allow it with --max-minutes {_suggest_minutes(estimate.seconds)} "
            f"(or PDTOOL_SKIP_WORK_CHECK=1)")


def _suggest_minutes(seconds: float) -> str:
    minutes = seconds / 60.0 * 1.5
    if not math.isfinite(minutes) or minutes > 1e6:
        return "N"  # beyond any sensible limit: let the user choose
    return f"{max(1, math.ceil(minutes)):d}"


def check_bake_work(prep, *, n_gaussians: int, n_particles: int, frames: int, frame_dt: float, E_max: float,
                    density: float, nu: float, speed: float, cfl_safety: float, substeps: int | None,
                    preview_pixels: int, device: str) -> WorkEstimate:
    """Estimate a bake of the prepared scene `prep` (pd_tool.prepare.preparation.PreparedScene) and
    check it (check_work). speed: m/s the force can give (|a| x duration). Returns the
    estimate."""
    n = cfl_substeps_estimate(frame_dt, prep.dx, E_max, density, nu, speed, cfl_safety, fixed=substeps)
    nodes = math.prod(d + 1 for d in prep.grid_dims)
    est = estimate_bake_work(n_gaussians=n_gaussians, n_particles=n_particles, grid_nodes=nodes, frames=frames,
                             substeps=n, preview_pixels=preview_pixels, device=device)
    check_work(est, fixes="shorten --seconds, lower --fps or --quality, or use a softer material "
                          "(its stiffness sets the substeps)" + ("" if substeps is None else ", or lower --substeps"))
    return est


def check_fit_work(prep, settings, videos, *, n_gaussians: int, cfl_safety: float,
                   drivers_per_particle: float | None = None) -> WorkEstimate:
    """Estimate a fit (pd_tool.fit.problem.FitProblem's preparation `prep`, its resolved
    FitSettings and reference videos) and check it (check_work). The substeps come from
    the starting E (settings.init_E). drivers_per_particle: with the floor of drivers a
    cell (PreparedScene.floor_ratio); None: the settings' driver ratio. Returns the estimate."""
    ratio = settings.driver_ratio if drivers_per_particle is None else drivers_per_particle
    q = max(1, int(math.ceil(float(ratio) * len(prep.positions_sim))))
    n = cfl_substeps_estimate(videos[0].frame_dt, prep.dx, float(settings.init_E), float(settings.density),
                              float(settings.nu), 0.0, cfl_safety, floor=settings.substeps)
    nodes = math.prod(d + 1 for d in prep.grid_dims)
    est = estimate_fit_work(
        n_gaussians=n_gaussians, n_particles=q, grid_nodes=nodes, frames=[int(v.num_frames) for v in videos],
        image_pixels=int(videos[0].frames[0].numel() // 3), substeps=n,
        velocity_iters=int(settings.velocity_iters), material_iters=int(settings.material_iters),
        rounds=int(settings.rounds), stage1_frames=int(settings.stage1_frames),
        calibrate_iters=int(settings.calibrate_iters),
        whole_clips=settings.whole_clip_measures(), device=str(settings.device))
    check_work(est, fixes="lower --quality, --working-size or the iterations (--velocity-iters, --material-iters), "
                          "measure less often (--keep-best), or use fewer frames")
    return est
