"""The fit's stages, each an optimisation over FitProblem's forward:

1. velocity: E's field frozen at its current value; optimise each video's v0 field on the
   first `stage1_frames` frames with full back-propagation through the simulation, and
   (`stage1_level`, on by default; the paper has it off) one log-E offset shared by every
   driver, folded into E when the stage ends;
2. material: v0 frozen (or refined, `refine_velocity`); optimise the shared E field and the
   per-driver residuals over all frames, back-propagating through every frame (or, with a
   `material_horizon` of K frames, each K frames simulated from the detached state before
   them, the last `polish_iters` iterations through every frame); every `keep_best_every`
   iterations the whole clip's loss is measured (an iteration through every frame measures
   the state before its step as it goes), and the stage ends in the state that explained
   it best (`Kept`); a stage that kept its start runs once more from it at `retry_step`
   of its step sizes;
3. calibration (`calibrate_iters`): a few whole-clip numbers, one log-E offset per
   stiffness cluster of the fitted field and one speed gain per video, fitted with the
   exact gradient through every frame.

A round is stage 1 then stage 2 (`fit_round`); the run repeats it `rounds` times.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable

import torch

from pd_tool.fit.problem import FitProblem, sequence_loss, whole_clip_loss
from pd_tool.fit.schedule import make_optimizer, make_tensor_optimizer
from pd_tool.fit.settings import FitSettings

ProgressFn = Callable[[str, int, int, float], None]  # stage, iteration, total, loss
# A stage's optimisers and learning-rate schedules by checkpoint suffix (see stage_optimizers)
Optimizers = dict[str, tuple[Any, Any]]
# Called when a checkpoint is due: (stage, iterations done, the stage's optimisers, the loss
# histories, round, the state stage 2 keeps so far or None)
CheckpointFn = Callable[[str, int, Optimizers, dict[str, list[float]], int, "Kept | None"], None]


class Kept:
    """The stage-2 state with the lowest whole-clip loss measured so far in a round
    (keep_best_every): the E field's weights, the residuals and the velocity fields (which
    move only with refine_velocity), the loss and the stage-2 iteration it was measured
    after (0: the stage's start)."""

    ENTRIES = ("kept_material", "kept_velocities", "kept_residual", "kept_at")  # its checkpoint entries

    def __init__(self, material: dict, velocities: dict, residual: torch.Tensor, loss: float, iteration: int):
        self.material, self.velocities, self.residual = material, velocities, residual
        self.loss, self.iteration = loss, iteration

    @classmethod
    def of(cls, pb: FitProblem, loss: float, iteration: int) -> "Kept":
        def copy(sd: dict) -> dict:
            return {k: v.detach().clone() for k, v in sd.items()}
        return cls(copy(pb.material.state_dict()), copy(pb.velocities.state_dict()), pb.log_e_residual.detach().clone(),
                   loss, iteration)

    def offer(self, pb: FitProblem, loss: float, iteration: int) -> None:
        """Keep pb's state instead when `loss` is finite and lower (or the kept one is not finite)."""
        if Kept.prefers(loss, self.loss):
            vars(self).update(vars(Kept.of(pb, loss, iteration)))

    @staticmethod
    def prefers(loss: float, kept: float) -> bool:
        return math.isfinite(loss) and not loss >= kept

    @staticmethod
    def ranked_first(measures: list[float], iterations: list[int]) -> tuple[float, int]:
        """(loss, iteration) a round keeps of its measures, taken in order from its start."""
        best, at = measures[0], iterations[0]
        for loss, it in zip(measures[1:], iterations[1:]):
            if Kept.prefers(loss, best):
                best, at = loss, it
        return best, at

    def restore(self, pb: FitProblem) -> None:
        with torch.no_grad():
            pb.material.load_state_dict(self.material)
            pb.velocities.load_state_dict(self.velocities)
            pb.log_e_residual.copy_(self.residual)

    def to_state(self) -> dict[str, Any]:
        """Checkpoint entries, ENTRIES (pd_tool.fit.resume)."""
        return {"kept_material": self.material, "kept_velocities": self.velocities, "kept_residual": self.residual,
                "kept_at": torch.tensor([self.loss, float(self.iteration)], dtype=torch.float64)}

    @classmethod
    def from_state(cls, state: dict, device: torch.device | str) -> "Kept":
        loss, iteration = state["kept_at"].tolist()
        return cls({k: v.to(device) for k, v in state["kept_material"].items()},
                   {k: v.to(device) for k, v in state["kept_velocities"].items()},
                   state["kept_residual"].to(device), loss, int(iteration))


def current_v0s(pb: FitProblem) -> list[torch.Tensor]:
    """Each video's initial driver velocities [Q, 3] m/s, detached."""
    with torch.no_grad():
        return [pb.driver_v0(i).detach() for i in range(len(pb.videos))]


def _clip_and_step(params: list[torch.Tensor], opt: Any, sched: Any, clip: float) -> bool:
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


def material_iteration(pb: FitProblem, v0s: list[torch.Tensor] | None, horizon: int | None) -> float:
    """One stage-2 iteration over every frame of every video; returns the mean frame loss.
    v0s: the frozen initial velocities, [Q, 3] m/s per video, or None to take them (with
    gradients) from the velocity fields; horizon: frames the gradient reaches back (None: all)."""
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
    (docs/fitting.md). Full back-propagation over the per-driver field finds other
    minima (docs/benchmarks.md); over a handful of numbers it cannot bend the field's shape
    to v0's error. The numbers: a log-E offset per stiffness cluster of the fitted field
    (`calibrate_clusters`, 1-D k-means on log E over the moving drivers) and a log speed
    gain per video. Adam, `calibrate_iters` steps of `lr_calibrate` nats; the parameters
    with the least loss seen are kept (the start among them, so the whole-clip loss never
    rises), folded into the per-driver residuals and the velocity fields' scales.
    Returns {"offsets": [calibrate_clusters] nats, "gains": [videos] speed factors,
    "losses": [calibrate_iters] whole-clip losses, "cluster_sizes": [calibrate_clusters]
    drivers} ("cluster_sizes" only when a finite loss was seen).
    """
    with torch.no_grad():
        E0 = pb.driver_E().detach()
    v0s = current_v0s(pb)
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


def stage_optimizers(pb: FitProblem, s: FitSettings, stage: str) -> Optimizers:
    """The optimisers and schedules of a stage, by checkpoint suffix: "" the stage's own
    (v0 fields in stage 1, the E field in stage 2), "_l" stage 1's level, "_r" the
    per-driver residuals, "_v" v0's refinement in stage 2 (each only when its setting is on)."""
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
                                          eps=s.residual_eps, weight_decay=s.residual_decay,
                                          pool=s.residual_pool, pool_groups=pb.pool_parts)
    if s.refine_velocity:  # the velocity fields keep moving, with their own smaller step
        out["_v"] = make_optimizer(list(pb.velocities), s.lr_velocity * s.refine_velocity_factor, n,
                                   warmup_steps=min(s.warmup, n))
    return out


def retries(s: FitSettings, kept: "Kept | None") -> bool:
    """Whether stage 2 runs again from its start at retry_step of its step sizes: when it keeps
    its start (no measure beat it), in a fit of one round (a later round's losses would no
    longer line up with its checkpoints)."""
    return s.retry_step > 0 and s.rounds == 1 and kept is not None and kept.iteration == 0 and s.material_iters > 0


def material_stage(pb: FitProblem, s: FitSettings, optimizers: Optimizers, v0s: list[torch.Tensor], start: int,
                   kept: "Kept | None", losses: dict[str, list[float]], label: str, progress: ProgressFn | None,
                   save: Callable[[int, "Kept | None"], None] | None,
                   on_start: Callable[[float], "Kept | None"] | None = None) -> tuple[int, "Kept | None"]:
    """Stage 2's iterations `start`..material_iters-1 with `optimizers` (stage_optimizers),
    v0s [Q, 3] m/s frozen unless refine_velocity. Offers each measure point's whole-clip loss
    to `kept` (borrowing an iteration's own loss where it is one), appends the losses, calls
    `save(iterations done, kept)` when a checkpoint is due (None: never). `on_start`: called
    with iteration 0's loss, the measure of the stage's start (FitSettings.borrows_start),
    it returns the state to keep from then on. Returns the steps skipped for a non-finite
    gradient and the kept state."""
    opt, sched = optimizers[""]
    opt_r, sched_r = optimizers.get("_r", (None, None))
    opt_v, sched_v = optimizers.get("_v", (None, None))
    points, borrowed = s.measure_points(), s.borrowed_points()
    skipped = 0
    for it in range(start, s.material_iters):
        if it == 0 and start == 0 and save is not None:
            save(0, kept)
        loss = material_iteration(pb, None if s.refine_velocity else v0s, s.horizon_at(it))
        if it == 0 and on_start is not None:
            kept = on_start(loss)
        if kept is not None and it in borrowed:  # this loss is the whole-clip loss of the state before the step
            losses["whole_clip"].append(loss)
            kept.offer(pb, loss, it)
        if not _clip_and_step(list(pb.material.parameters()), opt, sched, s.grad_clip):
            skipped += 1
        if opt_v is not None:
            _clip_and_step(list(pb.velocities.parameters()), opt_v, sched_v, s.grad_clip)
        if opt_r is None:
            pb.log_e_residual.grad = None  # nor, a round without residual steps, theirs
        else:
            if not _clip_and_step([pb.log_e_residual], opt_r, sched_r, math.inf):
                skipped += 1
            if s.residual_diffusion > 0:
                pb.diffuse_residuals(s.residual_diffusion)
            pb.share_residuals()
        losses["material"].append(loss)
        if progress:
            progress(label, it + 1, s.material_iters, loss)
        if kept is not None and it + 1 in points and it + 1 not in borrowed:
            measured = whole_clip_loss(pb, current_v0s(pb) if s.refine_velocity else v0s)
            losses["whole_clip"].append(measured)
            kept.offer(pb, measured, it + 1)
        if save is not None and (it + 1) % s.checkpoint_every == 0 and it + 1 < s.material_iters:
            save(it + 1, kept)
    return skipped, kept


def fit_round(pb: FitProblem, s: FitSettings, rnd: int, ckpt: dict | None, losses: dict[str, list[float]],
              seconds: dict[str, float], progress: ProgressFn | None, save: CheckpointFn) -> int:
    """One round: stage 1 (v0 per video, E frozen at its current value up to the level of
    stage1_level), then stage 2 (E, v0 frozen or refined). `ckpt`: a checkpoint of this
    round to continue from (checked by pd_tool.fit.resume.check_checkpoint). Adds the stages'
    losses and seconds, calls `save` every settings.checkpoint_every iterations and when stage
    2 starts; returns the stage-2 steps skipped for a non-finite gradient."""
    tag = "" if s.rounds == 1 else f" {rnd + 1}/{s.rounds}"
    s = s.round_settings(rnd)
    # ---- stage 1: initial velocity per video, E's field frozen (its level fitted with stage1_level)
    t0 = time.perf_counter()
    start = 0
    optimizers = stage_optimizers(pb, s, "velocity")
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
        else:
            pb.log_e_level.grad = None  # a round that does not fit the level (field_first) drops its gradient
        losses["velocity"].append(loss)
        if progress:
            progress("velocity" + tag, it + 1, s.velocity_iters, loss)
        if (it + 1) % s.checkpoint_every == 0 and it + 1 < s.velocity_iters:
            save("velocity", it + 1, optimizers, losses, rnd, None)
    if s.stage1_level and (ckpt is None or ckpt["stage"] == "velocity"):
        losses.setdefault("stage1_level", []).append(fold_level(pb))
    seconds["velocity"] = seconds.get("velocity", 0.0) + time.perf_counter() - t0

    # ---- stage 2: material (v0 frozen, or refined at a lower rate)
    t0 = time.perf_counter()
    v0s = current_v0s(pb)
    optimizers = stage_optimizers(pb, s, "material")
    start = 0
    if ckpt is not None and ckpt["stage"] == "material":
        for suffix, (o, sc) in optimizers.items():
            o.load_state_dict(ckpt["optimizer" + suffix])
            sc.load_state_dict(ckpt["scheduler" + suffix])
        start = ckpt["iteration"]
    kept = None
    points = s.measure_points()

    def start_measured(loss: float) -> Kept | None:
        if rnd == 0:
            # the whole-clip loss stage 2 starts from, against which the fit's final one is read
            losses["start"] = [loss]
        if not points:
            return None
        losses.setdefault("whole_clip", []).append(loss)
        return Kept.of(pb, loss, 0)

    # the start's measure: iteration 0's own loss where it back-propagates through every frame
    # (a checkpoint taken as the stage begins has neither), else simulated here
    measure_start = start == 0 and s.material_iters > 0 and (rnd == 0 or bool(points))
    if ckpt is not None and ckpt["stage"] == "material" and points and "kept_at" in ckpt:
        kept = Kept.from_state(ckpt, pb.device)
    elif measure_start and not s.borrows_start():
        kept = start_measured(whole_clip_loss(pb, v0s))
    borrow = start_measured if measure_start and s.borrows_start() else None
    skipped, kept = material_stage(pb, s, optimizers, v0s, start, kept, losses, "material" + tag, progress,
                                   lambda it, k: save("material", it, optimizers, losses, rnd, k), borrow)
    if retries(s, kept):
        # nothing this stage measured beat its start: its steps overshot. Again from the start
        # at a fraction of the step, keeping the first attempt's losses apart; no checkpoint is
        # taken in the retry, so a fit killed in it resumes in the first attempt and retries again
        kept.restore(pb)
        losses["material_first_try"], losses["material"] = losses["material"], []
        losses["whole_clip_first_try"], losses["whole_clip"] = losses["whole_clip"], [kept.loss]
        smaller = s.with_step_scale(s.retry_step)
        skipped += material_stage(pb, smaller, stage_optimizers(pb, smaller, "material"), v0s, 0, kept, losses,
                                  "material, retried" + tag, progress, None)[0]
    if kept is not None:
        if kept.iteration != s.material_iters:
            kept.restore(pb)
        losses.setdefault("kept", []).append(float(kept.iteration))
    seconds["material"] = seconds.get("material", 0.0) + time.perf_counter() - t0
    return skipped
