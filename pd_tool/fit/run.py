"""The fit, end to end (run_fit): settings resolved, refusals before any work, the
problem set up, `rounds` rounds of stage 1 and 2 with checkpoints (and `--resume` from
one), calibration, the checks after the fit, then the material file (.pdmat) and the
report lines. The result (FitResult) is what `pdtool fit` writes its outputs and report
from (pd_tool/fit/outputs.py).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pd_tool.core.scene import GaussianScene
from pd_tool.drivers import DriverSet
from pd_tool.fit.problem import FitProblem, whole_clip_loss
from pd_tool.fit.refusals import FitLearnsNothing, check_fit_can_learn, check_learned, check_videos_can_teach
from pd_tool.fit.resume import (
    check_checkpoint_destination,
    load_checkpoint,
    remove_own_checkpoint,
    restore,
    resume_key,
    save_checkpoint,
)
from pd_tool.fit.settings import FitSettings
from pd_tool.fit.stages import ProgressFn, calibrate, current_v0s, fit_round
from pd_tool.materials.file import MaterialFile, scene_fingerprint
from pd_tool.prepare.preparation import PreparedScene, PrepareOptions
from pd_tool.video.folder import ReferenceVideo


@dataclass
class FitResult:
    """What a fit found and ran at. Q drivers, F simulated Gaussians; E in Pa, v0 in m/s,
    seconds of wall time per stage."""

    material_path: Path
    driver_E: np.ndarray  # [Q] Pa, as written to the material file
    driver_v0: np.ndarray  # [Q, 3] m/s, the first video's fitted initial velocity
    gaussian_E: np.ndarray  # [F] per simulated Gaussian (its driver's E)
    # per stage, one per iteration; "stage1_level": the folded levels, nats; "start" and
    # "final": the whole-clip loss when stage 2 starts (absent without stage 2) and of the
    # result, one number each
    losses: dict[str, list[float]]
    seconds: dict[str, float]
    prep: PreparedScene
    drivers: DriverSet
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
    metrics: dict[str, Any] = field(default_factory=dict)  # as the material file records them


def whole_clip_text(losses: dict[str, list[float]]) -> str:
    """"START -> FINAL" of the whole-clip loss (FINAL alone without stage 2), for the lines
    the CLI and the demo print: the stages' own losses are on other footings (stage 1's
    first frames; stage 2's one-frame steps with a truncated horizon, and the state before
    each step)."""
    return " -> ".join(f"{losses[k][0]:.4f}" for k in ("start", "final") if losses.get(k))


def kept_measure(losses: dict[str, list[float]], s: FitSettings) -> float | None:
    """The whole-clip loss measured of the state the last round kept (losses["whole_clip"] at
    losses["kept"], keep_best_every of the fit's settings `s`), None when none was kept."""
    kept, measures, points = losses.get("kept"), losses.get("whole_clip"), s.measure_points()
    if not kept or not measures or not points:
        return None
    last_round = measures[-1 - len(points):]  # its start, then each measure point
    return last_round[[0, *points].index(int(kept[-1]))]


def whole_clip_note(losses: dict[str, list[float]], s: FitSettings | None = None) -> str | None:
    """The report's line when stage 2 raised the whole-clip loss, else None: when the last
    round kept an earlier state than its last (losses["kept"], keep_best_every of the fit's
    settings `s`), or, keeping none, ended above its start (losses["start"],
    losses["final"]). One-frame gradients can lower every step's loss while the clip as a
    whole drifts away (the donut of bench/fit_truth.py), and Adam's fixed-size steps can
    overshoot on whole-clip ones."""
    weak = ("these videos constrain E weakly; another video, of another push or from another side, gives the fit "
            "more to go on")
    kept = losses.get("kept")
    best = kept_measure(losses, s) if s is not None else None
    if best is not None and kept[-1] < s.measure_points()[-1]:
        at = int(kept[-1])
        where = "the E stage 1 left" if at == 0 else f"the E of its iteration {at}"
        return (f"stage 2 raised the whole-clip loss ({best:.4f} at its best, {losses['whole_clip'][-1]:.4f} at "
                f"its end): the fit keeps {where}; {weak}")
    start, final = losses.get("start"), losses.get("final")
    if kept or not start or not final or not final[0] > start[0]:
        return None
    return f"stage 2 raised the whole-clip loss ({start[0]:.4f} -> {final[0]:.4f}): {weak}"


def run_fit(
    scene: GaussianScene,
    scene_path: str | Path,
    videos: list[ReferenceVideo],
    out: str | Path,
    *,
    prepare_options: PrepareOptions | None = None,
    settings: FitSettings | None = None,
    progress: ProgressFn | None = None,
    resume: bool = False,
) -> FitResult:
    """Fit and write the material file `out` (.pdmat). A checkpoint `out`.ckpt is kept
    while fitting (every settings.checkpoint_every iterations) and removed at the end;
    resume=True continues from it. `progress(stage, iteration, total, loss)` is called after
    every iteration. Refuses with one line (PdToolError) a fit that cannot learn, cannot
    fit in memory or time, or a checkpoint it cannot continue from."""
    s = (settings or FitSettings()).resolved()
    out = Path(out)
    ckpt_path = out.with_name(out.name + ".ckpt")
    if s.velocity_iters + s.material_iters + s.calibrate_iters == 0:
        raise FitLearnsNothing("--velocity-iters 0 and --material-iters 0 leave nothing to fit (the material file "
                               "would hold the starting E); give at least one iteration")
    check_checkpoint_destination(out, ckpt_path)
    warm = None  # the material a warm start begins from, read and checked before any work
    if s.init_material is not None:
        warm = MaterialFile.load(s.init_material)
        warm.check_scene(scene_path, s.init_material)
    pb = FitProblem(scene, videos, prepare_options or PrepareOptions(), s)  # refuses what cannot fit in memory
    if warm is not None:
        pb.start_from(warm)
    check_videos_can_teach(videos)
    check_fit_can_learn(pb)
    losses: dict[str, list[float]] = {"velocity": [], "material": []}
    seconds: dict[str, float] = {}
    pb.resume_key = resume_key(pb, scene_path)
    ckpt = load_checkpoint(ckpt_path, pb, s) if resume else None
    if ckpt is not None:
        losses = ckpt["losses"]
        restore(ckpt_path, pb, ckpt)

    save = partial(save_checkpoint, ckpt_path, pb)
    skipped = 0
    resume_round = ckpt["round"] if ckpt is not None else 0
    for rnd in range(s.rounds):
        if rnd < resume_round:
            continue
        skipped += fit_round(pb, s, rnd, ckpt if rnd == resume_round else None, losses, seconds, progress, save)
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
    v0s = current_v0s(pb)
    with torch.no_grad():
        # the whole-clip loss, every frame simulated from rest in one go: what the fitted E and
        # v0 explain of the videos, on the same footing whatever the stages ran. The state stage
        # 2 kept was measured already, unless calibration moved E since.
        measured = kept_measure(losses, s) if s.calibrate_iters == 0 else None
        losses["final"] = [measured if measured is not None else whole_clip_loss(pb, v0s)]
        begun = losses.get("start")  # stage 2's start, on the same footing
        driver_E = pb.driver_E().double().cpu().numpy()
        v0_mean = torch.stack(v0s).mean(0).cpu().numpy()
    try:
        check_learned(losses)
    except FitLearnsNothing:
        remove_own_checkpoint(ckpt_path)  # nothing is left of a fit that learned nothing
        raise
    p = pb.prep
    labels = pb.drivers.labels.cpu().numpy()[: p.count]  # the Gaussians' drivers (filled particles follow)
    meta: dict[str, Any] = {
        "scene_sha256": scene_fingerprint(scene_path),
        "scene_path": str(Path(scene_path).resolve()),
        "prepare": p.options.to_dict(),
        "transform": p.transform.to_dict(),
        "nu": s.nu, "density": s.density, "damping": s.damping,
        "drivers": {"count": int(len(driver_E)), "ratio": s.driver_ratio, "seed": s.seed,
                    "min_per_cell": s.min_drivers_per_cell},
        # what a bake needs to simulate as the fit did (MaterialFile.fit_simulation)
        "simulation": {"grid_res": int(p.options.grid_res), "driver_ratio": s.driver_ratio, "driver_seed": s.seed,
                       "min_drivers_per_cell": s.min_drivers_per_cell, "cfl_safety": float(pb.cfl_safety)},
        "settings": s.to_dict(),
        "videos": [str(v.folder) for v in videos],
        "metrics": {
            "loss_velocity_first": losses["velocity"][0] if losses["velocity"] else None,
            "loss_velocity_last": losses["velocity"][-1] if losses["velocity"] else None,
            "loss_material_first": losses["material"][0] if losses["material"] else None,
            "loss_material_last": losses["material"][-1] if losses["material"] else None,
            "loss_start": begun[0] if begun else None,
            "loss_final": losses["final"][0],
            # keep_best_every: the stage-2 iteration whose state the last round kept (0: its start)
            "kept_iteration": int(losses["kept"][-1]) if losses.get("kept") else None,
            # retry_step: stage 2 ran again at a fraction of its step, having kept its start
            "stage2_retried": "whole_clip_first_try" in losses,
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
    remove_own_checkpoint(ckpt_path)
    report = list(p.report)
    if meta["metrics"]["stage2_retried"]:
        first = losses["whole_clip_first_try"]
        report.append(f"stage 2 kept its start: nothing it measured scored below {first[0]:.4g} (its best "
                      f"{min(first[1:], default=first[0]):.4g}), so it ran again from there at {s.retry_step:.2g} of "
                      f"its step")
    note = whole_clip_note(losses, s)
    if note:
        report.append(note)
    for i, g in enumerate(pb.gains):
        if float((g - 1.0).abs().max()) > 0.02:  # a camera that differs visibly from the splat's colours
            report.append(f"video {i}: exposure matched at rest, gain {' / '.join(f'{x:.2f}' for x in g.tolist())} "
                          f"(r / g / b; --no-match-exposure turns it off)")
    return FitResult(material_path=out, driver_E=driver_E, driver_v0=v0s[0].double().cpu().numpy(),
                     gaussian_E=driver_E[labels], losses=losses,
                     seconds=seconds, prep=p, drivers=pb.drivers, report=report, skipped_steps=skipped,
                     driver_v0s=[v.double().cpu().numpy() for v in v0s],
                     driver_E_uncalibrated=E_uncalibrated, calibration=calibration, settings=s,
                     cfl_safety=float(pb.cfl_safety), substeps=pb.substeps_range, metrics=meta["metrics"])
