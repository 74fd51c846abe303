"""The fit: estimate E(x) (and v0(x) per video) so that simulation + rendering match the
reference videos. PhysDreamer's two stages:

1. velocity: E's field frozen at its initial value; optimise each video's v0 field on the
   first `stage1_frames` frames with full back-propagation through the simulation, and
   (`stage1_level`, on by default; the paper has it off) one log-E offset shared by every
   driver, folded into E when the stage ends;
2. material: v0 frozen; optimise the shared E field over all frames, each frame simulated
   from the detached state of the previous one (a one-frame gradient horizon).

Then, optionally (`calibrate_iters`), a calibration of a few whole-clip numbers: one log-E
offset per stiffness cluster of the fitted field and one speed gain per video, fitted with
the exact gradient through every frame (see `calibrate`).

Each iteration: fields -> per-driver E, v0 -> differentiable MPM (warp, checkpointed) ->
rigid interpolation to every Gaussian -> differentiable rasteriser -> lambda L1 + (1 -
lambda) D-SSIM against the reference frame -> gradients into the fields.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from pd_tool.core.errors import PdToolError, VideoError
from pd_tool.prepare.preparation import PreparedScene, PrepareOptions, prepare_scene
from pd_tool.materials.presets import fit_simulation, load_preset
from pd_tool.core.scene import GaussianScene


@dataclass
class FitSettings:
    """Settings of a fit. Iteration counts default to the quality preset's.

    Units: E in Pa, velocities in m/s, lr per optimiser step.
    """

    quality: str = "default"
    velocity_iters: int | None = None
    material_iters: int | None = None
    stage1_frames: int = 3  # frames after the rest frame that stage 1 matches
    material_horizon: int | None = 1  # frames a stage-2 loss reaches back through the state (None: all)
    # The last this many stage-2 iterations back-propagate through every frame. A truncated
    # gradient stops where it vanishes, not where the loss is least: E that acts through
    # the whole motion (a stiff stem sets its frequency, hence the phase of later frames)
    # is under-counted by it. Counted within material_iters. A lower loss has not always
    # meant a better fit (docs/fitting.md), so 0 by default.
    polish_iters: int = 0
    # Least substeps per frame; None: as the CFL condition for the current E chooses each
    # iteration. MPM's numerical damping grows with the substep count, so a floor above the
    # CFL choice keeps the count, and the damping, fixed while E moves. The CFL count still
    # wins where E rises above what the floor allows (a fixed count would blow up there).
    substeps: int | None = None
    refine_velocity: bool = False  # stage 2 also refines v0 (the paper freezes it)
    # The fit's CFL substeps come from this quantile of the moving drivers' wave speeds (1:
    # the fastest, as a bake does). MPM loses energy in every transfer, so the count sets the
    # model's damping; with the maximum, a few outlying stiff drivers set it for the whole
    # object (at 100k: 180 substeps per frame under the fitted E against 75 under the truth).
    cfl_quantile: float = 1.0
    # Rounds of (stage 1, stage 2). Stage 1 fits v0 under the starting E, so a wrong E biases
    # v0, and stage 2 then fits E to the biased v0; each later round refits v0 under the
    # fitted E. The paper does one round, and so does the default: with two videos at 100k
    # a second round brought every region within 10% on five seeds, and made the new-force
    # motion worse on every seed compared (docs/benchmarks.md, fit recovery).
    rounds: int = 1
    # Stage 1 also fits one log-E offset shared by every driver (a level, not a field; the
    # paper freezes E there: False). Stage 1 fits v0 under the starting E; when that E is too
    # soft, a slower push matches the first frames (v0 7-11% slow at 100k, bench/stage1_v0.py)
    # and stage 2 then softens the stem to match it. One number cannot take on the field's
    # shape, unlike the whole field (1.33x against 3.49x at the quick scale). Folded into the
    # per-driver residuals when stage 1 ends. The recovery benchmark's new-force error improved
    # on eight of nine seeds at 100k (5.11x against 4.46x on average; docs/benchmarks.md).
    stage1_level: bool = True
    lr_level: float = 0.05  # Adam step of the level, nats of E
    # Stage 3, calibration: iterations of the exact whole-clip gradient over a few numbers
    # only, one log-E offset per stiffness cluster and one log speed gain per video (see
    # `calibrate`). 0: off.
    calibrate_iters: int = 0
    calibrate_clusters: int = 4  # stiffness clusters of the fitted field (1-D k-means on log E)
    lr_calibrate: float = 0.02  # Adam step, in log units (nats) of E and of v0's speed (0.05 overshot)
    # Per-driver log-E residual on top of the field. The field's parameters are shared by
    # every point, so the region with the largest gradient (the stem) moves them all; a
    # residual per driver lets each region follow its own gradient sign (see docs/fitting.md).
    driver_residual: bool = True
    lr_residual: float = 0.15
    # Adam's eps for the residuals. A driver whose gradient is below it takes proportionally
    # shorter steps; at 100k the leaves' and the flower's gradients are 1e-9 to 1e-7
    # (bench/fit_recovery.py --residual-gradients), so torch's 1e-8 held the leaves near the
    # start. 1e-16 alone moved them only within the seed spread, since the smoothness penalty
    # held them back; with the diffusion below it brings every region within 10%
    # (docs/benchmarks.md, fit).
    residual_eps: float = 1e-16
    # Weight of the mean squared residual difference between neighbouring drivers (a
    # diagnostic setting, 0 by default). Adam normalises its gradient per
    # driver against the video's, which is 100x weaker on a leaf than on the stem, so it held
    # the leaves back and hardly the stem; residual_diffusion does its job instead.
    residual_smoothness: float = 0.0
    # Diffusion of the residuals after every stage-2 step, in fit-grid cells squared per
    # iteration (0: off): each driver moves D dx^2 / h^2 of the way (at most 0.9) toward its
    # nearest drivers' mean, h being its mean distance to them, so the smoothing covers the
    # same length of object whatever the driver density (pd_tool/fit/diffusion.py). It acts
    # in the residual's own units, so it holds a driver with a strong video gradient (the
    # stem's stiff outliers, which set the substep count and so MPM's damping) as firmly as
    # one with a weak gradient (a leaf), and carries the leaves' softening out to their tips.
    # 0.02 moves the median driver about half way at the 100k benchmark's driver density.
    residual_diffusion: float = 0.02
    refine_velocity_factor: float = 0.5  # v0's stage-2 step size, as a fraction of lr_velocity
    lr_velocity: float = 2e-2
    lr_material: float = 5e-2
    warmup: int = 3  # iterations of linear warm-up per stage
    grad_clip: float = 1.0
    tv_weight: float = 1e-4
    loss_lambda: float = 0.1
    init_E: float = 1e6  # Pa, the uniform starting value (and the baseline it is compared with)
    E_min: float = 1e3  # Pa, bounds of the material field
    E_max: float = 1e8
    velocity_scale: float = 1.0  # m/s per unit of the velocity field's output
    velocity_resolution: int = 24  # triplane texels per side of the v0 field (paper: 24)
    material_resolution: int = 8  # ... of the E field (paper: 8)
    nu: float = 0.3
    density: float = 1000.0  # kg/m^3
    damping: float = 0.0  # 1/s
    driver_ratio: float | None = None  # None: the quality preset's
    working_long_side: int = 256  # px, reference frames are resized to this
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # Scale each video's render by a gain per colour channel, fitted once at rest (frame 0),
    # so that a camera's exposure and white balance do not count as motion error. A 10%
    # darker video left the loss at 0.067 on a 3,000-Gaussian plant and the fit drove E up
    # until nothing moved (bench/fit_truth.py).
    match_exposure: bool = True
    seed: int = 0
    device: str = "cpu"
    checkpoint_every: int = 5  # iterations between checkpoints (bounded loss of work on a kill)

    def resolved(self) -> "FitSettings":
        """These settings with every default filled in from the quality preset."""
        q = load_preset("quality", self.quality)
        out = FitSettings(**asdict(self))
        if out.rounds < 1:
            raise ValueError(f"rounds must be at least 1, got {out.rounds}")
        if out.polish_iters < 0:
            raise ValueError(f"polish_iters must be at least 0, got {out.polish_iters}")
        if not 0.0 < out.cfl_quantile <= 1.0:
            raise ValueError(f"cfl_quantile must be in (0, 1], got {out.cfl_quantile}")
        if not (math.isfinite(out.residual_diffusion) and out.residual_diffusion >= 0.0):
            raise ValueError(f"residual_diffusion must be >= 0 (grid cells squared), got {out.residual_diffusion}")
        if not out.residual_eps > 0:
            raise ValueError(f"residual_eps must be > 0, got {out.residual_eps}")
        if out.calibrate_iters < 0:
            raise ValueError(f"calibrate_iters must be at least 0, got {out.calibrate_iters}")
        if out.calibrate_clusters < 1:
            raise ValueError(f"calibrate_clusters must be at least 1, got {out.calibrate_clusters}")
        if out.stage1_level and not out.driver_residual:
            raise ValueError("stage1_level folds its offset into the per-driver residuals; keep driver_residual on")
        if out.calibrate_iters and not out.driver_residual:
            raise ValueError("calibration folds its offsets into the per-driver residuals; keep driver_residual on")
        if out.velocity_iters is None:
            out.velocity_iters = int(q["fit_velocity_iters"])
        if out.material_iters is None:
            out.material_iters = int(q["fit_material_iters"])
        if out.driver_ratio is None:
            out.driver_ratio = fit_simulation(q)[2]
        return out


@dataclass
class FitResult:
    material_path: Path
    driver_E: np.ndarray
    driver_v0: np.ndarray  # [Q, 3] m/s, the first video's fitted initial velocity
    gaussian_E: np.ndarray  # [F] per simulated Gaussian (its driver's E)
    losses: dict[str, list[float]]
    seconds: dict[str, float]
    prep: PreparedScene
    drivers: Any
    report: list[str] = field(default_factory=list)
    skipped_steps: int = 0  # material-stage optimiser steps skipped for a non-finite gradient
    driver_v0s: list[np.ndarray] = field(default_factory=list)  # [Q, 3] m/s per video, in video order
    # E per driver (Pa) before calibration, when the fit calibrated (diagnostics; not saved)
    driver_E_uncalibrated: np.ndarray | None = None
    calibration: dict[str, Any] | None = None  # the offsets, gains and losses calibration chose
    # what the fit ran at, for its report: the settings resolved from the quality preset,
    # the quality's CFL safety factor, and the least and most substeps per frame its
    # simulations took in this process (None: none ran, as when a resumed fit had finished)
    settings: FitSettings | None = None
    cfl_safety: float | None = None
    substeps: tuple[int, int] | None = None


ProgressFn = Callable[[str, int, int, float], None]  # stage, iteration, total, loss


class FitProblem:
    """Everything one fit needs, set up once: preparation, drivers, videos, fields, sim."""

    def __init__(self, scene: GaussianScene, videos: list, prep_options: PrepareOptions, settings: FitSettings) -> None:
        from pd_tool.bake.animate import GaussianAnimator
        from pd_tool.fit.fields import MaterialField, VelocityField

        self.s = settings
        self.substeps_range: tuple[int, int] | None = None  # least, most per frame so far
        self.device = torch.device(settings.device)
        torch.manual_seed(settings.seed)
        quality = load_preset("quality", settings.quality)
        prep_options.grid_res, self.cfl_safety, _ = fit_simulation(quality)
        prep_options.density_kg_m3 = settings.density
        self.scene = scene.to(self.device)
        self.prep = prepare_scene(self.scene, prep_options)
        p = self.prep
        # refuse now, before drivers, simulator and graph, when the fit cannot fit in memory
        from pd_tool.prepare.memory import check_memory, estimate_fit_memory

        check_memory(estimate_fit_memory(
            n_gaussians=scene.count, n_simulated=len(p.positions_sim), driver_ratio=settings.driver_ratio,
            grid_dims=p.grid_dims,
            frames=[v.num_frames for v in videos], image_pixels=int(videos[0].frames[0].numel() // 3),
            stage1_frames=settings.stage1_frames, device=settings.device),
            what="fit", quality=str(settings.quality), driver_ratio=settings.driver_ratio, device=settings.device,
            resolution=f"--working-size {settings.working_long_side}")
        from pd_tool.prepare.work import check_fit_work  # ... or would take longer than allowed

        check_fit_work(p, settings, videos, n_gaussians=scene.count, cfl_safety=self.cfl_safety)
        self.drivers = p.build_drivers(ratio=settings.driver_ratio, seed=settings.seed)
        self.animator = GaussianAnimator(self.scene, p, self.drivers, device=self.device)
        self.videos = videos
        fps = {round(v.fps, 6) for v in videos}
        if len(fps) != 1:
            raise VideoError(f"reference videos have different frame rates {sorted(fps)}; give them one --fps")
        self.frame_dt = videos[0].frame_dt
        d = self.drivers
        self.x_rest = d.positions.to(self.device, torch.float32)
        self.static = d.static.to(self.device).bool()
        self.volume = d.volume.to(self.device, torch.float32)
        self.mass = d.mass.to(self.device, torch.float32)
        # fields see positions normalised to the simulation box
        self.x_norm = (self.x_rest / torch.as_tensor(p.domain, dtype=torch.float32, device=self.device)).clamp(0, 1)
        self.material = MaterialField(settings.material_resolution, math.log(settings.E_min), math.log(settings.E_max),
                                      math.log(settings.init_E)).to(self.device)
        self.log_e_residual = torch.nn.Parameter(torch.zeros(len(self.x_rest), device=self.device))
        self.log_e_level = torch.nn.Parameter(torch.zeros((), device=self.device))  # stage 1's level (nats)
        from pd_tool.drivers import knn

        # each driver's nearest other drivers, for the residuals' smoothing (penalty and
        # diffusion), and its mean distance to them (m), the spacing residual_diffusion scales by
        dist2, nearest = knn(self.x_rest, self.x_rest, k=min(7, len(self.x_rest)))
        self.driver_pairs = nearest[:, 1:]
        self.driver_spacing = dist2[:, 1:].sqrt().mean(dim=1)
        self.velocities = torch.nn.ModuleList(
            [VelocityField(settings.velocity_resolution, settings.velocity_scale) for _ in videos]).to(self.device)
        from pd_tool.sim import DiffSim, SimConfig

        cfg = SimConfig(grid_res=max(p.grid_dims), domain=p.domain, nu=settings.nu, gravity=(0.0, 0.0, 0.0),
                        damping=settings.damping, cfl_safety=self.cfl_safety, min_substeps=settings.substeps)
        self.sim = DiffSim(self.volume.cpu().numpy(), self.mass.cpu().numpy(), self.static.cpu().numpy(), cfg,
                           device=str(self.device))
        ones = torch.ones(3, device=self.device)
        self.gains = [self.exposure_gain(i) if settings.match_exposure else ones for i in range(len(videos))]

    # ------------------------------------------------------------------ pieces
    def driver_E(self) -> torch.Tensor:
        """E per driver, Pa: the field, times exp(residual) when residuals are on; kept
        inside the field's bounds by a smooth squash (no clamp)."""
        log_e = self.material(self.x_norm)
        if self.s.driver_residual:
            lo, hi = self.material.log_e_min, self.material.log_e_max
            log_e = lo + (hi - lo) * torch.sigmoid(torch.logit(self._unit(log_e)) + self.log_e_residual)
        return torch.exp(log_e)

    def _unit(self, log_e: torch.Tensor) -> torch.Tensor:
        """log E (nats) as a fraction of the field's bounds, kept off 0 and 1 (logit finite)."""
        lo, hi = self.material.log_e_min, self.material.log_e_max
        return ((log_e - lo) / (hi - lo)).clamp(1e-6, 1 - 1e-6)

    @torch.no_grad()
    def set_driver_log_E(self, log_e: torch.Tensor) -> None:
        """Set the residuals so that driver_E() returns exp(log_e) (log_e [Q] in nats, inside
        the field's bounds): the inverse of driver_E's squash, for a stage that fits E per
        driver outside the field (calibrate). Needs driver_residual."""
        self.log_e_residual.copy_(torch.logit(self._unit(log_e)) - torch.logit(self._unit(self.material(self.x_norm))))

    def residual_penalty(self) -> torch.Tensor:
        r = self.log_e_residual
        return self.s.residual_smoothness * ((r[:, None] - r[self.driver_pairs]) ** 2).mean()

    def diffuse_residuals(self, cells2: float) -> None:
        """One diffusion step of the residuals over the driver graph (FitSettings.residual_diffusion)."""
        from pd_tool.fit.diffusion import diffuse, diffusion_fractions

        diffuse(self.log_e_residual.data, self.driver_pairs, diffusion_fractions(self.driver_spacing, self.prep.dx, cells2))

    def driver_v0(self, i: int) -> torch.Tensor:
        v = self.velocities[i](self.x_norm)
        return v * (~self.static).float()[:, None]

    def substeps(self, E: torch.Tensor, v0: torch.Tensor) -> int:
        from pd_tool.sim import cfl_substeps_for

        vmax = float(v0.detach().norm(dim=1).max()) if len(v0) else 0.0
        n = cfl_substeps_for(E, self.sim, self.frame_dt, vmax, self.s.cfl_quantile)
        lo, hi = self.substeps_range or (n, n)
        self.substeps_range = (min(lo, n), max(hi, n))
        return n

    def initial_state(self, v0: torch.Tensor):
        from pd_tool.sim import initial_state

        return initial_state(self.x_rest, v0)

    def step(self, state, E: torch.Tensor, substeps: int, frame_index: int):
        """One video frame of simulation, differentiable in state and E."""
        return self.sim.frame(state, E.float(), self.frame_dt, substeps, t0=(frame_index - 1) * self.frame_dt,
                              frame_index=frame_index)

    def render(self, i: int, driver_positions: torch.Tensor) -> torch.Tensor:
        from pd_tool.render import render

        pos, quats = self.animator(driver_positions)
        sc = self.scene
        return render(pos, quats, sc.scales, sc.opacities, sc.sh, self.videos[i].camera,
                      background=self.s.background).rgb

    def exposure_gain(self, i: int) -> torch.Tensor:
        """Video i's gain per colour channel [3]: the least-squares scale from the render at
        rest to the video's frame 0 (inside its mask, when it has one), within 0.5-2."""
        v = self.videos[i]
        with torch.no_grad():
            img = self.render(i, self.x_rest).reshape(-1, 3)
            ref = v.frames[0].to(img).reshape(-1, 3)
            w = torch.ones_like(ref[:, :1]) if v.masks is None else v.masks[0].to(img).reshape(-1, 1)
            g = (w * ref * img).sum(0) / (w * img * img).sum(0).clamp_min(1e-12)
        return g.clamp(0.5, 2.0)

    def frame_loss(self, i: int, k: int, image: torch.Tensor) -> torch.Tensor:
        from pd_tool.fit.losses import frame_loss

        v = self.videos[i]
        mask = None if v.masks is None else v.masks[k]
        return frame_loss(image * self.gains[i], v.frames[k], mask, lam=self.s.loss_lambda)


# ---------------------------------------------------------------------- stages
def _clip_and_step(params, opt, sched, clip: float) -> bool:
    """Clip, step, advance the schedule. A non-finite gradient (a simulation that blew up
    under a trial E) skips the step instead of writing NaN into the field; returns
    whether the step was taken."""
    norm = torch.nn.utils.clip_grad_norm_(params, clip)
    ok = bool(torch.isfinite(norm))
    if ok:
        opt.step()
    sched.step()
    opt.zero_grad(set_to_none=True)
    return ok


def velocity_iteration(pb: FitProblem) -> float:
    """One stage-1 iteration over every video; returns the mean frame loss. E is frozen,
    up to a shared factor exp(log_e_level) when settings.stage1_level is on."""
    E_frozen = pb.driver_E().detach()
    total = 0.0
    n = 0
    for i, video in enumerate(pb.videos):
        # scaled per video: each video's backward frees the graph it was built in
        E = E_frozen * torch.exp(pb.log_e_level) if pb.s.stage1_level else E_frozen
        v0 = pb.driver_v0(i)
        sub = pb.substeps(E, v0)
        state = pb.initial_state(v0)
        loss = torch.zeros((), device=pb.device)
        frames = min(pb.s.stage1_frames, video.num_frames - 1)
        for k in range(1, frames + 1):
            state = pb.step(state, E, sub, k)
            loss = loss + pb.frame_loss(i, k, pb.render(i, state[0]))
        (loss / frames + pb.s.tv_weight * pb.velocities[i].tv()).backward()
        total += float(loss.detach()) / frames
        n += 1
    return total / max(n, 1)


@torch.no_grad()
def fold_level(pb: FitProblem) -> float:
    """Move stage 1's shared log-E offset into the per-driver residuals (driver_E() is
    unchanged by the move) and zero it: stage 2 starts from the rescaled field. Returns the
    offset, nats."""
    level = float(pb.log_e_level)
    pb.set_driver_log_E(torch.log(pb.driver_E()) + pb.log_e_level)
    pb.log_e_level.zero_()
    return level


def sequence_loss(pb: FitProblem, E: torch.Tensor, v0s: list[torch.Tensor], horizon: int | None) -> torch.Tensor:
    """Mean frame loss over every frame of every video, simulated from rest with driver E
    (Pa) and each video's initial velocity v0s[i] (m/s); the graph is cut every `horizon`
    frames (None: never), which truncates the gradient as stage 2 does."""
    total = torch.zeros((), device=pb.device)
    count = 0
    for i, video in enumerate(pb.videos):
        sub = pb.substeps(E, v0s[i])
        state = pb.initial_state(v0s[i])
        for k in range(1, video.num_frames):
            # Cut the graph every `horizon` frames, but never before the first frame: its loss
            # must still reach v0 when stage 2 refines it (a cut at k = 1 left v0 without gradient).
            if horizon is not None and k > 1 and (k - 1) % horizon == 0:
                state = tuple(t.detach() for t in state)
            state = pb.step(state, E, sub, k)
            total = total + pb.frame_loss(i, k, pb.render(i, state[0]))
            count += 1
    return total / max(count, 1)


def material_iteration(pb: FitProblem, v0s: list[torch.Tensor] | None, horizon: int | None) -> float:
    """One stage-2 iteration over every frame of every video. v0s: the frozen initial
    velocities, or None to take them (with gradients) from the velocity fields; horizon:
    frames the gradient reaches back (None: all)."""
    E = pb.driver_E()
    if v0s is None:
        v0s = [pb.driver_v0(i) for i in range(len(pb.videos))]
    loss = sequence_loss(pb, E, v0s, horizon)
    reg = pb.s.tv_weight * pb.material.tv()
    if pb.s.driver_residual:
        reg = reg + pb.residual_penalty()
    (loss + reg).backward()
    return float(loss.detach())  # float() of a tensor that requires grad warns on stderr


def stiffness_clusters(log_e: torch.Tensor, k: int, iters: int = 50) -> torch.Tensor:
    """Labels [Q] in [0, k) of a 1-D k-means on log E (nats). The centres start evenly
    spaced between the 1st and 99th percentiles: deterministic, and (unlike quantiles, which
    put most centres in the most populous stiffness) one per level of a field with a few
    distinct levels."""
    k = max(1, min(k, len(log_e)))
    x = log_e.detach().double()
    lo, hi = torch.quantile(x, torch.tensor([0.01, 0.99], dtype=torch.float64, device=x.device)).tolist()
    centres = lo + (hi - lo) * (torch.arange(k, dtype=torch.float64, device=x.device) + 0.5) / k
    labels = torch.zeros(len(x), dtype=torch.long, device=x.device)
    for _ in range(iters):
        labels = (x[:, None] - centres[None, :]).abs().argmin(1)
        new = centres.clone()
        for c in range(k):
            sel = labels == c
            if sel.any():  # an empty cluster keeps its centre
                new[c] = x[sel].mean()
        if torch.equal(new, centres):
            break
        centres = new
    return labels


def calibrate(pb: FitProblem, s: FitSettings, progress: ProgressFn | None = None) -> dict[str, Any]:
    """Stage 3: fit a few whole-clip numbers with the exact gradient through every frame.

    The one-frame horizon of stage 2 under-counts what acts through the whole motion (a
    stem's stiffness sets the phase of every later frame), and stage 1 fits v0 under the
    starting E, which leaves it about 10% too slow when that E is too soft
    (bench/stage1_v0.py). Full back-propagation over the per-driver field finds other
    minima (docs/benchmarks.md); over a handful of numbers it cannot bend the field's shape
    to v0's error. The numbers: a log-E offset per stiffness cluster of the fitted field
    (`calibrate_clusters`, 1-D k-means on log E over the moving drivers) and a log speed
    gain per video. Adam, `calibrate_iters` steps of `lr_calibrate` nats; the parameters
    with the least loss seen are kept (the start among them, so the whole-clip loss never
    rises), folded into the per-driver residuals and the velocity fields' scales.
    Returns the offsets, gains and losses.
    """
    with torch.no_grad():
        E0 = pb.driver_E().detach()
        v0s = [pb.driver_v0(i).detach() for i in range(len(pb.videos))]
    moving = ~pb.static
    labels = torch.full((len(E0),), s.calibrate_clusters, dtype=torch.long, device=pb.device)  # static: no offset
    if moving.any():
        labels[moving] = stiffness_clusters(torch.log(E0[moving]), s.calibrate_clusters)
    offsets = torch.zeros(s.calibrate_clusters, device=pb.device, requires_grad=True)
    gains = torch.zeros(len(pb.videos), device=pb.device, requires_grad=True)
    opt = torch.optim.Adam([offsets, gains], lr=s.lr_calibrate)
    lo, hi = pb.material.log_e_min, pb.material.log_e_max
    history: list[float] = []
    best = (math.inf, None, None)
    for it in range(s.calibrate_iters):
        delta = torch.cat([offsets, offsets.new_zeros(1)])[labels]
        # offsets move lr_calibrate nats a step, so the field's bounds are far; the clamp only
        # keeps a driver already at a bound there, as the fold below does
        log_e = (torch.log(E0) + delta).clamp(lo, hi)
        loss = sequence_loss(pb, torch.exp(log_e), [v * torch.exp(g) for v, g in zip(v0s, gains)], None)
        value = float(loss.detach())
        history.append(value)
        if math.isfinite(value) and value < best[0]:
            best = (value, offsets.detach().clone(), gains.detach().clone())
        if progress:
            progress("calibrate", it + 1, s.calibrate_iters, value)
        if it + 1 == s.calibrate_iters:
            break  # the last loss is only measured: a step after it would go unchecked
        loss.backward()
        if torch.isfinite(offsets.grad).all() and torch.isfinite(gains.grad).all():
            opt.step()
        opt.zero_grad(set_to_none=True)
    if best[1] is None:
        return {"offsets": [0.0] * s.calibrate_clusters, "gains": [1.0] * len(pb.videos), "losses": history}
    _, off, gain = best
    pb.set_driver_log_E(torch.log(E0) + torch.cat([off, off.new_zeros(1)])[labels])
    for i, g in enumerate(gain.tolist()):
        pb.velocities[i].scale *= math.exp(g)
    return {"offsets": off.tolist(), "gains": [math.exp(g) for g in gain.tolist()], "losses": history,
            "cluster_sizes": torch.bincount(labels, minlength=s.calibrate_clusters + 1)[:-1].tolist()}


def _stage_optimizers(pb: FitProblem, s: FitSettings, stage: str) -> dict[str, tuple[Any, Any]]:
    """The optimisers and schedules of a stage, by checkpoint suffix: "" the stage's own
    (v0 fields in stage 1, the E field in stage 2), "_l" stage 1's level, "_r" the
    per-driver residuals, "_v" v0's refinement in stage 2 (each only when its setting is on)."""
    from pd_tool.fit.schedule import make_optimizer, make_tensor_optimizer

    if stage == "velocity":
        n = max(s.velocity_iters, 1)
        out = {"": make_optimizer(list(pb.velocities), s.lr_velocity, n, warmup_steps=min(s.warmup, n))}
        if s.stage1_level:
            out["_l"] = make_tensor_optimizer(pb.log_e_level, s.lr_level, n, warmup_steps=min(s.warmup, n))
        return out
    n = max(s.material_iters, 1)
    out = {"": make_optimizer(pb.material, s.lr_material, n, warmup_steps=min(s.warmup, n))}
    if s.driver_residual:
        out["_r"] = make_tensor_optimizer(pb.log_e_residual, s.lr_residual, n, warmup_steps=min(s.warmup, n),
                                          eps=s.residual_eps)
    if s.refine_velocity:  # the velocity fields keep moving, with their own smaller step
        out["_v"] = make_optimizer(list(pb.velocities), s.lr_velocity * s.refine_velocity_factor, n,
                                   warmup_steps=min(s.warmup, n))
    return out


def _save_checkpoint(path: Path, pb: FitProblem, stage: str, it: int, optimizers: dict[str, tuple[Any, Any]],
                     losses: dict[str, list[float]], rnd: int = 0) -> None:
    """Write the fit's state after `it` iterations of `stage` in round `rnd` (the file
    format: pd_tool/fit/checkpoint.py; what it must hold: _check_checkpoint)."""
    from pd_tool.fit.checkpoint import write_checkpoint

    state: dict[str, Any] = {
        "stage": stage, "iteration": it, "round": rnd,
        "material": pb.material.state_dict(), "velocities": pb.velocities.state_dict(),
        "residual": pb.log_e_residual.detach(), "level": pb.log_e_level.detach(),
        # float64 arrays: a loss that came out NaN is written, and refused when resuming
        "losses": {k: torch.tensor(v, dtype=torch.float64) for k, v in losses.items()},
        "torch_rng": torch.get_rng_state(),
    }
    for suffix, (opt, sched) in optimizers.items():
        state["optimizer" + suffix], state["scheduler" + suffix] = opt.state_dict(), sched.state_dict()
    write_checkpoint(path, state, getattr(pb, "resume_key", {}))  # none when a bench script runs a round


def _resume_key(pb: FitProblem, scene_path: str | Path) -> dict:
    """What a checkpoint must share with the fit that resumes it: the scene file, the
    preparation's result, the videos and the settings (the device may change)."""
    from pd_tool.materials.file import scene_fingerprint

    settings = {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(pb.s).items() if k != "device"}
    return {"scene_sha256": scene_fingerprint(scene_path), "drivers": int(len(pb.x_rest)),
            "frames": [int(v.num_frames) for v in pb.videos],
            "image": [list(v.frames.shape[1:3]) for v in pb.videos], "settings": settings}


_RESUME_FIX = "delete it, or fit without --resume"


def _foreign_checkpoint(path: Path, what: str) -> PdToolError:
    from pd_tool.fit.checkpoint import CheckpointError

    return CheckpointError(f"{path}: is not a pdtool fit checkpoint ({what}), and a fit keeps its checkpoint at "
                           f"that path; pdtool neither reads nor replaces it: move it away, or fit to another --out")


def _checkpoint_max_bytes(pb: FitProblem, s: FitSettings) -> int:
    """The largest checkpoint this fit writes, with room to spare: every trained tensor
    with two Adam moments (x3, x4 for the slack), the loss histories, the header."""
    from pd_tool.fit.checkpoint import MAX_HEADER_BYTES

    tensors = [*pb.material.parameters(), *pb.velocities.parameters(), pb.log_e_residual, pb.log_e_level]
    weights = sum(t.numel() * t.element_size() for t in tensors)
    return 4 * weights + 8 * s.rounds * (s.velocity_iters + s.material_iters + 2) + MAX_HEADER_BYTES + (1 << 20)


def _load_checkpoint(path: Path, pb: FitProblem, s: FitSettings) -> dict | None:
    """The checkpoint at `path`, checked against this fit (_check_checkpoint), with its
    losses as lists; None when there is none. One-line CheckpointError otherwise."""
    from pd_tool.fit.checkpoint import CheckpointError, ForeignCheckpointFile, is_pdtool_checkpoint, read_checkpoint

    if not path.exists() and not path.is_symlink():
        return None
    ours, what = is_pdtool_checkpoint(path)
    if not ours:
        raise _foreign_checkpoint(path, what)
    try:
        problem, state = read_checkpoint(path, max_bytes=_checkpoint_max_bytes(pb, s))
    except ForeignCheckpointFile:
        raise _foreign_checkpoint(path, "unrecognised") from None
    except CheckpointError as e:
        raise CheckpointError(f"{e}; {_RESUME_FIX}") from None
    _check_resume_key(path, problem, pb.resume_key)
    _check_checkpoint(path, state, pb, s)
    state["losses"] = {k: v.tolist() for k, v in state["losses"].items()}
    return state


def _check_resume_key(path: Path, problem: dict, key: dict) -> None:
    # a checkpoint of another fit (other scene, options, videos, or a preparation that came
    # out differently) would load into tensors of the wrong shape, or silently mix two fits
    from pd_tool.fit.checkpoint import CheckpointError

    if not problem:
        raise CheckpointError(f"{path}: the checkpoint does not say which fit it belongs to (no problem key); "
                              f"{_RESUME_FIX}")
    for name in [*key, *(k for k in problem if k not in key)]:
        if problem.get(name) != key.get(name):
            what = name if name != "drivers" else f"driver count {problem.get(name)!r:.20} != {key[name]}"
            raise CheckpointError(f"{path}: the checkpoint belongs to another fit ({what} differs); {_RESUME_FIX}")


def _check_checkpoint(path: Path, state: dict, pb: FitProblem, s: FitSettings) -> None:
    """Refuse (one line) a checkpoint this fit cannot continue from: a stage, iteration or
    round outside the fit's ranges, missing or unknown entries, tensors of another shape or
    dtype than this fit's, optimiser or schedule states that do not match the fit's
    settings and iteration, loss histories of the wrong length. The checksum only tells a
    damaged file; these checks hold for a crafted one that recomputed it."""
    from pd_tool.fit.checkpoint import CheckpointError

    def bad(why: str) -> CheckpointError:
        return CheckpointError(f"{path}: {why}; {_RESUME_FIX}")

    def integer(name: str, lo: int, hi: int) -> int:
        v = state.get(name)
        if type(v) is not int or not lo <= v <= hi:
            raise bad(f"{name} {v!r:.24} is outside this fit's range {lo}-{hi}")
        return v

    stage = state.get("stage")
    if stage not in ("velocity", "material"):
        raise bad(f"stage {stage!r:.24} is not 'velocity' or 'material'")
    iters = s.velocity_iters if stage == "velocity" else s.material_iters
    if iters < 1:
        raise bad(f"it stopped in the {stage} stage, which this fit skips ({stage}_iters = 0)")
    it = integer("iteration", 0, iters - 1)
    rnd = integer("round", 0, s.rounds - 1)
    optimizers = _stage_optimizers(pb, s, stage)
    want = {"stage", "iteration", "round", "material", "velocities", "residual", "level", "losses", "torch_rng"}
    want |= {f"{kind}{suffix}" for suffix in optimizers for kind in ("optimizer", "scheduler")}
    if set(state) != want:
        missing, unknown = sorted(want - set(state)), sorted(map(str, set(state) - want))
        raise bad(f"it lacks {', '.join(missing)}" if missing else f"it holds unknown entries {', '.join(unknown)}")

    def tensor(name: str, t: Any, like: torch.Tensor) -> None:
        if not isinstance(t, torch.Tensor) or t.dtype != like.dtype or t.shape != like.shape:
            found = f"{t.dtype} {list(t.shape)}" if isinstance(t, torch.Tensor) else type(t).__name__
            raise bad(f"{name} is {found}, where this fit has {like.dtype} {list(like.shape)}")

    def module(name: str, sd: Any, like: dict) -> None:
        if not isinstance(sd, dict) or set(sd) != set(like):
            raise bad(f"{name} does not hold this fit's field weights")
        for k, t in like.items():
            tensor(f"{name}.{k}", sd[k], t)

    module("material", state["material"], pb.material.state_dict())
    module("velocities", state["velocities"], pb.velocities.state_dict())
    tensor("residual", state["residual"], pb.log_e_residual.detach())
    tensor("level", state["level"], pb.log_e_level.detach())
    tensor("torch_rng", state["torch_rng"], torch.get_rng_state())
    for suffix, (opt, sched) in optimizers.items():
        _check_optimizer(bad, "optimizer" + suffix, state["optimizer" + suffix], opt, sched, it, tensor)
        _check_scheduler(bad, "scheduler" + suffix, state["scheduler" + suffix], sched, it)

    # the histories hold one loss per iteration run so far (and one level per fold)
    vi, mi = s.velocity_iters, s.material_iters
    lengths = {"velocity": rnd * vi + (it if stage == "velocity" else vi),
               "material": rnd * mi + (it if stage == "material" else 0)}
    folds = rnd + (stage == "material") if s.stage1_level else 0
    if folds:
        lengths["stage1_level"] = folds
    losses = state["losses"]
    if not isinstance(losses, dict) or set(losses) != set(lengths):
        raise bad(f"its loss histories are not {', '.join(sorted(lengths))}")
    for k, n in lengths.items():
        tensor(f"losses.{k}", losses[k], torch.zeros(n, dtype=torch.float64))


def _same(a: Any, b: Any) -> bool:
    """Equal values of equal types, all the way down (1 == 1.0 == True is not enough)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    return a == b


def _scheduled_lrs(sched: Any, it: int) -> list[float]:
    # what LambdaLR sets after `it` steps: base lr times the schedule's factor at step `it`
    return [base * fn(it) for fn, base in zip(sched.lr_lambdas, sched.base_lrs)]


def _check_optimizer(bad, name: str, sd: Any, opt: Any, sched: Any, it: int, tensor) -> None:
    """An Adam/AdamW state_dict as this fit's optimiser has it after `it` iterations:
    this fit's hyperparameters and scheduled lr, moments shaped like the parameters, at
    most `it` steps."""
    like = opt.state_dict()
    if not isinstance(sd, dict) or set(sd) != {"state", "param_groups"}:
        raise bad(f"{name} is not an optimiser state")
    groups = sd["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(like["param_groups"]):
        raise bad(f"{name} has other parameter groups than this fit")
    params: dict[int, torch.Tensor] = {}
    for g, g_like, lr, live in zip(groups, like["param_groups"], _scheduled_lrs(sched, it), opt.param_groups):
        if not isinstance(g, dict) or g.keys() != g_like.keys():
            raise bad(f"{name} has other parameter groups than this fit")
        for k, v in g_like.items():
            if not _same(g[k], lr if k == "lr" else v):
                raise bad(f"{name}'s {k} is {g[k]!r:.40}, where this fit has {(lr if k == 'lr' else v)!r:.40}")
        params.update(zip(g_like["params"], live["params"]))
    if not isinstance(sd["state"], dict):
        raise bad(f"{name} is not an optimiser state")
    for idx, st in sd["state"].items():
        if idx not in params:
            raise bad(f"{name} holds a state for a parameter this fit does not have")
        p = params[idx].detach()
        keys = {"step", "exp_avg", "exp_avg_sq"}
        if not isinstance(st, dict) or set(st) != keys:
            raise bad(f"{name} holds a parameter state other than Adam's")
        step = st["step"]
        if not (isinstance(step, torch.Tensor) and step.dim() == 0 and step.dtype in (torch.float32, torch.float64)
                and float(step) == int(step) and 1 <= float(step) <= it):
            raise bad(f"{name} has a step count outside 1-{it}")
        tensor(f"{name}.exp_avg", st["exp_avg"], p)
        tensor(f"{name}.exp_avg_sq", st["exp_avg_sq"], p)
        if (st["exp_avg_sq"] < 0).any():
            raise bad(f"{name} has a negative second moment")


def _check_scheduler(bad, name: str, sd: Any, sched: Any, it: int) -> None:
    """A LambdaLR state_dict as this fit's schedule has it after `it` iterations."""
    like = sched.state_dict()
    if not isinstance(sd, dict) or sd.keys() != like.keys():
        raise bad(f"{name} is not this fit's learning-rate schedule")
    expect = dict(like, last_epoch=it, _step_count=it + 1, _last_lr=_scheduled_lrs(sched, it))
    for k, v in expect.items():
        if k in sd and not _same(sd[k], v):
            raise bad(f"{name}'s {k} is {sd[k]!r:.40}, where this fit has {v!r:.40} at iteration {it}")


def _fit_round(pb: FitProblem, s: FitSettings, rnd: int, ckpt: dict | None, ckpt_path: Path,
               losses: dict[str, list[float]], seconds: dict[str, float], progress: ProgressFn | None) -> int:
    """One round: stage 1 (v0 per video, E frozen at its current value up to the level of
    stage1_level), then stage 2 (E, v0 frozen or refined). `ckpt`: a checkpoint of this
    round to continue from (checked by _check_checkpoint). Adds the stages' losses and
    seconds; returns the stage-2 steps skipped for a non-finite gradient."""
    tag = "" if s.rounds == 1 else f" {rnd + 1}/{s.rounds}"
    # ---- stage 1: initial velocity per video, E's field frozen (its level fitted with stage1_level)
    t0 = time.perf_counter()
    start = 0
    optimizers = _stage_optimizers(pb, s, "velocity")
    opt, sched = optimizers[""]
    opt_l, sched_l = optimizers.get("_l", (None, None))
    if ckpt is not None:
        if ckpt["stage"] == "velocity":
            for suffix, (o, sc) in optimizers.items():
                o.load_state_dict(ckpt["optimizer" + suffix])
                sc.load_state_dict(ckpt["scheduler" + suffix])
            start = ckpt["iteration"]
        else:
            start = s.velocity_iters
    for it in range(start, s.velocity_iters):
        loss = velocity_iteration(pb)
        _clip_and_step(list(pb.velocities.parameters()), opt, sched, s.grad_clip)
        if opt_l is not None:
            _clip_and_step([pb.log_e_level], opt_l, sched_l, math.inf)
        losses["velocity"].append(loss)
        if progress:
            progress("velocity" + tag, it + 1, s.velocity_iters, loss)
        if (it + 1) % s.checkpoint_every == 0 and it + 1 < s.velocity_iters:
            _save_checkpoint(ckpt_path, pb, "velocity", it + 1, optimizers, losses, rnd=rnd)
    if s.stage1_level and (ckpt is None or ckpt["stage"] == "velocity"):
        losses.setdefault("stage1_level", []).append(fold_level(pb))
    seconds["velocity"] = seconds.get("velocity", 0.0) + time.perf_counter() - t0

    # ---- stage 2: material (v0 frozen, or refined at a lower rate)
    t0 = time.perf_counter()
    with torch.no_grad():
        v0s = [pb.driver_v0(i).detach() for i in range(len(pb.videos))]
    optimizers = _stage_optimizers(pb, s, "material")
    opt, sched = optimizers[""]
    opt_r, sched_r = optimizers.get("_r", (None, None))
    opt_v, sched_v = optimizers.get("_v", (None, None))
    start = 0
    if ckpt is not None and ckpt["stage"] == "material":
        for suffix, (o, sc) in optimizers.items():
            o.load_state_dict(ckpt["optimizer" + suffix])
            sc.load_state_dict(ckpt["scheduler" + suffix])
        start = ckpt["iteration"]
    skipped = 0
    for it in range(start, s.material_iters):
        if it == 0 and start == 0:
            _save_checkpoint(ckpt_path, pb, "material", 0, optimizers, losses, rnd=rnd)
        horizon = None if it >= s.material_iters - s.polish_iters else s.material_horizon
        loss = material_iteration(pb, None if s.refine_velocity else v0s, horizon)
        if not _clip_and_step(list(pb.material.parameters()), opt, sched, s.grad_clip):
            skipped += 1
        if opt_v is not None:
            _clip_and_step(list(pb.velocities.parameters()), opt_v, sched_v, s.grad_clip)
        if opt_r is not None and not _clip_and_step([pb.log_e_residual], opt_r, sched_r, math.inf):
            skipped += 1
        if opt_r is not None and s.residual_diffusion > 0:
            pb.diffuse_residuals(s.residual_diffusion)
        losses["material"].append(loss)
        if progress:
            progress("material" + tag, it + 1, s.material_iters, loss)
        if (it + 1) % s.checkpoint_every == 0 and it + 1 < s.material_iters:
            _save_checkpoint(ckpt_path, pb, "material", it + 1, optimizers, losses, rnd=rnd)
    seconds["material"] = seconds.get("material", 0.0) + time.perf_counter() - t0
    return skipped


class FitLearnsNothing(PdToolError):
    """The fit's inputs cannot move its loss: nothing to see, nothing free to move, no motion."""


# Thresholds of the "learns nothing" checks. Frames and masks are read from 8-bit files, so
# half a level (0.5/255) is the finest difference they hold: a rendered change below it is
# not in the data.
_PIXEL_LEVEL = 0.5 / 255
# A reference video "shows no motion" when no pixel of any frame differs from frame 0 by more
# than this. Image frames are each stored on their own, so a still scene repeats frame 0 to
# within 8-bit rounding. A video file's codec adds noise to a still scene: libx264 on a
# still 256-px plant reached 3/255 at crf 18, 9/255 at crf 23 and 22/255 at crf 35. A swaying
# plant changes its edge pixels by far more: 60-200/255 in the tests' 24-32 px videos, over
# 200/255 at 256 px, in PNG frames and in mp4 at every crf tried.
_STILL_FRAMES = 4.0 / 255
_STILL_VIDEO_FILE = 32.0 / 255
# A video whose masks hold less than one whole pixel of weight over every compared frame
# leaves the loss nothing to compare (frame_loss gives 0 for an empty mask).
_MIN_MASK_PIXELS = 1.0
# After the fit: a loss history "did not move" when its spread is within this fraction of its
# size. Adam moves every parameter with a non-zero gradient by about its lr, which changes the
# loss by far more; a loss the parameters cannot reach stays the same bit for bit.
_FLAT_LOSS = 1e-6


def check_videos_can_teach(videos: list) -> None:
    """Refuse (FitLearnsNothing, one line) a reference video the fit cannot learn from,
    before any simulation: every mask of the compared frames (1 on) black, or no motion
    (no pixel, inside the masks, changes from frame 0 by more than a few 8-bit levels)."""
    for v in videos:
        frames = v.frames[1:]
        weight = None
        if v.masks is not None:
            weight = v.masks[1:]
            total = float(weight.sum())
            if total < _MIN_MASK_PIXELS:
                raise FitLearnsNothing(
                    f"{v.folder / 'masks'}: every mask of frames 1-{v.num_frames - 1} is black (no pixel marks "
                    f"the object), so the fit has nothing to compare; paint the object white in the masks, or "
                    f"remove masks/ to fit on whole frames")
        largest = 0.0
        for k in range(len(frames)):  # a frame at a time: no second copy of the whole video
            change = (frames[k] - v.frames[0]).abs().amax(dim=-1)  # [H, W], the largest channel change
            if weight is not None:
                change = change * (weight[k] > 0)
            largest = max(largest, float(change.max()))
        from pd_tool.video.folder import VIDEO_EXTS

        source = v.frame_paths[0] if len(v.frame_paths) == 1 and v.frame_paths[0].suffix.lower() in VIDEO_EXTS \
            else v.folder
        if largest <= (_STILL_VIDEO_FILE if source != v.folder else _STILL_FRAMES):
            where = " inside the masks" if weight is not None else ""
            raise FitLearnsNothing(
                f"{source}: no frame differs from frame 0 by more than {largest * 255:.1f}/255{where}, so the "
                f"video shows no motion to fit; pass a video of the object moving (frame 0 at rest)")


@torch.no_grad()
def check_fit_can_learn(pb: FitProblem) -> None:
    """Refuse (FitLearnsNothing, one line) a fit whose simulation cannot change what its
    videos compare, before any simulation: every particle static (bake refuses the same
    scene: nothing can move), or, per video, the moving Gaussians out of the camera's view
    (all behind it, or all outside the image) or changing no pixel of the rest frame inside
    the masks (hidden, masked out, transparent)."""
    if not (~pb.static).any():
        o = pb.prep.options
        region = " and ".join(f"--{k.replace('_', '-')} {getattr(o, k)}" for k in ("static_below", "static_box")
                              if getattr(o, k) is not None)
        raise FitLearnsNothing(f"every particle is static ({region or 'the static region'} pins all "
                               f"{len(pb.prep.static):,}), so nothing can move; shrink the static region "
                               f"(--static-below / --static-box)")
    p = pb.prep
    fg = torch.as_tensor(p.foreground, dtype=torch.long, device=pb.scene.positions.device)
    moving = fg[torch.as_tensor(~p.static[: len(p.foreground)], device=fg.device)]
    sc = pb.scene
    for v in pb.videos:
        cam = v.camera
        near = 0.01  # the rasteriser's near plane (pd_tool.render.render), world units
        with np.errstate(divide="ignore", invalid="ignore"):  # a centre on the camera's plane: u, v infinite
            uvz = torch.as_tensor(cam.project(sc.positions[moving].detach().double().cpu().numpy()))
        front = uvz[:, 2] > near
        # a Gaussian reaches 3 sigma past its centre on screen
        reach = 3.0 * sc.scales[moving].detach().double().cpu().amax(dim=1) * max(cam.fx, cam.fy) / uvz[:, 2].clamp_min(near)
        inside = front & (uvz[:, 0] + reach >= 0) & (uvz[:, 0] - reach <= cam.width) \
            & (uvz[:, 1] + reach >= 0) & (uvz[:, 1] - reach <= cam.height)
        what = f"{v.folder}: the moving part of the scene ({len(moving):,} Gaussians)"
        fix = (f"so the fit cannot see it move; use the camera frame 0 was seen with ({v.camera_path}), "
               f"or check the static region")
        if not front.any():
            raise FitLearnsNothing(f"{what} is behind the camera, {fix}")
        if not inside.any():
            raise FitLearnsNothing(f"{what} lies outside the camera's {cam.width}x{cam.height} image, {fix}")
        from pd_tool.render import render

        shown = render(sc.positions, sc.quats, sc.scales, sc.opacities, sc.sh, cam, background=pb.s.background).rgb
        opacity = sc.opacities.clone()
        opacity[moving] = 0.0
        hidden = render(sc.positions, sc.quats, sc.scales, opacity, sc.sh, cam, background=pb.s.background).rgb
        change = (shown - hidden).abs().amax(dim=-1)  # [H, W]
        if v.masks is not None:
            # SSIM compares 11-px windows (pd_tool.fit.losses), so a change up to 5 px outside
            # a mask still reaches the loss
            seen = (v.masks[1:] > 0).any(dim=0).float()[None, None]
            seen = torch.nn.functional.max_pool2d(seen, 11, stride=1, padding=5)[0, 0] > 0
            change = change * seen.to(change.device)
        if float(change.max()) <= _PIXEL_LEVEL:
            masked = " inside the masks" if v.masks is not None else ""
            raise FitLearnsNothing(f"{what} changes no pixel of the rest frame{masked} (hidden, masked out or "
                                   f"transparent), {fix}")


def _check_learned(ckpt_path: Path, losses: dict[str, list[float]]) -> None:
    """After the fit, before anything is written: refuse (FitLearnsNothing) when every loss
    history of two or more iterations stayed flat, i.e. the videos gave the fit no gradient
    (E may still have moved, under the smoothness terms alone). The checkpoint, pdtool's
    own, goes too: nothing is left."""
    judged = {k: [x for x in losses[k] if math.isfinite(x)] for k in ("velocity", "material", "calibrate")
              if len(losses.get(k, [])) >= 2}
    if not judged:
        return  # one iteration per stage: a loss cannot be seen to move or not
    for h in judged.values():
        if len(h) >= 2 and max(h) - min(h) > _FLAT_LOSS * max(abs(x) for x in h):
            return
    _remove_own_checkpoint(ckpt_path)
    k, h = max(judged.items(), key=lambda kv: len(losses[kv[0]]))
    at = f"stayed at {h[0]:.6g}" if h else "was NaN"
    raise FitLearnsNothing(
        f"the fit learned nothing: its {k} loss {at} over {len(losses[k])} iterations, so the videos do not "
        f"constrain the moving part (out of view, masked out or still); nothing was written; check the camera, "
        f"masks/ and the static region")


def _check_destination(out: Path, ckpt_path: Path) -> None:
    """Before any work: the checkpoint's path holds nothing but a pdtool checkpoint (a fit
    replaces and deletes that file, so it must be pdtool's own), and out's folder takes new
    files (a read-only folder is found now, not at the first checkpoint)."""
    from pd_tool.core.atomic import check_destination
    from pd_tool.fit.checkpoint import is_pdtool_checkpoint

    if ckpt_path.exists() or ckpt_path.is_symlink():
        ours, what = is_pdtool_checkpoint(ckpt_path)
        if not ours:
            raise _foreign_checkpoint(ckpt_path, what)
    check_destination(out)


def _remove_own_checkpoint(path: Path) -> None:
    from pd_tool.fit.checkpoint import is_pdtool_checkpoint

    if is_pdtool_checkpoint(path)[0]:
        path.unlink()


def run_fit(
    scene: GaussianScene,
    scene_path: str | Path,
    videos: list,
    out: str | Path,
    *,
    prepare_options: PrepareOptions | None = None,
    settings: FitSettings | None = None,
    progress: ProgressFn | None = None,
    resume: bool = False,
) -> FitResult:
    """Fit and write the material file `out` (.pdmat). A checkpoint `out`.ckpt is kept
    while fitting (every settings.checkpoint_every iterations) and removed at the end;
    resume=True continues from it."""
    from pd_tool.materials.file import MaterialFile, scene_fingerprint

    s = (settings or FitSettings()).resolved()
    out = Path(out)
    ckpt_path = out.with_name(out.name + ".ckpt")
    if s.velocity_iters + s.material_iters + s.calibrate_iters == 0:
        raise FitLearnsNothing("--velocity-iters 0 and --material-iters 0 leave nothing to fit (the material file "
                               "would hold the starting E); give at least one iteration")
    _check_destination(out, ckpt_path)
    pb = FitProblem(scene, videos, prepare_options or PrepareOptions(), s)  # refuses what cannot fit in memory
    check_videos_can_teach(videos)
    check_fit_can_learn(pb)
    losses: dict[str, list[float]] = {"velocity": [], "material": []}
    seconds: dict[str, float] = {}
    pb.resume_key = _resume_key(pb, scene_path)
    ckpt = _load_checkpoint(ckpt_path, pb, s) if resume else None
    if ckpt is not None:
        # _check_checkpoint matched every tensor's shape and dtype to this fit's, so these loads
        # cannot fail on the data; torch may still refuse an RNG state it cannot use
        pb.material.load_state_dict(ckpt["material"])
        pb.velocities.load_state_dict(ckpt["velocities"])
        losses = ckpt["losses"]
        try:
            torch.set_rng_state(ckpt["torch_rng"])
        except (RuntimeError, ValueError, TypeError):
            from pd_tool.fit.checkpoint import CheckpointError

            raise CheckpointError(f"{ckpt_path}: its random-number state is not one torch accepts; "
                                  f"{_RESUME_FIX}") from None
        with torch.no_grad():
            pb.log_e_residual.copy_(ckpt["residual"].to(pb.device))
            pb.log_e_level.copy_(ckpt["level"].to(pb.device))

    skipped = 0
    resume_round = ckpt["round"] if ckpt is not None else 0
    for rnd in range(s.rounds):
        if rnd < resume_round:
            continue
        skipped += _fit_round(pb, s, rnd, ckpt if rnd == resume_round else None, ckpt_path, losses, seconds,
                              progress)
        ckpt = None

    E_uncalibrated = None
    calibration = None
    if s.calibrate_iters > 0:
        t0 = time.perf_counter()
        with torch.no_grad():
            E_uncalibrated = pb.driver_E().double().cpu().numpy()
        calibration = calibrate(pb, s, progress)
        losses["calibrate"] = calibration["losses"]
        seconds["calibrate"] = time.perf_counter() - t0

    # ---- result
    with torch.no_grad():
        v0s = [pb.driver_v0(i).detach() for i in range(len(videos))]
        driver_E = pb.driver_E().double().cpu().numpy()
        v0_mean = torch.stack(v0s).mean(0).cpu().numpy()
    _check_learned(ckpt_path, losses)
    p = pb.prep
    labels = pb.drivers.labels.cpu().numpy()[: p.count]  # the Gaussians' drivers (filled particles follow)
    meta: dict[str, Any] = {
        "scene_sha256": scene_fingerprint(scene_path),
        "scene_path": str(Path(scene_path).resolve()),
        "prepare": p.options.to_dict(),
        "transform": p.transform.to_dict(),
        "nu": s.nu, "density": s.density, "damping": s.damping,
        "drivers": {"count": int(len(driver_E)), "ratio": s.driver_ratio, "seed": s.seed},
        # what a bake needs to simulate as the fit did (MaterialFile.fit_simulation)
        "simulation": {"grid_res": int(p.options.grid_res), "driver_ratio": s.driver_ratio, "driver_seed": s.seed,
                       "cfl_safety": float(pb.cfl_safety)},
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(s).items()},
        "videos": [str(v.folder) for v in videos],
        "metrics": {
            "loss_velocity_first": losses["velocity"][0] if losses["velocity"] else None,
            "loss_velocity_last": losses["velocity"][-1] if losses["velocity"] else None,
            "loss_material_first": losses["material"][0] if losses["material"] else None,
            "loss_material_last": losses["material"][-1] if losses["material"] else None,
            "skipped_material_steps": skipped,
            "stage1_levels": losses.get("stage1_level"),  # nats per round, with stage1_level
            "calibration": None if calibration is None else {
                k: calibration[k] for k in ("offsets", "gains", "cluster_sizes") if k in calibration},
        },
        "fields": {"material": pb.material.config(),
                   **{f"velocity{i}": v.config() for i, v in enumerate(pb.velocities)}},
    }
    fields = {"material": {k: v.detach().cpu().numpy() for k, v in pb.material.state_dict().items()}}
    for i, v in enumerate(pb.velocities):
        fields[f"velocity{i}"] = {k: t.detach().cpu().numpy() for k, t in v.state_dict().items()}
    mf = MaterialFile(driver_E=driver_E, driver_v0=v0_mean,
                      driver_rest=p.transform.to_scene(pb.x_rest.double().cpu().numpy()), meta=meta, fields=fields)
    mf.save(out)
    _remove_own_checkpoint(ckpt_path)
    report = list(p.report)
    for i, g in enumerate(pb.gains):
        if float((g - 1.0).abs().max()) > 0.02:  # a camera that differs visibly from the splat's colours
            report.append(f"video {i}: exposure matched at rest, gain {' / '.join(f'{x:.2f}' for x in g.tolist())} "
                          f"(r / g / b; --no-match-exposure turns it off)")
    return FitResult(material_path=out, driver_E=driver_E, driver_v0=v0s[0].double().cpu().numpy(),
                     gaussian_E=driver_E[labels], losses=losses,
                     seconds=seconds, prep=p, drivers=pb.drivers, report=report, skipped_steps=skipped,
                     driver_v0s=[v.double().cpu().numpy() for v in v0s],
                     driver_E_uncalibrated=E_uncalibrated, calibration=calibration, settings=s,
                     cfl_safety=float(pb.cfl_safety), substeps=pb.substeps_range)
