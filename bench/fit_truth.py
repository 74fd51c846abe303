"""Does a fit recover a material it did not make? `pdtool fit` on reference videos simulated
by a converged simulation, then `pdtool bake` under a new force, against the converged truth.

For each scene and hidden E field:
  1. the truth: E per Gaussian (`region`: the plant's stem / leaf / flower, a capture's
     three height bands; `smooth`: stiff at the base to soft at the top, 3x stiffer on one
     side; `random`: a seeded smooth random field), the same E range on every scene (every
     scene is scaled to 1 m, as pdtool does);
  2. two reference videos from a converged simulation (`--reference` cells, CFL safety
     0.25, every particle split into sub-particles over its Gaussian's extent, `--split` a
     cell along each axis: one particle per Gaussian is about one a cell on a fine grid, and
     such particles separate under a push), each an initial push (along x, then y) seen
     from a low view behind the object (azimuth 200, elevation 8 degrees) and from a high
     side view (azimuth 290, elevation 35) that no default was tuned on, with a slight
     blur, 10% less exposure and pixel noise of sigma 2/255;
  3. `pdtool fit SCENE VIDEO0 VIDEO1` at `--quality` through the CLI;
  4. `pdtool bake --material` under a new force (diagonal, at the side of the object at
     70% of its height: another direction and place than either video's push) as the fit
     simulated (no --quality), and at default and at final, matched to the fit's motion
     (the product's bake) and with the fitted E as it is (--no-match-fit); the uniform start E (the fit's
     --init-e) and the best uniform E (the truth's geometric mean over the moving
     Gaussians, an oracle a user could at best hand-tune to) baked at each quality; and
     the true E put on the fit's drivers (`true E`), baked as fitted and at each bake
     quality as it is: what an exact recovery of E would score on that discretisation;
     and the uniform start on the fit's drivers baked as fitted (`uniform start, as fit`):
     what the fit gained on its own discretisation.
     Where even it is not far below the uniform start, the bake's discretisation limits,
     not E. It is not a bound: a fitted E can absorb part of the discretisation's error;
  5. each bake's positions (read back from its USD) against the converged truth under the
     same force: RMS over frames and moving Gaussians, as a fraction of the object's size.
The error is taken over the Gaussians that the new force moves more than 1% of the
object's size in the truth; `still` is what a material that does not move would score.
Also the E error: median |ln(E_fit / E_true)| and Spearman's rank correlation (ties at
their mean rank) over the Gaussians that move more than 1% of the object's size in a
video, split into the fit's level (median ln) and its shape (median |ln| about that
level), beside the same median for the uniform start and the best uniform E; and for each
matched bake, the factor it scaled the fitted E by and the same median for the E it moved
with (`matched_abs_ln`). `thin_split` gives the same statistics over those Gaussians that
lie in parts under a quarter of the fit's cell and over the rest (the thin-part notice's
reading, pd_tool.prepare.thickness.thin_mask).
Each row's `goals` give, for the bare bake and each bake quality, the error each new-force
target asks for (the uniform bake's over 3 and the best uniform's over 2), whether the fitted
bake meets it, and with `--check-reference` whether the reference can tell: a target asking
for less than the reference's own distance from a finer grid cannot be judged against it.

`--set FIELD=VALUE` and `--fit-args` try another fit setting on every scene and field (a
default must hold on all of them).

`--losses` also asks whether the fit's own model prefers the truth: the whole-clip video
loss under the fitted E, the true E and the uniform start, each with v0 refitted under it
(`pdtool fit --init-material E --material-iters 0 --no-level`), and under the answer itself:
the true E with the true pushes on the fit's own drivers (`true E, true push`). A fit ending
above that stopped short of the answer; one ending below it found a pair its loss prefers.

`--fit-grid N` and `--fit-floor K` fit on N cells with at least K drivers a moving cell (a
quality file derived from `--quality`): the fit's discretisation, against which the loss can
or cannot tell the true E from a uniform one.

`--given-push` runs the fit's E search alone: its stage 2 from the uniform start with each
video's v0 held at the true push (no stage 1), with the same E error and whole-clip loss.
On `--control --clean` videos the answer scores about 0, so an E left far from the truth
there is the E search's own failing, not v0's or the model's.

`--warm-from-field` fits E's field alone first (no per-driver residuals, no stage-1
level), then the row's fit from that E (`--init-material`): the field's pattern, then the
residuals' contrast.

`--warm-from-truth` starts the row's fit from the true E put on its drivers: whether the
fit keeps the answer when it starts there (a diagnostic, like `--losses`).

`--clean` writes the reference videos as rendered, without the camera's blur, exposure
change and noise.

`--capture NAME=PATH[:UP]` runs the same on a capture of your own (any splat file pdtool
reads; UP its up axis, or auto for pdtool's guess), and `--views AZ:EL,AZ:EL` films the two
videos from other cameras: a fit's figures should hold on scenes and views no default was
tuned on.

`--control` simulates the reference videos with the fit's own grid, CFL safety and driver
ratio instead: the inverse crime, kept as a labelled control so that its size stays
visible. Targets at default quality: new-force error at least 3x below the uniform start
and 2x below the best uniform E; median |ln| at most 0.5. Figures: docs/benchmarks.md,
"Fit against a converged truth".

    python bench/fit_truth.py --quick                    # CPU, CI scale (minutes)
    python bench/fit_truth.py --device cuda --gaussians 20000 --scenes udon --fields smooth --json out.json
    python bench/fit_truth.py --device cuda --gaussians 20000 --capture hat=hat.ply:+z --views 30:10,150:25
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import re
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # fit_recovery's --set parser

# the repository is on the path from here: its own packages, not an installed copy's
from pd_tool.prepare.split import SPLIT_MOST  # noqa: E402
from usd_export import instance_positions  # noqa: E402

SCENES = {"plant": "+z", "udon": "-y", "donut": "-y", "tree": "-y"}
CAPTURES = {"udon": "udon.ply", "donut": "donut_fused.ply", "tree": "tree_100k.splat"}  # under --data
FIELDS = ("region", "smooth", "random")
E_SOFT, E_STIFF = 6e4, 2e6  # Pa: the range of every field (a 1 m object)
REGION_E = {"stem": 2e6, "leaf": 6e4, "flower": 3e5}  # the plant's regions; a capture's bands base -> top
BANDS = (2e6, 3e5, 6e4)
VIEWS = ((200.0, 8.0), (290.0, 35.0))  # (azimuth, elevation) degrees per video
PUSHES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0))  # simulation axes
PUSH_SPEED = 0.6  # m/s at the top
NOISE, BLUR, EXPOSURE = 2.0 / 255.0, 0.7, 0.9  # pixel sigma, blur sigma (px), exposure factor
NEW_FORCE = dict(direction=(-1.0, 1.0, 0.0), height=0.7, accel=3.0, duration=0.3, radius=0.25)
MOVING = 0.01  # of the object's size: a Gaussian moving less in every video says nothing of its E


@dataclass
class Judge:
    """A run against the truth under the new force, over the Gaussians the truth moves
    further than MOVING of the object's size: a local push leaves most of the object still,
    and a material that does not move at all would score well over all of it."""

    x_true: np.ndarray  # [T, N, 3] scene units
    free: np.ndarray  # [N] bool: the Gaussians not pinned
    moving: np.ndarray  # [N] bool: free, and moved further than MOVING by the truth
    size: float  # the object's size, scene units

    @classmethod
    def of(cls, prep, x_true: np.ndarray, size: float) -> "Judge":
        """prep: the truth's PreparedScene (its pinned Gaussians are never judged)."""
        free = np.zeros(x_true.shape[1], bool)
        free[prep.foreground[~prep.static[: prep.count]]] = True
        return cls(x_true, free, free & (np.linalg.norm(x_true - x_true[0], axis=-1).max(axis=0) > MOVING * size),
                   size)

    def peak(self, x: np.ndarray) -> float:
        """The largest displacement of a moving Gaussian in x [T, N, 3], / size."""
        m = self.moving
        return float(np.linalg.norm(x[:, m] - x[0, m], axis=-1).max() / self.size)

    def off(self, x: np.ndarray) -> float:
        """RMS over frames and moving Gaussians of x [T, N, 3] against the truth, / size."""
        m = self.moving
        return float(np.sqrt((np.linalg.norm(x[:, m] - self.x_true[: len(x)][:, m], axis=-1) ** 2).mean()) / self.size)


@dataclass
class Row:
    scene: str
    field: str
    reference: str  # "converged" or "control (fit's own discretisation)"
    up: str = ""  # the scene's up axis (a --capture's guessed one with "auto")
    reference_particles: int = 0  # simulated particles of the reference
    reference_per_cell: float = math.nan  # of them per occupied cell of its grid
    reference_check: dict = field(default_factory=dict)  # the truth on --check-reference cells against it
    fit_s: float = math.nan
    # the fit's own record (its material file's metrics): the whole-clip loss at stage 2's start
    # and at the end, the stage-2 iteration whose state it kept, the steps it skipped
    fit_metrics: dict = field(default_factory=dict)
    median_abs_ln: float = math.nan
    median_ln: float = math.nan  # the fit's level: median ln(E_fit / E_true)
    shape_abs_ln: float = math.nan  # median |ln(E_fit / E_true)| once that level is taken out
    baseline_abs_ln: dict = field(default_factory=dict)  # the same median for the uniform start and best uniform E
    spearman: float = math.nan
    moving_share: float = math.nan
    # the same E statistics over the moving Gaussians in parts thinner than a quarter of the
    # fit's cell ("thin") and over the rest ("other"), with the thin ones' share and the
    # cell (m): whether E's error lives where the fit's grid bends thin parts too stiffly
    thin_split: dict = field(default_factory=dict)
    errors: dict = field(default_factory=dict)  # bake name -> RMS / object size
    # "fitted, QUALITY" bakes: the factor the bake scaled the fitted E by to move as the fit
    # did, and median |ln(factor E_fit / E_true)| over the moving drivers
    match_factor: dict = field(default_factory=dict)
    matched_abs_ln: dict = field(default_factory=dict)
    ratios: dict = field(default_factory=dict)  # "uniform start / fitted" etc.
    # --losses: the fit's whole-clip video loss under an E, with v0 fitted under that E:
    # "fitted" (the fit's own v0), and the fitted E, the true E and the uniform start, each
    # with v0 refitted by stage 1 alone; "true E, true push": the answer (exact_pair_loss)
    losses: dict = field(default_factory=dict)
    # --given-push: the fit's stage 2 from the uniform start with v0 held at the true pushes
    # (given_push_fit): its E statistics as above, and its whole-clip loss at start and end
    given_push: dict = field(default_factory=dict)
    seconds: dict = field(default_factory=dict)  # wall time per step
    # per bake quality and goal: the error it asks for, whether the fitted bake meets it, and,
    # with --check-reference, whether the reference can tell (goals())
    goals: dict = field(default_factory=dict)


# the benchmark's targets at default quality: the fitted bake's new-force error this many times
# below the uniform start's and the best uniform E's, each baked at the same quality
GOALS = {"uniform start": 3.0, "best uniform": 2.0}


def uniform_bake(label: str, quality: str, fit_quality: str) -> str:
    """The error key of a uniform E's bake (`label`: "uniform start" or "best uniform") at
    `quality`: the bare name at the fit's own quality, else "LABEL, QUALITY"."""
    return label if quality == fit_quality else f"{label}, {quality}"


def goals(errors: dict, qualities: list[str], fit_quality: str, check_rms: float | None) -> dict:
    """For the bare bake ("as fit", against the uniform E baked at the fit's quality) and
    each bake quality Q, and each goal: {"asks": the uniform bake's error over the goal's
    factor (RMS / size), "fitted": the fitted bake's error ("fitted, as fit" or the
    product's "fitted, Q"), "met", and "measurable": whether the asked error lies above
    `check_rms`, the reference's own distance from a finer one (None when it was not
    checked). A goal asking for less than that distance cannot be judged against this
    reference: the truth itself is not known that well."""
    out: dict = {}
    for q in ["as fit", *qualities]:
        fitted = errors.get(f"fitted, {q}")
        if fitted is None:
            continue
        for base, factor in GOALS.items():
            uniform = uniform_bake(base, fit_quality if q == "as fit" else q, fit_quality)
            if uniform not in errors:
                continue
            asks = errors[uniform] / factor
            out.setdefault(q, {})[f"{factor:g}x below {base}"] = {
                "asks": asks, "fitted": fitted, "met": bool(fitted <= asks),
                "measurable": None if check_rms is None else bool(asks > check_rms)}
    return out


def heights(pos: np.ndarray, up: str) -> np.ndarray:
    """Height fraction [N] in 0-1 along the up axis."""
    from pd_tool.prepare.preparation import up_rotation

    h = pos @ up_rotation(up)[2]
    return (h - h.min()) / max(float(np.ptp(h)), 1e-12)


def truth_field(scene, up: str, kind: str, seed: int) -> np.ndarray:
    """E per Gaussian [N] in Pa."""
    from pd_tool.prepare.preparation import up_rotation

    pos = scene.positions.detach().cpu().double().numpy()
    t = heights(pos, up)
    if kind == "region":
        if scene.labels is not None and scene.label_names:
            table = np.array([REGION_E.get(n, E_STIFF) for n in scene.label_names])
            return table[scene.labels]
        return np.array(BANDS)[np.digitize(t, [0.45, 0.75])]
    R = up_rotation(up)
    side = pos @ R[0]
    side = (side - np.median(side)) / max(float(np.ptp(side)), 1e-12)
    if kind == "smooth":
        log_e = np.log(E_STIFF) + t * (np.log(E_SOFT) - np.log(E_STIFF))
        return np.exp(log_e) * 3.0 ** (1.0 / (1.0 + np.exp(-side / 0.05)))
    if kind == "random":
        rng = np.random.default_rng(seed)
        u = (pos - pos.min(0)) / max(float(np.ptp(pos, axis=0).max()), 1e-12)
        centres, signs = rng.uniform(0, 1, (6, 3)), rng.choice([-1.0, 1.0], 6)
        f = sum(s * np.exp(-np.sum((u - c) ** 2, 1) / (2 * 0.2 ** 2)) for c, s in zip(centres, signs))
        f = (f - f.mean()) / max(float(f.std()), 1e-12)
        mid, half = 0.5 * (np.log(E_SOFT) + np.log(E_STIFF)), 0.5 * (np.log(E_STIFF) - np.log(E_SOFT))
        return np.exp(mid + half * np.tanh(0.8 * f))
    raise ValueError(kind)


def particle_E(prep, gaussian_E: np.ndarray) -> np.ndarray:
    """E [P] of every simulated particle: a Gaussian's own, a filled particle its source's."""
    e = gaussian_E[prep.foreground]
    if prep.fill_source is not None:
        e = np.concatenate([e, e[prep.fill_source]])
    return e


def group_log_mean(members: np.ndarray, E: np.ndarray, q: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean of ln E over each of q groups [q] (0 for an empty group), members per group [q])."""
    count = np.bincount(members, minlength=q)
    return np.bincount(members, np.log(E), q) / np.maximum(count, 1), count


def driver_E(prep, drivers, gaussian_E: np.ndarray) -> np.ndarray:
    """Each driver's E [Q]: the geometric mean over its particles."""
    return np.exp(group_log_mean(drivers.labels.cpu().numpy(), particle_E(prep, gaussian_E), len(drivers.positions))[0])


def answer_problem(scene_path: Path, videos: list[Path], settings, prepare: dict, E_true: np.ndarray,
                   given_push: bool = False):
    """The fit's own problem (its resolved FitSettings and the preparation options a fit
    records) and the answer on its drivers: (problem, each video's true push [Q, 3] m/s
    (PUSHES, PUSH_SPEED), the true log E per driver [Q] nats, clamped to the field's
    bounds). With `given_push` the problem's v0 is pinned to those pushes (GivenPush)."""
    import torch

    from pd_tool.fit.problem import FitProblem
    from pd_tool.fit.reference import push_velocity
    from pd_tool.io import load_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.video.folder import load_reference_video

    class GivenPush(FitProblem):
        """A fit's problem whose videos' v0 are the true pushes (set as `pushes` after it is
        built) instead of its velocity fields."""

        def driver_v0(self, i: int) -> torch.Tensor:
            return self.pushes[i]

    refs = [load_reference_video(v, working_size=settings.working_long_side, device=settings.device) for v in videos]
    pb = (GivenPush if given_push else FitProblem)(load_splats(scene_path, device=settings.device), refs,
                                                   PrepareOptions.from_dict(prepare), settings)
    with torch.no_grad():
        log_e = torch.log(torch.as_tensor(driver_E(pb.prep, pb.drivers, E_true), dtype=torch.float32, device=pb.device))
        rest, static = pb.x_rest.double().cpu().numpy(), pb.static.cpu().numpy()
        pushes = [torch.as_tensor(push_velocity(rest, static, direction=d, speed=PUSH_SPEED), dtype=torch.float32,
                                  device=pb.device) for d in PUSHES[:len(refs)]]
    if given_push:
        pb.pushes = pushes
    return pb, pushes, log_e.clamp(pb.material.log_e_min, pb.material.log_e_max)


def exact_pair_loss(scene_path: Path, videos: list[Path], settings, prepare: dict, E_true: np.ndarray) -> float | None:
    """`pdtool fit`'s whole-clip loss (its loss_final) under the answer: the fit's own
    problem with each driver's E from the Gaussians' true E [N] (Pa) and each video's v0
    the push that made it. Near 0 on clean videos made at the fit's own discretisation
    (--control --clean). A fit ending above it stopped short of the answer; one ending
    below it found an (E, v0) pair that its loss prefers to the truth. None where the fit
    has no per-driver residuals to hold E per driver."""
    import torch

    from pd_tool.fit.problem import whole_clip_loss

    if not settings.driver_residual:
        return None
    pb, pushes, log_e = answer_problem(scene_path, videos, settings, prepare, E_true)
    with torch.no_grad():
        pb.set_driver_log_E(log_e)
    return whole_clip_loss(pb, pushes)


def given_push_fit(scene_path: Path, videos: list[Path], settings, prepare: dict, E_true: np.ndarray,
                   points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The fit's E search alone: its stage 2 (every round, as the fit's settings run it) from
    the uniform start with each video's v0 held at the true push, so no v0 error can pull E
    away. Returns (E [M] Pa at `points` [M, 3] scene units, read as the fitted E is
    (MaterialFile.E_at: the nearest driver's), the whole-clip loss stage 2 starts from, the
    one it ends at). Stage 1 does not run (nothing is left for it: no v0 to fit, and its
    level would fold into the start)."""
    from pd_tool.fit.problem import whole_clip_loss
    from pd_tool.fit.stages import fit_round
    from pd_tool.materials.file import MaterialFile

    s = dataclasses.replace(settings, velocity_iters=0, stage1_level=False, init_material=None)
    pb, pushes, _ = answer_problem(scene_path, videos, s, prepare, E_true, given_push=True)
    start = whole_clip_loss(pb, pushes)
    losses: dict[str, list[float]] = {"velocity": [], "material": []}
    for rnd in range(s.rounds):
        fit_round(pb, s, rnd, None, losses, {}, None, lambda *_: None)
    rest = pb.prep.transform.to_scene(pb.x_rest.double().cpu().numpy())
    found = MaterialFile(pb.driver_E().detach().double().cpu().numpy(), np.zeros_like(rest), rest, {})
    return found.E_at(points), start, whole_clip_loss(pb, pushes)


def degrade(frames: np.ndarray, rng) -> np.ndarray:
    """What a camera adds: blur, an exposure change and pixel noise. frames uint8 [T, H, W, 3]."""
    import torch

    x = torch.as_tensor(frames, dtype=torch.float32).permute(0, 3, 1, 2) / 255.0
    r = 2
    k = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float32) ** 2 / (2 * BLUR ** 2))
    k = k / k.sum()
    c = x.shape[1]
    x = torch.nn.functional.pad(x, (r, r, r, r), mode="replicate")
    x = torch.nn.functional.conv2d(x, k.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    x = torch.nn.functional.conv2d(x, k.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    y = x.permute(0, 2, 3, 1).numpy() * EXPOSURE + rng.normal(0.0, NOISE, x.permute(0, 2, 3, 1).shape)
    return (np.clip(y, 0, 1) * 255 + 0.5).astype(np.uint8)


def simulation(scene, up: str, static_below: float, grid: int, ratio: float, gaussian_E: np.ndarray, device: str,
               split: int = 0, min_per_cell: float = 0.0, most: int = SPLIT_MOST):
    """(prep, drivers, driver E) of one discretisation: K-Means drivers at `ratio` (at
    least `min_per_cell` a moving cell, PreparedScene.build_drivers), or with
    `split` > 0 every particle split into sub-particles, `split` a cell along each axis and
    at most `most` along each of a Gaussian's axes (pd_tool.prepare.split.split_particles),
    each with its particle's E."""
    from pd_tool.prepare.split import split_particles
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene

    prep = prepare_scene(scene, PrepareOptions(grid_res=grid, up_axis=up, static_below=static_below))
    if split > 0:
        drivers, owner = split_particles(scene, prep, per_cell=split, most=most, device=device)
        return prep, drivers, particle_E(prep, gaussian_E)[owner]
    drivers = prep.build_drivers(ratio=ratio, seed=0, device=device, min_per_cell=min_per_cell)
    return prep, drivers, driver_E(prep, drivers, gaussian_E)


def per_cell(prep, drivers) -> float:
    """Simulated particles per occupied cell of `prep`'s grid."""
    x = drivers.positions.double().cpu().numpy()
    return len(x) / len(np.unique(np.floor(x / prep.dx).astype(np.int64), axis=0))


def reference_videos(folder: Path, scene, up: str, sim, cfl: float, size: int, frames: int, device: str,
                     seed: int, clean: bool = False, views=VIEWS) -> tuple[list[Path], np.ndarray]:
    """Write the two reference videos, one per PUSHES seen from `views` ((azimuth, elevation)
    degrees each; as rendered with `clean`, else degraded as a camera would); returns their
    folders and each Gaussian's largest displacement in them [N] (scene units)."""
    from pd_tool.core.cameras import auto_camera
    from pd_tool.video.folder import write_video_folder
    from pd_tool.fit.reference import push_velocity, simulate_reference

    prep, drivers, e = sim
    rest = drivers.positions.double().cpu().numpy()
    static = drivers.static.cpu().numpy().astype(bool)
    pos0 = scene.positions.detach().cpu().numpy()
    moved = np.zeros(scene.count, np.float32)
    rng = np.random.default_rng(seed)
    out = []
    for k, ((az, el), push) in enumerate(zip(views, PUSHES)):
        cam = auto_camera(pos0, size, size * 9 // 16 if size >= 512 else size, up_axis=up, azimuth_deg=az,
                          elevation_deg=el)
        images = simulate_reference(scene, prep, drivers, e, push_velocity(rest, static, direction=push,
                                                                           speed=PUSH_SPEED),
                                    cam, n_frames=frames, fps=30.0, nu=0.3, cfl_safety=cfl, device=device,
                                    displacement=moved)
        frames_out = images if clean else degrade(images, rng)
        out.append(write_video_folder(folder / f"video{k}", frames_out, cam, 30.0, overwrite=True))
    return out, moved


def new_force(scene, up: str) -> tuple[tuple[float, float, float], tuple[float, float, float], float, float]:
    """(acceleration, point, radius, size) of the new force in scene units: diagonal in the
    horizontal plane, on the side of the object at NEW_FORCE['height'] of its height."""
    from pd_tool.prepare.preparation import up_rotation

    pos = scene.positions.detach().cpu().double().numpy()
    R = up_rotation(up)
    size = float(np.ptp(pos, axis=0).max())
    t = heights(pos, up)
    band = np.abs(t - NEW_FORCE["height"]) < 0.05
    lateral = pos @ R[0]
    point = pos[band][np.argmax(lateral[band])] if band.any() else pos[np.argmax(t)]
    d = np.asarray(NEW_FORCE["direction"]) / np.linalg.norm(NEW_FORCE["direction"])
    # m/s^2 along d in simulation axes; pdtool scales a scene to 1 m, so a scene unit is 1 / size m
    accel = tuple((R.T @ d) * NEW_FORCE["accel"] * size)
    return accel, tuple(point.tolist()), NEW_FORCE["radius"] * size, size


UPS = ("+x", "-x", "+y", "-y", "+z", "-z", "auto")


def capture_spec(text: str) -> tuple[str, str, str]:
    """--capture: "NAME=PATH[:UP]" -> (NAME, PATH, UP), UP one of UPS ("auto", the default,
    takes pdtool's guess from the splats). NAME may not be a built-in scene's."""
    name, eq, rest = text.partition("=")
    path, colon, up = rest.rpartition(":")
    if not colon or up not in UPS:  # no axis given (a colon may belong to the path)
        path, up = rest, "auto"
    if not eq or not name or not path or name in SCENES or "," in name:
        raise argparse.ArgumentTypeError(
            f"{text!r}: give NAME=PATH[:UP] with a NAME other than {', '.join(SCENES)} and UP one of {', '.join(UPS)}")
    return name, path, up


def views_spec(text: str) -> tuple[tuple[float, float], ...]:
    """--views: "AZ:EL,AZ:EL" (degrees) -> one (azimuth, elevation) per video, as many as PUSHES."""
    try:
        views = tuple((float(az), float(el)) for az, el in (v.split(":") for v in text.split(",")))
    except ValueError:
        views = ()
    if len(views) != len(PUSHES) or not all(-90.0 < el < 90.0 for _, el in views):
        raise argparse.ArgumentTypeError(
            f"{text!r}: give {len(PUSHES)} views as AZ:EL,AZ:EL in degrees, elevations between -90 and 90")
    return views


# the run's scale: the GPU rows' defaults, and --quick's CI scale; a flag given wins over both
SCALE = {"gaussians": 30000, "quality": "default", "reference": 128, "size": 512, "frames": 14, "seconds": 1.5,
         "bake_qualities": "default,final"}
QUICK = {"gaussians": 3000, "quality": "draft", "reference": 48, "size": 96, "frames": 10, "seconds": 1.0,
         "bake_qualities": ""}


def fill_scale(args: argparse.Namespace) -> None:
    """Give each scale option the user left out (None) its default, --quick's with --quick."""
    for key, value in (QUICK if args.quick else SCALE).items():
        if getattr(args, key) is None:
            setattr(args, key, value)


def scene_counts(text: str) -> dict[str, int]:
    """--scene-gaussians: "donut=50000,udon=3000" -> {"donut": 50000, "udon": 3000}."""
    out = {}
    for item in filter(None, text.split(",")):
        name, _, count = item.partition("=")
        if name not in SCENES or not count.isdigit() or int(count) < 1:
            raise argparse.ArgumentTypeError(f"{item!r}: give SCENE=N with SCENE one of {', '.join(SCENES)}")
        out[name] = int(count)
    return out


def override_fit_defaults(items: list[str]) -> None:
    """`--set FIELD=VALUE`: `pdtool fit` (run in this process) builds its settings from a
    subclass of FitSettings with these defaults."""
    from fit_recovery import setting_overrides

    overrides = setting_overrides(items)
    if overrides:
        _fit_defaults(overrides)


def unapplied(recorded: dict, overrides: dict) -> list[str]:
    """The --set fields whose value the fit did not run at: `recorded` is the settings a
    fit wrote into its material file (meta["settings"]). `pdtool fit` passes some fields
    from its own flags (--polish, --diffusion, --material-iters, ...), which a changed
    default cannot reach; one line per field naming the value it ran at."""
    return [f"--set {k}={v!r} did not reach the fit, which ran at {recorded.get(k)!r}: `pdtool fit` passes "
            f"{k} from its own flag; give that flag in --fit-args instead (pdtool fit --help)"
            for k, v in overrides.items() if recorded.get(k) != v]


def _fit_defaults(overrides: dict):
    """Make `pdtool fit` (run in this process) build its settings from a subclass of
    FitSettings with these defaults; returns the class it replaced."""
    import dataclasses

    import pd_tool.fit.settings as fs

    base = fs.FitSettings
    names = {f.name: f for f in dataclasses.fields(base)}
    for key in overrides:
        if key not in names:
            raise SystemExit(f"--set {key}: FitSettings has no such field")
    fs.FitSettings = dataclasses.make_dataclass(
        "FitSettings", [(k, names[k].type, dataclasses.field(default=v)) for k, v in overrides.items()], bases=(base,))
    return base


@contextlib.contextmanager
def field_alone():
    """`pdtool fit` in the block fits E's field alone: no per-driver residuals (the caller
    adds --no-level, the stage-1 level being folded into them)."""
    import pd_tool.fit.settings as fs

    base = _fit_defaults({"driver_residual": False})
    try:
        yield
    finally:
        fs.FitSettings = base


def fit_quality(quality: str, grid: int, floor: float | None, folder: Path) -> str:
    """A quality file in the existing `folder`: `quality` with the fit on `grid` cells (0: as it is) and
    `floor` drivers a moving cell (None: as it is); its path. The bakes at a named quality
    are unchanged."""
    from pd_tool.materials.presets import load_preset

    q = {k: v for k, v in load_preset("quality", quality).items() if k != "name"}
    if grid:
        q["fit_grid_res"] = grid
    if floor is not None:
        q["fit_min_drivers_per_cell"] = floor
    path = Path(folder) / f"fit{grid or ''}_floor{floor if floor is not None else ''}.toml"
    path.write_text("".join(f"{k} = {json.dumps(v)}\n" for k, v in q.items()))
    return str(path)


def cli(args: list[str]) -> str:
    """Run pdtool in this process; returns what it printed."""
    from click.testing import CliRunner

    from cli import main

    res = CliRunner().invoke(main, args, catch_exceptions=False)
    if res.exit_code != 0:
        raise RuntimeError(f"pdtool {' '.join(args[:1])} failed ({res.exit_code}): {res.output[-2000:]}")
    return res.output


# pd_tool.bake.transfer.MotionMatch.line, as `pdtool bake` prints it
MATCH_LINE = re.compile(r"fitted material matched to this grid: E x([0-9.eE+-]+),")


def match_factor(bake_output: str) -> float:
    """The factor by which `pdtool bake` scaled the fitted E so that its grid moves as the
    fit's did (its report line); 1 where it baked the fitted E as it is."""
    found = MATCH_LINE.search(bake_output)
    return float(found.group(1)) if found else 1.0


def bake_positions(folder: Path, name: str, scene_path: Path, material: list[str], force, seconds: float,
                   device: str, up: str, extra: list[str]) -> tuple[np.ndarray, float]:
    """`pdtool bake` under the new force; positions [T, N, 3] in scene axes, read back
    from its USD (whose axes follow pd_tool.bake.baker.usd_frame), and the factor the bake
    scaled a fitted E by (match_factor)."""
    from pxr import Usd

    from pd_tool.bake.baker import usd_frame

    accel, point, radius, _ = force
    out = folder / f"{name}.usd"
    printed = cli(["bake", "--scene", str(scene_path), *material, "--force", ",".join(f"{a:.9g}" for a in accel), "--force-units", "scene",
         "--at", ",".join(f"{a:.9g}" for a in point), "--radius", f"{radius:.9g}",
         "--duration", str(NEW_FORCE["duration"]), "--seconds", str(seconds), "--format", "instancer",
         "--device", device, *extra, str(out)])
    stage = Usd.Stage.Open(str(out))  # held: its prims expire with it
    frames = int(round(seconds * 30)) + 1
    R = usd_frame(up)[0]
    # every instance by id: pinned ones sit on their own prim, written once
    x = np.stack([instance_positions(stage, float(f))[1].astype(np.float64) for f in range(frames)]) @ R
    return x, match_factor(printed)


def truth_material(fitted, pos: np.ndarray, E_true: np.ndarray, path: Path) -> Path:
    """The fitted material file with each driver's E replaced by the truth's geometric mean
    over the Gaussians nearest to it."""
    import torch

    from pd_tool.drivers import nearest_drivers
    from pd_tool.materials.file import MaterialFile

    rest = fitted.driver_rest
    near = nearest_drivers(torch.as_tensor(pos, dtype=torch.float64), torch.as_tensor(rest, dtype=torch.float64),
                           k=1)[:, 0].numpy()
    log_e, count = group_log_mean(near, E_true, len(rest))
    # a driver no Gaussian is nearest to (a filled particle's) takes its nearest Gaussian's E
    empty = count == 0
    if empty.any():
        g = nearest_drivers(torch.as_tensor(rest[empty]), torch.as_tensor(pos, dtype=torch.float64), k=1)[:, 0].numpy()
        log_e[empty] = np.log(E_true[g])
    return MaterialFile(np.exp(log_e), fitted.driver_v0, rest, dict(fitted.meta), fitted.fields).save(path)


def ranks(x: np.ndarray) -> np.ndarray:
    """Ranks [M] from 0, ties sharing their mean rank: every Gaussian of a driver carries its
    driver's E, so a fitted E is mostly ties, and ranking them in index order would
    correlate the scene's storage order."""
    _, inverse, counts = np.unique(x, return_inverse=True, return_counts=True)
    return (np.cumsum(counts) - (counts + 1) / 2.0)[inverse]


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of a [M] and b [M]; NaN with fewer than three values or
    when either is constant (no order to compare)."""
    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return math.nan
    return float(np.corrcoef(ranks(a), ranks(b))[0, 1])


def e_error(E_fit: np.ndarray, E_true: np.ndarray) -> dict[str, float]:
    """How far E_fit [M] is from E_true [M] (Pa): median |ln(E_fit / E_true)|, its level
    (median ln) and shape (median |ln| about that level), and Spearman's rank correlation."""
    ln = np.log(E_fit / E_true)
    level = float(np.median(ln))
    return {"median_abs_ln": float(np.median(np.abs(ln))), "median_ln": level,
            "shape_abs_ln": float(np.median(np.abs(ln - level))), "spearman": spearman(E_fit, E_true)}


def thin_split(scene, prepare: dict, sel: np.ndarray, E_fit: np.ndarray, E_true: np.ndarray) -> dict:
    """e_error over the selected Gaussians (sel [N] bool) that lie in thin parts on the
    fit's grid (pd_tool.prepare.thickness.thin_mask, the scene prepared with the fit's
    `prepare` options) and over the other selected ones, each where more than two; with
    the thin ones' share of sel and the fit's cell dx_m."""
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.prepare.thickness import thin_mask

    prep = prepare_scene(scene, PrepareOptions.from_dict(prepare))
    mask = thin_mask(prep.positions_sim, ~prep.static, prep.dx, prep.volumes)
    thin = np.zeros(len(sel), bool)
    thin[prep.foreground] = mask[: prep.count]
    out: dict = {"share": float(thin[sel].mean()), "dx_m": float(prep.dx)}
    for key, part in (("thin", sel & thin), ("other", sel & ~thin)):
        if part.sum() > 2:
            out[key] = e_error(E_fit[part], E_true[part])
    return out


def load_scene(name: str, gaussians: int, data: Path, path: str | None = None):
    """The thin plant (make_plant(thin=True), as bench/convergence.py has it), a capture
    from `data`, or the splat file `path` (--capture), at most `gaussians` of it kept (seed
    0: the same ones as convergence.py)."""
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import make_plant

    if name == "plant" and path is None:
        return make_plant(gaussians, seed=0, thin=True)
    scene = load_splats(Path(path) if path is not None else data / CAPTURES[name])
    if scene.count <= gaussians:
        return scene
    return scene.subset(np.sort(np.random.default_rng(0).choice(scene.count, gaussians, replace=False)))


def run_case(name: str, kind: str, args, tmp: Path) -> Row:
    from fit_recovery import setting_overrides
    from pd_tool.fit.reference import simulate_positions
    from pd_tool.io import save_splats
    from pd_tool.materials.file import MaterialFile
    from pd_tool.fit.settings import FitSettings
    from pd_tool.prepare.preparation import up_rotation
    from pd_tool.materials.presets import fit_min_per_cell, fit_simulation, load_preset

    path, up = args.captures.get(name, (None, SCENES.get(name)))
    scene = load_scene(name, args.scene_gaussians.get(name, args.gaussians), args.data, path)
    if up == "auto":
        from pd_tool.render.views import auto_up

        up = auto_up(scene)[0]
    scene = scene.to(args.device)
    pos = scene.positions.detach().cpu().double().numpy()
    h = pos @ up_rotation(up)[2]
    static_below = float(h.min() + 0.1 * np.ptp(h))
    folder = tmp / f"{name}_{kind}"
    folder.mkdir()
    scene_path = save_splats(scene.to("cpu"), folder / f"{name}.ply")
    E_true = truth_field(scene, up, kind, args.seed)
    q = load_preset("quality", args.quality)
    floor = 0.0
    if args.control:
        grid, cfl, ratio = fit_simulation(q)
        floor = fit_min_per_cell(q)
        label = "control (the fit's own discretisation)"
    else:
        grid, cfl, ratio = args.reference, 0.25, 1.0
        label = (f"converged ({grid} cells, every particle split {args.split} a cell along each axis, CFL 0.25)"
                 if args.split else f"{grid} cells, every Gaussian one particle, CFL 0.25")
    split = 0 if args.control else args.split
    size = float(np.ptp(pos, axis=0).max())
    force = new_force(scene, up)

    def under_new_force(sim_) -> np.ndarray:
        prep_, drivers_, e_ = sim_
        return simulate_positions(scene, prep_, drivers_, e_, nu=0.3, seconds=args.seconds, fps=30.0,
                                  accel=force[0], device=args.device, cfl_safety=0.25,
                                  duration=NEW_FORCE["duration"], at=force[1], radius=force[2])

    t0 = time.perf_counter()
    sim = simulation(scene, up, static_below, grid, ratio, E_true, args.device, split, floor, args.split_most)
    # the truth under the new force, at the converged settings whatever the videos used
    ref = sim if not args.control else simulation(scene, up, static_below, args.reference, 1.0, E_true, args.device,
                                                  args.split, most=args.split_most)
    row = Row(name, kind, label, up, reference_particles=len(ref[1].positions), reference_per_cell=per_cell(*ref[:2]))
    x_true = under_new_force(ref)
    judge = Judge.of(ref[0], x_true, size)
    free, moving, peak, off = judge.free, judge.moving, judge.peak, judge.off
    row.seconds["truth"] = time.perf_counter() - t0

    row.errors["truth peak"] = peak(x_true)
    if args.check_reference:  # the truth again on a finer grid: how far from converged it is
        t0 = time.perf_counter()
        check = simulation(scene, up, static_below, args.check_reference, 1.0, E_true, args.device, args.split,
                           most=args.split_most)
        x_check = under_new_force(check)
        row.reference_check = {
            "grid": args.check_reference, "particles": len(check[1].positions), "per_cell": per_cell(*check[:2]),
            "rms": off(x_check), "peak_ratio": peak(x_check) / max(peak(x_true), 1e-12)}
        row.seconds["check"] = time.perf_counter() - t0
    if args.reference_only:
        return row
    t0 = time.perf_counter()
    videos, moved = reference_videos(folder, scene, up, sim, cfl, args.size, args.frames, args.device, args.seed,
                                     args.clean, args.views)
    row.seconds["videos"] = time.perf_counter() - t0

    def fit(material: Path, *extra: str) -> None:
        """`pdtool fit` of the videos to `material`, as the row's fit runs (--fit-args), then `extra`."""
        cli(["fit", str(scene_path), *map(str, videos), "-o", str(material), "--quality", args.quality, "--up", up,
             "--static-below", f"{static_below:.9g}", "--device", args.device, "--no-preview",
             *args.fit_args.split(), *extra])

    t0 = time.perf_counter()
    out = folder / "fit.pdmat"
    if args.warm_from_field:
        # E's smooth pattern first, where the per-driver residuals scatter it least, then
        # the row's own fit from it, for the contrast a field alone cannot hold
        with field_alone():
            fit(folder / "field.pdmat", "--no-level")
        row.seconds["field fit"] = time.perf_counter() - t0
        fit(out, "--init-material", str(folder / "field.pdmat"))
    elif args.warm_from_truth:
        # the product's fit started from the answer: the drivers come from a fit that fits
        # nothing (one stage-1 iteration, no E), the true E is put on them, and the row's
        # fit starts there. If it keeps the truth, the fit from the uniform start stops
        # short of an E that its loss prefers; if it leaves it, its loss or its step sizes
        # lead it away (--losses and --control tell the two apart)
        fit(folder / "drivers.pdmat", "--velocity-iters", "1", "--material-iters", "0", "--no-level")
        truth_start = truth_material(MaterialFile.load(folder / "drivers.pdmat"), pos, E_true,
                                     folder / "truth_start.pdmat")
        row.seconds["drivers fit"] = time.perf_counter() - t0
        fit(out, "--init-material", str(truth_start))
    else:
        fit(out)
    row.fit_s = time.perf_counter() - t0
    fitted_file = MaterialFile.load(out)
    row.fit_metrics = {k: fitted_file.meta["metrics"].get(k)
                       for k in ("loss_start", "loss_final", "kept_iteration", "stage2_retried", "skipped_material_steps")}
    lost = unapplied(fitted_file.meta.get("settings", {}), setting_overrides(args.set))
    if lost:  # a row fitted at other settings than asked would be reported as if it had not been
        print("\n".join(lost), file=sys.stderr)
        raise SystemExit(2)
    E_fit = fitted_file.E_at(pos)
    sel = moved > MOVING * size
    row.moving_share = float(sel.mean())
    if sel.sum() > 2:
        for key, value in e_error(E_fit[sel], E_true[sel]).items():
            setattr(row, key, value)
        row.thin_split = thin_split(scene, fitted_file.meta["prepare"], sel, E_fit, E_true)
    E_uniform = float(FitSettings().init_E)  # `pdtool fit`'s --init-e default
    E_best = float(np.exp(np.mean(np.log(E_true[free]))))
    if sel.sum() > 2:
        row.baseline_abs_ln = {k: float(np.median(np.abs(np.log(e / E_true[sel]))))
                               for k, e in (("uniform start", E_uniform), ("best uniform", E_best))}
    # the true E on the fit's drivers, baked as the fitted E is (as fit, and at each bake
    # quality as it is): what an exact recovery of E would score on that discretisation
    truth = truth_material(fitted_file, pos, E_true, folder / "truth.pdmat")
    # the uniform start on the fit's drivers: what the fit gained on its own discretisation
    start = MaterialFile(np.full(len(fitted_file.driver_rest), float(FitSettings().init_E)), fitted_file.driver_v0,
                         fitted_file.driver_rest, dict(fitted_file.meta), fitted_file.fields).save(folder / "start.pdmat")
    settings = FitSettings.from_dict(fitted_file.meta["settings"])  # what the fit ran at, for the diagnostics
    if args.given_push and sel.sum() > 2:
        # E's search alone: stage 2 with the true pushes, so no error of stage 1's v0 can
        # pull E away; what it leaves is the E search's own (or, against a converged
        # reference, the model's discretisation's)
        t0 = time.perf_counter()
        E_given, start_loss, end_loss = given_push_fit(scene_path, videos, settings.resolved(),
                                                       fitted_file.meta["prepare"], E_true, pos)
        row.given_push = {**e_error(E_given[sel], E_true[sel]), "loss_start": start_loss, "loss_final": end_loss}
        row.seconds["given push"] = time.perf_counter() - t0
    if args.losses:
        # Does the fit's own model prefer the truth? v0 refitted under each E (stage 1 alone,
        # no level), then the whole-clip loss: the truth scoring above the fitted E means the
        # model's discretisation or v0 field, not the optimiser, pulls E away from it. And the
        # truth with the true pushes, which no fitted v0 stands in for
        row.losses["fitted"] = float(row.fit_metrics["loss_final"])
        t0 = time.perf_counter()
        exact = exact_pair_loss(scene_path, videos, settings.resolved(), fitted_file.meta["prepare"], E_true)
        if exact is not None:
            row.losses["true E, true push"] = exact
        row.seconds["loss true E, true push"] = time.perf_counter() - t0
        for key, start_args in (("fitted, v0 refitted", ["--init-material", str(out)]),
                                ("true E", ["--init-material", str(truth)]), ("uniform start", [])):
            t0 = time.perf_counter()
            again = folder / f"loss_{key.split(',')[0].replace(' ', '_')}.pdmat"
            fit(again, "--material-iters", "0", "--no-level", *start_args)
            row.losses[key] = float(MaterialFile.load(again).meta["metrics"]["loss_final"])
            row.seconds[f"loss {key}"] = time.perf_counter() - t0
    bakes = {"fitted, as fit": (["--material", str(out)], []), "true E, as fit": (["--material", str(truth)], []),
             "uniform start, as fit": (["--material", str(start)], [])}
    for qname in args.bake_qualities:
        # the product's bake (matched to the fit's motion first) and the fitted E as it is
        bakes[f"fitted, {qname}"] = (["--material", str(out)], ["--quality", qname])
        bakes[f"fitted as is, {qname}"] = (["--material", str(out)], ["--quality", qname, "--no-match-fit"])
        bakes[f"true E, {qname}"] = (["--material", str(truth)], ["--quality", qname, "--no-match-fit"])
    for label_e, E in (("uniform start", E_uniform), ("best uniform", E_best)):
        mat = folder / f"{label_e.replace(' ', '_')}.toml"
        mat.write_text(f"E = {E:.9g}\nnu = 0.3\ndensity = 1000.0\n")
        # at the fit's quality, and at each bake quality: a fitted bake is judged against
        # a uniform one on the same grid
        for qname in dict.fromkeys([args.quality, *args.bake_qualities]):
            bakes[uniform_bake(label_e, qname, args.quality)] = (
                ["--preset", str(mat)], ["--quality", qname, "--up", up, "--static-below", f"{static_below:.9g}"])
    for bname, (material, extra) in bakes.items():
        t0 = time.perf_counter()
        x, factor = bake_positions(folder, bname.replace(" ", "_").replace(",", ""), scene_path, material, force,
                                   args.seconds, args.device, up, extra)
        row.errors[bname] = off(x)
        if bname.removeprefix("fitted, ") in args.bake_qualities and sel.sum() > 2:
            # the E the product's bake moves with, against the truth: the match takes out
            # the level the fit's coarser grid puts on E, not its shape
            row.match_factor[bname] = factor
            row.matched_abs_ln[bname] = float(np.median(np.abs(np.log(factor * E_fit[sel] / E_true[sel]))))
        row.seconds[f"bake {bname}"] = time.perf_counter() - t0
    # what a material that does not move at all would score
    row.errors["still"] = float(np.sqrt((np.linalg.norm(x_true[:, moving] - x_true[0, moving], axis=-1) ** 2).mean())
                                / size)
    fitted = row.errors["fitted, as fit"]
    row.ratios = {"uniform start / fitted": row.errors["uniform start"] / fitted,
                  "best uniform / fitted": row.errors["best uniform"] / fitted,
                  "uniform start / fitted, as fit": row.errors["uniform start, as fit"] / fitted}
    for qname in args.bake_qualities:
        # each bake quality against the uniform E baked at that quality
        for label_e in ("uniform start", "best uniform"):
            for what in ("fitted", "true E"):
                ratio = row.errors[uniform_bake(label_e, qname, args.quality)] / row.errors[f"{what}, {qname}"]
                row.ratios[f"{label_e} / {what}, {qname}"] = ratio
    row.goals = goals(row.errors, args.bake_qualities, args.quality,
                      row.reference_check["rms"] if row.reference_check else None)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="CPU, CI scale: plant and udon, smooth field, 3000 Gaussians, draft, 96 px, reference 48, "
                         "10 frames (each of these options, given, still wins)")
    ap.add_argument("--scenes", default=None, help=f"comma-separated, of {','.join(SCENES)} (default: all)")
    ap.add_argument("--fields", default=None, help=f"comma-separated, of {','.join(FIELDS)} (default: all)")
    ap.add_argument("--capture", type=capture_spec, action="append", default=[], metavar="NAME=PATH[:UP]",
                    help="also a capture of your own (any splat file pdtool reads), run as scene NAME; UP is its "
                         "up axis (+x ... -z, or auto: pdtool's guess, the default). Repeatable. With --capture "
                         "and no --scenes, only the captures run; it takes --gaussians")
    ap.add_argument("--views", type=views_spec, default=VIEWS, metavar="AZ:EL,AZ:EL",
                    help="the two videos' camera azimuth and elevation, degrees (default: "
                         + ",".join(f"{az:g}:{el:g}" for az, el in VIEWS) + ")")
    ap.add_argument("--gaussians", type=int, default=None, help="default 30000 (--quick: 3000)")
    ap.add_argument("--scene-gaussians", type=scene_counts, default={}, metavar="SCENE=N[,SCENE=N]",
                    help="another --gaussians for these scenes, e.g. donut=50000: 20,000 of the donut's 45,624 "
                         "Gaussians close its shell to 87%%, under the fill's 90%%, so it is simulated hollow")
    ap.add_argument("--reference", type=int, default=None,
                    help="the converged simulation's grid cells (default 128; --quick: 48)")
    ap.add_argument("--quality", default=None, help="the fit's quality (default: default; --quick: draft)")
    ap.add_argument("--bake-qualities", default=None,
                    help="fitted material also baked at these (default: default,final; --quick: none)")
    ap.add_argument("--split", type=int, default=2,
                    help="the reference's sub-particles per cell along each axis (0: one particle per Gaussian, "
                         "about one a cell on a fine grid, which separates under a push)")
    ap.add_argument("--split-most", type=int, default=SPLIT_MOST,
                    help="the reference's most sub-particles along each of a Gaussian's axes (a long strand's "
                         "Gaussians, as udon's, need more than 4 to fill a fine grid)")
    ap.add_argument("--check-reference", type=int, default=0,
                    help="also simulate the truth on this many cells and report how far it is from the reference "
                         "(RMS / size, peak ratio): whether the reference has converged (0: no check)")
    ap.add_argument("--reference-only", action="store_true",
                    help="only the truth under the new force (and --check-reference): no videos, fit or bakes")
    ap.add_argument("--size", type=int, default=None, help="reference frames' long side, px (default 512; --quick: 96)")
    ap.add_argument("--frames", type=int, default=None, help="frames a video (default 14; --quick: 10)")
    ap.add_argument("--seconds", type=float, default=None, help="the new force's animation (default 1.5; --quick: 1.0)")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a FitSettings default of `pdtool fit`, e.g. --set driver_residual=false "
                         "(repeatable). A field that `pdtool fit` passes from its own flag (--polish, "
                         "--diffusion, ...) is not reached: the first fit stops the run, naming it; give "
                         "the flag in --fit-args")
    ap.add_argument("--fit-args", default="", help="extra `pdtool fit` flags, e.g. '--diffusion 0.2'")
    ap.add_argument("--fit-grid", type=int, default=0,
                    help="fit on this many cells instead of --quality's fit_grid_res (0: the quality's)")
    ap.add_argument("--fit-floor", type=float, default=None,
                    help="the fit's floor of drivers a moving cell instead of --quality's fit_min_drivers_per_cell")
    ap.add_argument("--losses", action="store_true",
                    help="also the fit's whole-clip video loss under the fitted E, the true E and the uniform start, "
                         "each with v0 refitted under it (three more stage-1 fits a row), and under the true E "
                         "with the true pushes: does the fit's own model prefer the truth?")
    ap.add_argument("--given-push", action="store_true",
                    help="also the fit's E search alone: its stage 2 from the uniform start with each video's v0 "
                         "held at the true push (no stage 1), and the same E error and whole-clip loss: does E "
                         "find the truth once v0 is right?")
    ap.add_argument("--control", action="store_true", help="reference videos at the fit's own discretisation")
    ap.add_argument("--warm-from-field", action="store_true",
                    help="fit E's field alone first (no per-driver residuals, no stage-1 level), then the row's fit "
                         "warm-started from it (--init-material); the row's fit time counts both")
    ap.add_argument("--warm-from-truth", action="store_true",
                    help="start the row's fit from the true E on its drivers (--init-material) instead of the "
                         "uniform start: does the fit keep the truth, or does its loss lead it away?")
    ap.add_argument("--clean", action="store_true",
                    help="reference videos as rendered: no blur, exposure change or noise (with --losses: does "
                         "the camera's degradation, or the model, let the fit prefer another E to the truth?)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--keep", type=Path, help="keep every scene, video, fit and USD in this new folder")
    args = ap.parse_args()
    args.captures = {}
    for name, path, up in args.capture:
        if name in args.captures:
            ap.error(f"--capture {name} given twice; give each capture its own NAME")
        if not Path(path).is_file():
            ap.error(f"--capture {name}={path}: no such file")
        args.captures[name] = (str(Path(path).resolve()), up)
    if args.captures and not args.scenes:
        args.scenes = ",".join(args.captures)
    if args.quick:
        args.scenes, args.fields = args.scenes or "plant,udon", args.fields or "smooth"
    if args.warm_from_field and args.warm_from_truth:
        ap.error("--warm-from-field and --warm-from-truth are two starts; give one")
    fill_scale(args)
    args.bake_qualities = [q for q in args.bake_qualities.split(",") if q]
    args.scenes, args.fields = args.scenes or ",".join(SCENES), args.fields or ",".join(FIELDS)
    for name in args.scenes.split(","):
        if name not in SCENES and name not in args.captures:
            ap.error(f"--scenes {name}: not one of {', '.join([*SCENES, *args.captures])} (a capture of your own: "
                     "--capture NAME=PATH[:UP])")
    for kind in args.fields.split(","):
        if kind not in FIELDS:
            ap.error(f"--fields {kind}: not one of {', '.join(FIELDS)}")

    from pd_tool.core.device import init_warp_quietly

    init_warp_quietly()
    override_fit_defaults(args.set)
    rows = []
    print("scene  field   fit s  |ln|   rho  then each bake's new-force error (RMS / size), and the ratios", flush=True)
    if args.keep:
        args.keep.mkdir(parents=True)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = args.keep or tmp
        if args.fit_grid or args.fit_floor is not None:  # the fit's discretisation, from a derived quality file
            args.quality = fit_quality(args.quality, args.fit_grid, args.fit_floor, Path(tmp))
        for name in args.scenes.split(","):
            for kind in args.fields.split(","):
                row = run_case(name, kind, args, Path(tmp))
                rows.append(row)
                errs = "  ".join(f"{k} {v:.2%}" for k, v in row.errors.items())
                ratios = "  ".join(f"{k} {v:.2f}" for k, v in row.ratios.items())
                base = "  ".join(f"{k} {v:.2f}" for k, v in row.baseline_abs_ln.items())
                print(f"{name:6} {kind:7} {row.fit_s:5.0f} {row.median_abs_ln:5.2f} {row.spearman:5.2f}  level "
                      f"{row.median_ln:+.2f} shape {row.shape_abs_ln:.2f} (|ln| of {base})  {errs}  |  {ratios}",
                      flush=True)
                if row.thin_split:
                    ts = row.thin_split
                    print(f"       E in parts under a quarter of the fit's {ts['dx_m'] * 100:.2g} cm cell "
                          f"({ts['share']:.0%} of the moving): " + "; ".join(
                              f"{k} |ln| {ts[k]['median_abs_ln']:.2f} (level {ts[k]['median_ln']:+.2f})"
                              for k in ("thin", "other") if k in ts), flush=True)
                if row.match_factor:
                    print("       the bake's E against the truth: " + "  ".join(
                        f"{k}: E x{row.match_factor[k]:.3g}, |ln| {row.matched_abs_ln[k]:.2f}" for k in row.match_factor),
                        flush=True)
                for q, per_goal in row.goals.items():
                    print(f"       goals at {q}: " + "  ".join(
                        f"{g}: asks {v['asks']:.2%}, {'met' if v['met'] else 'missed'}"
                        + (" (within the reference's own error)" if v["measurable"] is False else "")
                        for g, v in per_goal.items()), flush=True)
                if row.given_push:
                    g = row.given_push
                    print(f"       given the true pushes: |ln| {g['median_abs_ln']:.2f}, level {g['median_ln']:+.2f}, "
                          f"shape {g['shape_abs_ln']:.2f}, rho {g['spearman']:.2f}; whole-clip loss "
                          f"{g['loss_start']:.5f} -> {g['loss_final']:.5f}", flush=True)
                if row.losses:
                    print("       whole-clip loss: " + "  ".join(f"{k} {v:.5f}" for k, v in row.losses.items()),
                          flush=True)
                print(f"       reference {row.reference_particles:,} particles, {row.reference_per_cell:.1f} a cell"
                      + ("" if not row.reference_check else "; on {grid} cells ({per_cell:.1f} a cell) RMS {rms:.2%}"
                         " of the size, peak x{peak_ratio:.3f}".format(**row.reference_check)), flush=True)
                if args.json:  # after every row: a run cut short keeps what it measured
                    import torch

                    args.json.write_text(json.dumps({
                        "device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
                        "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                        "rows": [asdict(r) for r in rows]}, indent=2))


if __name__ == "__main__":
    main()
