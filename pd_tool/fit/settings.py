"""The fit's settings (FitSettings): what `pdtool fit` and its presets can change.

Units throughout: E in Pa, velocities in m/s, learning rates per optimiser step, log-E
quantities in nats.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from pd_tool.materials.presets import DRIVERS_PER_CELL_RANGE, fit_min_per_cell, fit_simulation, load_preset


@dataclass
class FitSettings:
    """Settings of a fit. Iteration counts and the driver ratio default to the quality
    preset's (`resolved` fills them in).

    Units: E in Pa, velocities in m/s, lr per optimiser step.
    """

    quality: str = "default"
    velocity_iters: int | None = None
    material_iters: int | None = None
    # Frames after the rest frame that stage 1 matches (the paper's 3). v0 is fitted under the
    # starting E; the further the clip runs, the less a v0 that makes up for a wrong E can
    # match it. With whole-clip stage 2 below, six frames bring the fit on clean videos of its
    # own discretisation from 0.73 / 0.65 to 0.58 / 0.42 nats of the truth (plant / tree
    # smooth); with one-frame stage 2 they do not help (docs/fitting.md).
    stage1_frames: int = 6
    # Frames a stage-2 loss reaches back through the state (None: all; the paper's 1). A
    # truncated gradient stops where it vanishes, not where the loss is least: E that acts
    # through the whole motion (a stiff stem sets its frequency, hence the phase of later
    # frames) is under-counted by it. Given the true pushes, whole-clip gradients bring
    # E within 0.42-0.49 nats of the truth on clean videos of the fit's own discretisation,
    # one-frame gradients 0.71-1.08. Together with six stage-1 frames they bring the fit
    # against a converged truth closer on nine rows of ten (docs/benchmarks.md).
    material_horizon: int | None = None
    # The last this many stage-2 iterations back-propagate through every frame, whatever
    # material_horizon says (for a truncated horizon). Counted within material_iters.
    polish_iters: int = 0
    # Least substeps per frame; None: as the CFL condition for the current E chooses each
    # iteration. MPM's numerical damping grows with the substep count, so a floor above the
    # CFL choice keeps the count, and the damping, fixed while E moves. The CFL count still
    # wins where E rises above what the floor allows (a fixed count would blow up there).
    substeps: int | None = None
    refine_velocity: bool = False  # stage 2 also refines v0 (the paper freezes it)
    # Stage 2's steps need not lower the whole-clip loss: one-frame gradients can lower every
    # step's loss while the clip as a whole drifts away (on the donut of bench/fit_truth.py
    # one of two runs ended above its start), and Adam's fixed-size steps can overshoot on
    # whole-clip ones. Every this many stage-2 iterations, and at its end, the whole-clip loss
    # is measured, and the round keeps the state that scored lowest, its start included. A
    # measure costs one stage-2 iteration's forward pass, or nothing where the next iteration
    # back-propagates through every frame: its own loss is the measure. 0: keep the last state.
    keep_best_every: int = 10
    # When stage 2 keeps its start (no measure beat it: its first steps overshot and it never
    # came back), it runs again from the start with every step size times this: the halving
    # of a backtracking line search. Once, in a fit of one round; 0: off. The retry is step-
    # bound (its last iteration is its best), so the largest step that does not overshoot
    # goes furthest: on the 100k plant's two seeds of eight that kept their start, half the
    # step ends 58-65x below the uniform start under a new force, a third 32x, a tenth 24x,
    # keeping the start 20x (docs/fitting.md).
    retry_step: float = 0.5
    # The fit's CFL substeps come from this quantile of the moving drivers' wave speeds (1:
    # the fastest, as a bake does). MPM loses energy in every transfer, so the count sets the
    # model's damping; with the maximum, a few outlying stiff drivers set it for the whole
    # object (at 100k: 180 substeps per frame under the fitted E against 75 under the truth).
    cfl_quantile: float = 1.0
    # Rounds of (stage 1, stage 2). Stage 1 fits v0 under the starting E, so a wrong E biases
    # v0, and stage 2 then fits E to the biased v0; each later round refits v0 under the
    # fitted E. 1, the paper's: with two videos at 100k a second round brings every region
    # within 10% on five seeds but makes the new-force motion worse on every seed compared
    # (docs/benchmarks.md, fit recovery).
    rounds: int = 1
    # The first round fits E's field alone (no per-driver residuals, no stage-1 level), and
    # the later rounds add the residuals on top of the field it found (round_settings);
    # needs rounds >= 2. With residual_decay the residuals are pulled back to that field. A
    # diagnostic setting (bench/fit_truth.py --set), off by default.
    field_first: bool = False
    # Stage 1 also fits one log-E offset shared by every driver (a level, not a field; the
    # paper freezes E there: False). Stage 1 fits v0 under the starting E; when that E is too
    # soft, a slower push matches the first frames (v0 7-11% slow at 100k, docs/fitting.md)
    # and stage 2 then softens the stem to match it. One number cannot take on the field's
    # shape, unlike the whole field (1.33x against 3.49x at the quick scale). Folded into the
    # per-driver residuals when stage 1 ends. It lowers the recovery benchmark's new-force
    # error on eight of nine seeds at 100k (5.11x against 4.46x on average; docs/benchmarks.md).
    stage1_level: bool = True
    lr_level: float = 0.05  # Adam step of the level, nats of E
    # Stage 3, calibration: iterations of the exact whole-clip gradient over a few numbers
    # only, one log-E offset per stiffness cluster and one log speed gain per video (see
    # `pd_tool.fit.stages.calibrate`). 0: off.
    calibrate_iters: int = 0
    calibrate_clusters: int = 4  # stiffness clusters of the fitted field (1-D k-means on log E)
    lr_calibrate: float = 0.02  # Adam step, in log units (nats) of E and of v0's speed (0.05 overshoots)
    # Per-driver log-E residual on top of the field. The field's parameters are shared by
    # every point, so the region with the largest gradient (the stem) moves them all; a
    # residual per driver lets each region follow its own gradient sign (see docs/fitting.md).
    driver_residual: bool = True
    lr_residual: float = 0.15
    # Adam's eps for the residuals. A driver whose gradient is below it takes proportionally
    # shorter steps; at 100k the leaves' and the flower's gradients are 1e-9 to 1e-7
    # (bench/fit_recovery.py --residual-gradients), so torch's 1e-8 would hold the leaves near
    # the start. With the diffusion below, 1e-16 brings every region within 10%
    # (docs/benchmarks.md, fit).
    residual_eps: float = 1e-16
    # Weight of the mean squared residual difference between neighbouring drivers (a
    # diagnostic setting, 0 by default). Adam normalises its gradient per driver against the
    # video's, which is 100x weaker on a leaf than on the stem, so the penalty holds the
    # leaves back and hardly the stem; residual_diffusion smooths the residuals instead.
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
    # Decoupled weight decay of the residuals (AdamW, 0: off): each stage-2 step multiplies
    # them by 1 - lr_t * residual_decay, a pull back to the field in nats that, unlike a
    # penalty in the loss, Adam's per-driver scaling does not undo. A driver whose video
    # gradient keeps one sign settles near 1 / residual_decay nats from the field; one whose
    # gradient changes sign returns to it. A diagnostic setting (bench/fit_truth.py --set).
    residual_decay: float = 0.0
    # One residual per part instead of per driver (0: per driver): the moving drivers split
    # into this many k-means parts by rest position, and after each residual step every
    # driver takes its part's mean. Fewer unknowns than drivers, so the videos pin each one
    # down more firmly, while a part can still differ from its neighbour as a region does.
    # Static drivers keep their own residual (nothing moves them). A diagnostic setting.
    residual_parts: int = 0
    # How far the residuals' step shares Adam's second moment over all drivers (0: Adam, each
    # driver normalised by its own; 1: one normaliser for all; PooledAdam). Adam steps every
    # driver about lr_residual a step wherever its gradient points, so near the answer, where
    # the gradients are small, E scatters; shared, a driver with a weak gradient steps less,
    # and E keeps its pattern, but a region whose gradient is weak throughout (thin leaves)
    # barely leaves the start. A diagnostic setting (docs/fitting.md, residual pool).
    residual_pool: float = 0.0
    # Pool within this many k-means parts of the moving drivers (by rest position) instead of
    # over all drivers (0: all). A part's drivers share their own scale, so a region whose
    # gradients are all weak (a leaf) still steps as Adam would, while within it a driver
    # with a weaker gradient than its neighbours steps less. Static drivers keep Adam. A
    # diagnostic setting.
    residual_pool_parts: int = 0
    refine_velocity_factor: float = 0.5  # v0's stage-2 step size, as a fraction of lr_velocity
    lr_velocity: float = 2e-2
    lr_material: float = 5e-2
    warmup: int = 3  # iterations of linear warm-up per stage
    grad_clip: float = 1.0
    tv_weight: float = 1e-4
    loss_lambda: float = 0.1
    init_E: float = 1e6  # Pa, the uniform starting value (and the baseline it is compared with)
    # A material file (.pdmat) of the same scene to start from instead of the uniform init_E:
    # each driver takes its nearest fitted driver's E (a warm start). With material_iters 0 and
    # stage1_level off only v0 is fitted, under that E, and losses["final"] says how well that
    # E explains the videos (bench/fit_truth.py --losses compares the truth's E with the fit's).
    init_material: str | None = None
    E_min: float = 1e3  # Pa, bounds of the material field
    E_max: float = 1e8
    velocity_scale: float = 1.0  # m/s per unit of the velocity field's output
    velocity_resolution: int = 24  # triplane texels per side of the v0 field (paper: 24)
    material_resolution: int = 8  # ... of the E field (paper: 8)
    nu: float = 0.3
    density: float = 1000.0  # kg/m^3
    damping: float = 0.0  # 1/s
    driver_ratio: float | None = None  # None: the quality preset's
    # drivers in each cell the moving particles occupy, at least (PreparedScene.build_drivers);
    # None: the quality preset's fit_min_drivers_per_cell
    min_drivers_per_cell: float | None = None
    working_long_side: int = 256  # px, reference frames are resized to this
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    # Scale each video's render by a gain per colour channel, fitted once at rest (frame 0),
    # so that a camera's exposure and white balance do not count as motion error. Without
    # it, a video 10% darker than the splat leaves the loss at 0.067 on a 3,000-Gaussian
    # plant and the fit drives E up until nothing moves (bench/fit_truth.py).
    match_exposure: bool = True
    seed: int = 0
    device: str = "cpu"
    checkpoint_every: int = 5  # iterations between checkpoints (bounded loss of work on a kill)
    # Memory for the frames the simulation's forward stores so that their backward need not
    # recompute them (SimConfig.keep_budget_mb), MB. None: half of what the fit's memory
    # estimate leaves free, at most 1 GB of RAM on the CPU (prepare/memory.py); 0: every
    # backward recomputes its frame (the same gradients, more time). A cap for a GPU shared
    # with other work.
    stored_frames_mb: float | None = None

    def measure_points(self) -> list[int]:
        """The stage-2 iterations after which a round measures its whole-clip loss for
        keep_best_every (the last always; none when it is 0); of resolved settings."""
        n, every = int(self.material_iters or 0), self.keep_best_every
        return [k for k in range(1, n + 1) if k % every == 0 or k == n] if every > 0 else []

    def horizon_at(self, it: int) -> int | None:
        """Frames stage-2 iteration `it` (0-based) back-propagates through (None: all): the
        last polish_iters reach every frame; of resolved settings."""
        return None if it >= int(self.material_iters or 0) - self.polish_iters else self.material_horizon

    def borrowed_points(self) -> list[int]:
        """The measure points whose whole-clip loss is the next iteration's own: an iteration
        that back-propagates through every frame simulates the whole clip from the state
        before its step, so measuring that state again would repeat its forward pass. Every
        point but the last (no iteration follows it) where that iteration's horizon is None;
        of resolved settings."""
        n = int(self.material_iters or 0)
        return [p for p in self.measure_points() if p < n and self.horizon_at(p) is None]

    def borrows_start(self) -> bool:
        """Whether stage 2's first iteration back-propagates through every frame, so that its
        own loss is the whole-clip loss of the state the stage starts from (the start's
        measure, taken as it goes rather than simulated on its own); of resolved settings."""
        return int(self.material_iters or 0) > 0 and self.horizon_at(0) is None

    def whole_clip_measures(self) -> int:
        """Whole-clip losses a fit simulates on their own (every frame, forward only): stage
        2's start (in every round when keeping the best state, else the first) unless its
        first iteration measures it (borrows_start), each round's measure points but the
        borrowed ones, and the result, which reuses the kept state's measure unless
        calibration moved E after it; of resolved settings. A stage 2 run again (retry_step)
        is not foreseen here."""
        points = self.measure_points()
        start = 0 if self.borrows_start() else 1
        own = start + len(points) - len(self.borrowed_points())
        starts = (self.rounds * own if points else start) if self.material_iters else 0
        return starts + (0 if points and not self.calibrate_iters else 1)

    def with_step_scale(self, factor: float) -> "FitSettings":
        """These settings with stage 2's step sizes (the E field's, the residuals' and v0's
        refinement) times `factor`."""
        return replace(self, lr_material=self.lr_material * factor, lr_residual=self.lr_residual * factor,
                       refine_velocity_factor=self.refine_velocity_factor * factor)

    def to_dict(self) -> dict[str, Any]:
        """Every field, JSON-ready (tuples as lists): a material file's and a checkpoint's
        record of what the fit ran at. from_dict reads it back."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "FitSettings":
        """The settings a to_dict recorded; keys that name no field (a file written by
        another version of pdtool) are left out, and fields it lacks take their defaults."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items() if k in names})

    def round_settings(self, rnd: int) -> "FitSettings":
        """The settings round `rnd` (0-based) runs with: with field_first, round 0 fits the
        field alone (no residual step, no stage-1 level); otherwise these."""
        if self.field_first and rnd == 0:
            return replace(self, driver_residual=False, stage1_level=False)
        return self

    def resolved(self) -> FitSettings:
        """These settings with every default filled in from the quality preset; ValueError
        (one line) for a value out of range or a combination the fit cannot run."""
        q = load_preset("quality", self.quality)
        out = FitSettings(**asdict(self))
        if out.rounds < 1:
            raise ValueError(f"rounds must be at least 1, got {out.rounds}")
        if out.field_first and (out.rounds < 2 or not out.driver_residual or out.init_material is not None):
            raise ValueError(f"field_first fits the field alone in the first round and adds the per-driver residuals "
                             f"after it: it needs rounds >= 2 (got {out.rounds}), driver_residual on and no init_material")
        if out.keep_best_every < 0:
            raise ValueError(f"keep_best_every must be at least 0 (0: off), got {out.keep_best_every}")
        if not (math.isfinite(out.retry_step) and 0.0 <= out.retry_step < 1.0):
            raise ValueError(f"retry_step must be in [0, 1) (a fraction of stage 2's step; 0: no retry), "
                             f"got {out.retry_step}")
        if out.polish_iters < 0:
            raise ValueError(f"polish_iters must be at least 0, got {out.polish_iters}")
        if not 0.0 < out.cfl_quantile <= 1.0:
            raise ValueError(f"cfl_quantile must be in (0, 1], got {out.cfl_quantile}")
        if not (math.isfinite(out.residual_diffusion) and out.residual_diffusion >= 0.0):
            raise ValueError(f"residual_diffusion must be >= 0 (grid cells squared), got {out.residual_diffusion}")
        if not (math.isfinite(out.residual_decay) and out.residual_decay >= 0.0):
            raise ValueError(f"residual_decay must be >= 0 (per unit step), got {out.residual_decay}")
        if not (math.isfinite(out.residual_pool) and 0.0 <= out.residual_pool <= 1.0):
            raise ValueError(f"residual_pool must be in [0, 1] (0: Adam per driver), got {out.residual_pool}")
        if out.residual_pool_parts < 0:
            raise ValueError(f"residual_pool_parts must be >= 0 (0: pool over all drivers), got {out.residual_pool_parts}")
        if out.residual_parts < 0:
            raise ValueError(f"residual_parts must be >= 0 (0: one residual per driver), got {out.residual_parts}")
        if not out.residual_eps > 0:
            raise ValueError(f"residual_eps must be > 0, got {out.residual_eps}")
        if out.stored_frames_mb is not None and not (math.isfinite(out.stored_frames_mb)
                                                     and out.stored_frames_mb >= 0.0):
            raise ValueError(f"stored_frames_mb must be >= 0 (MB), or None for the automatic budget, "
                             f"got {out.stored_frames_mb}")
        if out.calibrate_iters < 0:
            raise ValueError(f"calibrate_iters must be at least 0, got {out.calibrate_iters}")
        if out.calibrate_clusters < 1:
            raise ValueError(f"calibrate_clusters must be at least 1, got {out.calibrate_clusters}")
        if out.stage1_level and not out.driver_residual:
            raise ValueError("stage1_level folds its offset into the per-driver residuals; keep driver_residual on")
        if out.init_material is not None and not out.driver_residual:
            raise ValueError("init_material sets the per-driver residuals; keep driver_residual on")
        if out.calibrate_iters and not out.driver_residual:
            raise ValueError("calibration folds its offsets into the per-driver residuals; keep driver_residual on")
        if out.velocity_iters is None:
            out.velocity_iters = int(q["fit_velocity_iters"])
        if out.material_iters is None:
            out.material_iters = int(q["fit_material_iters"])
        if out.driver_ratio is None:
            out.driver_ratio = fit_simulation(q)[2]
        if out.min_drivers_per_cell is None:
            out.min_drivers_per_cell = fit_min_per_cell(q)
        lo, hi = DRIVERS_PER_CELL_RANGE
        if not lo <= out.min_drivers_per_cell <= hi:
            raise ValueError(f"min_drivers_per_cell must be in [{lo:g}, {hi:g}], got {out.min_drivers_per_cell}")
        return out
