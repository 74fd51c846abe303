"""Checkpoint and resume, wired to the fit: what a checkpoint of a FitProblem holds
(save_checkpoint), which fit it belongs to (resume_key), and the checks that let `--resume`
continue from it only when it is this fit's, in range and consistent (load_checkpoint,
check_checkpoint). The file format itself is pd_tool/fit/checkpoint.py.

Every refusal is one CheckpointError line that names the file, what is wrong and the fix.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from pd_tool.core.atomic import check_destination
from pd_tool.core.errors import PdToolError
from pd_tool.fit.checkpoint import (
    MAX_HEADER_BYTES,
    CheckpointError,
    ForeignCheckpointFile,
    is_pdtool_checkpoint,
    read_checkpoint,
    write_checkpoint,
)
from pd_tool.fit.problem import FitProblem
from pd_tool.fit.settings import FitSettings
from pd_tool.fit.stages import Kept, Optimizers, stage_optimizers
from pd_tool.materials.file import scene_fingerprint


def save_checkpoint(path: Path, pb: FitProblem, stage: str, it: int, optimizers: Optimizers,
                    losses: dict[str, list[float]], rnd: int = 0, kept: Kept | None = None) -> None:
    """Write the fit's state after `it` iterations of `stage` in round `rnd`, with the state
    stage 2 keeps so far (`kept`, keep_best_every) (the file format:
    pd_tool/fit/checkpoint.py; what it must hold: check_checkpoint)."""
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
    if kept is not None:
        state.update(kept.to_state())
    write_checkpoint(path, state, getattr(pb, "resume_key", {}))  # run_fit sets the key; a bare FitProblem has none


def resume_key(pb: FitProblem, scene_path: str | Path) -> dict:
    """What a checkpoint must share with the fit that resumes it: the scene file, the
    preparation's result, the videos and the settings (the device may change)."""
    settings = {k: v for k, v in pb.s.to_dict().items() if k != "device"}
    return {"scene_sha256": scene_fingerprint(scene_path), "drivers": int(len(pb.x_rest)),
            "frames": [int(v.num_frames) for v in pb.videos],
            "image": [list(v.frames.shape[1:3]) for v in pb.videos], "settings": settings}


_RESUME_FIX = "delete it, or fit without --resume"


def _foreign_checkpoint(path: Path, what: str) -> PdToolError:
    return CheckpointError(f"{path}: is not a pdtool fit checkpoint ({what}), and a fit keeps its checkpoint at "
                           f"that path; pdtool neither reads nor replaces it: move it away, or fit to another --out")


def _checkpoint_max_bytes(pb: FitProblem, s: FitSettings) -> int:
    """The largest checkpoint this fit writes, with room to spare: every trained tensor
    with two Adam moments and stage 2's kept copy (x4, x5 for the slack), the loss
    histories (the whole-clip measures among them), the header."""
    tensors = [*pb.material.parameters(), *pb.velocities.parameters(), pb.log_e_residual, pb.log_e_level]
    weights = sum(t.numel() * t.element_size() for t in tensors)
    entries = s.rounds * (s.velocity_iters + s.material_iters + len(s.measure_points()) + 4)
    return 5 * weights + 8 * entries + MAX_HEADER_BYTES + (1 << 20)


def load_checkpoint(path: Path, pb: FitProblem, s: FitSettings) -> dict | None:
    """The checkpoint at `path`, checked against this fit (check_checkpoint), with its
    losses as lists; None when there is none. One-line CheckpointError otherwise."""
    if not path.exists() and not path.is_symlink():
        return None
    ours, what = is_pdtool_checkpoint(path)
    if not ours:
        raise _foreign_checkpoint(path, what)
    try:
        # a whole-clip measure of a diverged state is NaN, and the kept state's loss with it
        problem, state = read_checkpoint(path, max_bytes=_checkpoint_max_bytes(pb, s),
                                         nonfinite=("state.losses", "state.kept_at"))
    except ForeignCheckpointFile:
        raise _foreign_checkpoint(path, "unrecognised") from None
    except CheckpointError as e:
        raise CheckpointError(f"{e}; {_RESUME_FIX}") from None
    _check_resume_key(path, problem, pb.resume_key)
    check_checkpoint(path, state, pb, s)
    state["losses"] = {k: v.tolist() for k, v in state["losses"].items()}
    return state


def restore(path: Path, pb: FitProblem, state: dict) -> None:
    """Load a checkpoint that load_checkpoint accepted into pb: the fields' weights, the
    residuals, stage 1's level and torch's random-number state. The optimisers' states load
    when their stage starts (pd_tool.fit.stages.fit_round)."""
    # check_checkpoint matched every tensor's shape and dtype to this fit's, so these loads
    # cannot fail on the data; torch may still refuse an RNG state it cannot use
    pb.material.load_state_dict(state["material"])
    pb.velocities.load_state_dict(state["velocities"])
    try:
        torch.set_rng_state(state["torch_rng"])
    except (RuntimeError, ValueError, TypeError):
        raise CheckpointError(f"{path}: its random-number state is not one torch accepts; "
                              f"{_RESUME_FIX}") from None
    with torch.no_grad():
        pb.log_e_residual.copy_(state["residual"].to(pb.device))
        pb.log_e_level.copy_(state["level"].to(pb.device))


def _check_resume_key(path: Path, problem: dict, key: dict) -> None:
    # a checkpoint of another fit (other scene, options, videos, or a preparation that came
    # out differently) would load into tensors of the wrong shape, or silently mix two fits
    if not problem:
        raise CheckpointError(f"{path}: the checkpoint does not say which fit it belongs to (no problem key); "
                              f"{_RESUME_FIX}")
    for name in [*key, *(k for k in problem if k not in key)]:
        if problem.get(name) != key.get(name):
            what = name if name != "drivers" else f"driver count {problem.get(name)!r:.20} != {key[name]}"
            raise CheckpointError(f"{path}: the checkpoint belongs to another fit ({what} differs); {_RESUME_FIX}")


def check_checkpoint(path: Path, state: dict, pb: FitProblem, s: FitSettings) -> None:
    """Refuse (one line) a checkpoint this fit cannot continue from: a stage, iteration or
    round outside the fit's ranges, missing or unknown entries, tensors of another shape or
    dtype than this fit's, optimiser or schedule states that do not match the fit's
    settings and iteration, loss histories of the wrong length. The checksum only tells a
    damaged file; these checks hold for a crafted one that recomputed it."""
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
    optimizers = stage_optimizers(pb, s.round_settings(rnd), stage)
    want = {"stage", "iteration", "round", "material", "velocities", "residual", "level", "losses", "torch_rng"}
    want |= {f"{kind}{suffix}" for suffix in optimizers for kind in ("optimizer", "scheduler")}
    points = s.measure_points()
    # a checkpoint taken as stage 2 begins, whose start the first iteration will measure
    # (FitSettings.borrows_start), holds no measure and no kept state yet
    unmeasured = stage == "material" and it == 0 and s.borrows_start()
    keeping = stage == "material" and bool(points) and not unmeasured
    # the points this round has measured: a borrowed one is measured by the iteration after it,
    # which a checkpoint taken at that point has not run yet
    done = [p for p in points if p < it or p == it and p not in s.borrowed_points()] if keeping else []
    if keeping:
        want |= set(Kept.ENTRIES)
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
    if keeping:  # the state stage 2 keeps so far, measured at its start or a measure point up to `it`
        module("kept_material", state["kept_material"], pb.material.state_dict())
        module("kept_velocities", state["kept_velocities"], pb.velocities.state_dict())
        tensor("kept_residual", state["kept_residual"], pb.log_e_residual.detach())
        tensor("kept_at", state["kept_at"], torch.zeros(2, dtype=torch.float64))
        at = float(state["kept_at"][1])
        if at not in [0, *done]:
            raise bad(f"kept_at names iteration {at:g}, where by iteration {it} this fit has measured at {[0, *done]}")
    for suffix, (opt, sched) in optimizers.items():
        _check_optimizer(bad, "optimizer" + suffix, state["optimizer" + suffix], opt, sched, it, tensor)
        _check_scheduler(bad, "scheduler" + suffix, state["scheduler" + suffix], sched, it)

    # the histories hold one loss per iteration run so far (and one level per fold)
    vi, mi = s.velocity_iters, s.material_iters
    lengths = {"velocity": rnd * vi + (it if stage == "velocity" else vi),
               "material": rnd * mi + (it if stage == "material" else 0)}
    # one fold per stage 1 finished by a round that fits the level
    folds = sum(s.round_settings(r).stage1_level for r in range(rnd)) + \
        (stage == "material" and s.round_settings(rnd).stage1_level)
    if folds:
        lengths["stage1_level"] = folds
    if mi > 0 and (rnd > 0 or stage == "material" and not unmeasured):
        lengths["start"] = 1  # the whole-clip loss when the first stage 2 began
    if points:  # keep_best_every: each stage 2's measures (its start, then `points`), and each finished one's keep
        lengths["whole_clip"] = rnd * (1 + len(points)) + (1 + len(done) if keeping else 0)
        lengths["kept"] = rnd
    lengths = {k: n for k, n in lengths.items() if n > 0 or k in ("velocity", "material")}
    losses = state["losses"]
    if not isinstance(losses, dict) or set(losses) != set(lengths):
        raise bad(f"its loss histories are not {', '.join(sorted(lengths))}")
    for k, n in lengths.items():
        tensor(f"losses.{k}", losses[k], torch.zeros(n, dtype=torch.float64))
    if "whole_clip" in losses:  # each round keeps the state its own measures rank first (Kept.offer)
        measures, per = losses["whole_clip"].tolist(), 1 + len(points)
        for r in range(rnd):
            _, at = Kept.ranked_first(measures[r * per:(r + 1) * per], [0, *points])
            if not float(losses["kept"][r]) == at:
                raise bad(f"losses.kept names iteration {float(losses['kept'][r]):g} for round {r + 1}, "
                          f"where its measures rank iteration {at} first")
        if keeping:
            ats = [0, *done]
            best, at = Kept.ranked_first(measures[rnd * per:], ats)
            loss, kept_it = (float(v) for v in state["kept_at"])
            if not (kept_it == at and (loss == best or math.isnan(loss) and math.isnan(best))):
                raise bad(f"kept_at names iteration {kept_it:g} at the whole-clip loss {loss:.6g}, where this "
                          f"round's measures rank iteration {at} first, at {best:.6g}")


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


def check_checkpoint_destination(out: Path, ckpt_path: Path) -> None:
    """Before any work: the checkpoint's path holds nothing but a pdtool checkpoint (a fit
    replaces and deletes that file, so it must be pdtool's own), and out's folder takes new
    files (a read-only folder is found now, not at the first checkpoint)."""
    if ckpt_path.exists() or ckpt_path.is_symlink():
        ours, what = is_pdtool_checkpoint(ckpt_path)
        if not ours:
            raise _foreign_checkpoint(ckpt_path, what)
    check_destination(out)


def remove_own_checkpoint(path: Path) -> None:
    """Delete the file at `path` when it is a pdtool fit checkpoint; leave anything else."""
    if is_pdtool_checkpoint(path)[0]:
        path.unlink()
