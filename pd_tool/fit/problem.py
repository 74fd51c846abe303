"""The fit's differentiable forward (FitProblem): per-driver E and v0 from the fields ->
differentiable MPM (warp, checkpointed) -> rigid interpolation to every Gaussian ->
differentiable rasteriser -> lambda L1 + (1 - lambda) D-SSIM against the reference frame.

Shapes: Q drivers, F simulated Gaussians, images [H, W, 3] in 0-1. Units: E in Pa,
velocities in m/s, positions in the simulation box's metres, log E in nats.
"""
from __future__ import annotations

import math

import torch

from pd_tool.bake.animate import GaussianAnimator
from pd_tool.core.errors import VideoError
from pd_tool.core.scene import GaussianScene
from pd_tool.drivers import kmeans, knn
from pd_tool.fit.diffusion import diffuse, diffusion_fractions, part_means
from pd_tool.fit.fields import MaterialField, VelocityField
from pd_tool.fit.losses import frame_loss
from pd_tool.fit.settings import FitSettings
from pd_tool.materials.file import MaterialFile
from pd_tool.materials.presets import fit_simulation, load_preset
from pd_tool.prepare import memory
from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
from pd_tool.prepare.work import check_fit_work
from pd_tool.render import render
from pd_tool.sim import DiffSim, SimConfig, cfl_substeps_for, initial_state
from pd_tool.sim.autograd import State
from pd_tool.video.folder import ReferenceVideo


class FitProblem:
    """Everything one fit needs, set up once: preparation, drivers, videos, fields, sim.

    `settings` are resolved (FitSettings.resolved). Refuses (one line) a fit that would not
    fit in memory or would take longer than the work policy allows, before building drivers
    or a simulator, and videos of different frame rates.
    """

    def __init__(self, scene: GaussianScene, videos: list[ReferenceVideo], prep_options: PrepareOptions,
                 settings: FitSettings) -> None:
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
        drivers_per_particle = p.floor_ratio(settings.driver_ratio, settings.min_drivers_per_cell)
        need = memory.estimate_fit_memory(
            n_gaussians=scene.count, n_simulated=len(p.positions_sim), driver_ratio=drivers_per_particle,
            grid_dims=p.grid_dims,
            frames=[v.num_frames for v in videos], image_pixels=int(videos[0].frames[0].numel() // 3),
            stage1_frames=settings.stage1_frames, device=settings.device)
        available = memory.available_memory(settings.device)
        memory.check_memory(need, what="fit", quality=str(settings.quality), driver_ratio=settings.driver_ratio,
                            device=settings.device, resolution=f"--working-size {settings.working_long_side}",
                            available=available)
        # ... or when it would take longer than allowed
        check_fit_work(p, settings, videos, n_gaussians=scene.count, cfl_safety=self.cfl_safety,
                       drivers_per_particle=drivers_per_particle)
        self.drivers = p.build_drivers(ratio=settings.driver_ratio, seed=settings.seed, device=self.device,
                                       min_per_cell=settings.min_drivers_per_cell)
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
        # each driver's nearest other drivers, for the residuals' smoothing (penalty and
        # diffusion), and its mean distance to them (m), the spacing residual_diffusion scales by
        dist2, nearest = knn(self.x_rest, self.x_rest, k=min(7, len(self.x_rest)))
        self.driver_pairs = nearest[:, 1:]
        self.driver_spacing = dist2[:, 1:].sqrt().mean(dim=1)
        self.residual_parts = self._residual_parts(settings.residual_parts)
        self.pool_parts = self._residual_parts(settings.residual_pool_parts) if settings.residual_pool else None
        self.velocities = torch.nn.ModuleList(
            [VelocityField(settings.velocity_resolution, settings.velocity_scale) for _ in videos]).to(self.device)
        # frames stored for the backward fill half of what the estimate leaves free, unless set
        stored = settings.stored_frames_mb
        cfg = SimConfig(grid_res=max(p.grid_dims), domain=p.domain, nu=settings.nu, gravity=(0.0, 0.0, 0.0),
                        damping=settings.damping, cfl_safety=self.cfl_safety, min_substeps=settings.substeps,
                        keep_budget_mb=memory.stored_frames_budget_mb(need, available) if stored is None else stored)
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

    @torch.no_grad()
    def start_from(self, material: MaterialFile) -> None:
        """Start from a fitted material's E: each driver takes the E of the material's
        nearest driver (MaterialFile.E_at), kept inside the field's bounds."""
        rest = self.prep.transform.to_scene(self.x_rest.double().cpu().numpy())
        log_e = torch.log(torch.as_tensor(material.E_at(rest), dtype=torch.float32, device=self.device))
        self.set_driver_log_E(log_e.clamp(self.material.log_e_min, self.material.log_e_max))

    def residual_penalty(self) -> torch.Tensor:
        """FitSettings.residual_smoothness times the mean squared residual difference
        between neighbouring drivers (nats^2), a scalar."""
        r = self.log_e_residual
        return self.s.residual_smoothness * ((r[:, None] - r[self.driver_pairs]) ** 2).mean()

    def diffuse_residuals(self, cells2: float) -> None:
        """One diffusion step of the residuals over the driver graph (FitSettings.residual_diffusion)."""
        diffuse(self.log_e_residual.data, self.driver_pairs, diffusion_fractions(self.driver_spacing, self.prep.dx, cells2))

    def _residual_parts(self, k: int) -> torch.Tensor | None:
        """The k-means part [Q] of each driver by rest position (FitSettings.residual_parts and
        residual_pool_parts; static drivers -1), or None for k = 0."""
        moving = (~self.static).nonzero().squeeze(1)
        if k <= 0 or len(moving) == 0:
            return None
        _, labels = kmeans(self.x_rest[moving].double().cpu(), min(int(k), len(moving)), seed=self.s.seed)
        parts = torch.full((len(self.x_rest),), -1, dtype=torch.long)
        parts[moving.cpu()] = labels
        return parts.to(self.device)

    @torch.no_grad()
    def share_residuals(self) -> None:
        """Each moving driver's residual becomes its part's mean (FitSettings.residual_parts)."""
        parts = self.residual_parts
        if parts is None:
            return
        self.log_e_residual.data.copy_(part_means(self.log_e_residual.data, parts))

    def driver_v0(self, i: int) -> torch.Tensor:
        """Video i's initial velocity per driver [Q, 3], m/s; 0 on static drivers."""
        v = self.velocities[i](self.x_norm)
        return v * (~self.static).float()[:, None]

    def substeps(self, E: torch.Tensor, v0: torch.Tensor) -> int:
        """Substeps per frame that the CFL condition allows under driver E [Q] (Pa) and v0
        [Q, 3] (m/s), at least FitSettings.substeps; the range seen goes to the report."""
        vmax = float(v0.detach().norm(dim=1).max()) if len(v0) else 0.0
        n = cfl_substeps_for(E, self.sim, self.frame_dt, vmax, self.s.cfl_quantile)
        lo, hi = self.substeps_range or (n, n)
        self.substeps_range = (min(lo, n), max(hi, n))
        return n

    def initial_state(self, v0: torch.Tensor) -> State:
        """The drivers at rest, moving at v0 [Q, 3] m/s: (x [Q, 3], v, C [Q, 3, 3], F)."""
        return initial_state(self.x_rest, v0)

    def step(self, state: State, E: torch.Tensor, substeps: int, frame_index: int) -> State:
        """One video frame of simulation, differentiable in state and E."""
        return self.sim.frame(state, E.float(), self.frame_dt, substeps, t0=(frame_index - 1) * self.frame_dt,
                              frame_index=frame_index)

    def render(self, i: int, driver_positions: torch.Tensor) -> torch.Tensor:
        """The scene seen by video i's camera with its drivers at driver_positions [Q, 3]:
        image [H, W, 3] in 0-1, differentiable in the positions."""
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
        """Loss (scalar) of a render [H, W, 3], scaled by video i's exposure gain, against
        the video's frame k, inside its mask when it has one."""
        v = self.videos[i]
        mask = None if v.masks is None else v.masks[k]
        return frame_loss(image * self.gains[i], v.frames[k], mask, lam=self.s.loss_lambda)


def sequence_loss(pb: FitProblem, E: torch.Tensor, v0s: list[torch.Tensor], horizon: int | None) -> torch.Tensor:
    """Mean frame loss (scalar) over every frame of every video, simulated from rest with
    driver E [Q] (Pa) and each video's initial velocity v0s[i] [Q, 3] (m/s); the graph is
    cut every `horizon` frames (None: never), which truncates the gradient as stage 2 does."""
    total = torch.zeros((), device=pb.device)
    count = 0
    for i, video in enumerate(pb.videos):
        sub = pb.substeps(E, v0s[i])
        state = pb.initial_state(v0s[i])
        for k in range(1, video.num_frames):
            # Cut the graph every `horizon` frames, but never before the first frame: its loss
            # must still reach v0 when stage 2 refines it (a cut at k = 1 leaves v0 without gradient).
            if horizon is not None and k > 1 and (k - 1) % horizon == 0:
                state = tuple(t.detach() for t in state)
            state = pb.step(state, E, sub, k)
            total = total + pb.frame_loss(i, k, pb.render(i, state[0]))
            count += 1
    return total / max(count, 1)


@torch.no_grad()
def whole_clip_loss(pb: FitProblem, v0s: list[torch.Tensor]) -> float:
    """sequence_loss under the current driver E with no gradient horizon: every frame of
    every video simulated from rest in one go (FitResult.losses "start" and "final")."""
    return float(sequence_loss(pb, pb.driver_E(), v0s, None))
