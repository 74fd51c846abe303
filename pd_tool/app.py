"""Use cases from paths: what `cli.py`, the demo, batch jobs and the Blender add-on share.

A frontend parses its own input (options, a jobs file, a panel) into a `FitJob` or a
`BakeJob` and calls `fit` or `bake` here. These functions read the files, check every
destination before any work, run the stage and write the outputs; they print nothing, so
each frontend reports in its own way. Stages below never import this module.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from pd_tool.bake import BakeResult, BakeSettings, ForceSpec
from pd_tool.bake import bake as run_bake
from pd_tool.core.atomic import check_destination, check_outputs
from pd_tool.core.errors import MissingInput, OutputError
from pd_tool.fit.outputs import check_fit_outputs, write_fit_outputs
from pd_tool.fit.run import FitResult, run_fit
from pd_tool.fit.settings import FitSettings
from pd_tool.io import load_splats
from pd_tool.materials.file import MaterialFile, check_record, is_material_file, read_record, write_record
from pd_tool.materials.presets import Material, load_preset
from pd_tool.prepare import PrepareOptions
from pd_tool.prepare.work import WorkEstimate, work_policy
from pd_tool.render.views import scene_camera
from pd_tool.video.clip import MAX_FPS, MAX_FRAMES, ClipChoice, prepare_clip
from pd_tool.video.folder import load_reference_video

FitProgress = Callable[[str, int, int, float], None]  # (stage, iteration, total, loss)
BakeProgress = Callable[[int, int], None]  # (frames done, total)


@dataclass
class FitJob:
    """A fit as a user names it.

    scene: the splat file; videos: reference-video folders or .mp4 files, one per view;
    out: the material file (.pdmat). `out_named`: the user named `out`; an unnamed default
    (SCENE.pdmat) replaces only a pdtool material file. `record_dir`: the folder whose
    last-fit record a plain `pdtool bake` there reads. start, max_frames, max_fps and
    stabilise: which frames of each clip the fit uses and whether a shaken camera is
    warped back onto frame 0's view (pd_tool.video.clip).
    """

    scene: Path
    videos: Sequence[Path]
    out: Path
    settings: FitSettings = field(default_factory=FitSettings)
    prepare: PrepareOptions = field(default_factory=PrepareOptions)
    camera: Path | None = None
    view: str | int | None = None
    fps: float | None = None
    preview: bool = True
    resume: bool = False
    out_named: bool = True
    record_dir: Path = Path(".")
    start: int = 0
    max_frames: int | None = MAX_FRAMES
    max_fps: float | None = MAX_FPS
    stabilise: bool = True


@dataclass
class FitDone:
    result: FitResult
    side: dict[str, Path]  # kind -> path of the side outputs (report, loss plot, E field, preview)
    estimate: WorkEstimate | None  # the last run-time estimate, None when none was made
    clips: list[ClipChoice] = field(default_factory=list)  # per video: the frames used, stabilised or not


def check_fit_destinations(job: FitJob) -> None:
    """Before a fit runs: its side outputs and the last-fit record replace only pdtool's
    own files, and a material file nobody named (SCENE.pdmat) only a pdtool material file."""
    inputs = {"SCENE": job.scene, **{f"VIDEO {i}": v for i, v in enumerate(job.videos)},
              "--init-material": job.settings.init_material}
    check_outputs({"--out": job.out}, {}, inputs)
    if not job.out_named and (job.out.exists() or job.out.is_symlink()) and not is_material_file(job.out):
        raise OutputError(f"{job.out}: exists and is not a pdtool material file, which the fit would replace; move "
                          "or rename it, or name the material file with -o", path=job.out)
    check_destination(job.out)
    check_fit_outputs(job.out.parent, job.out.stem, preview=job.preview, inputs=inputs)
    check_record(job.record_dir)


def fit(job: FitJob, *, progress: FitProgress | None = None, max_minutes: float | None = None,
        on_estimate: Callable[[WorkEstimate], None] | None = None,
        say: Callable[[str], None] | None = None) -> FitDone:
    """Fit the material of `job.scene` to its videos and write the material file, its side
    outputs and the last-fit record. Refused (WorkTooLarge) before any work when the run-time
    estimate exceeds `max_minutes`. `say` gets a line per clip that was trimmed, thinned
    or stabilised."""
    load_preset("quality", job.settings.quality)
    check_fit_destinations(job)
    dev = job.settings.device
    refs = [load_reference_video(v, camera_path=job.camera, view=job.view, fps=job.fps,
                                 working_size=job.settings.working_long_side, device=dev) for v in job.videos]
    splats = load_splats(job.scene, device=dev)
    clips = []
    for i, v in enumerate(job.videos):
        refs[i], choice = prepare_clip(refs[i], start=job.start, max_frames=job.max_frames, max_fps=job.max_fps,
                                       still=job.stabilise, scene=splats)
        line = choice.line(str(v))
        if line is not None and say is not None:
            say(line)
        clips.append(choice)
    estimates: list[WorkEstimate] = []

    def estimated(est: WorkEstimate) -> None:
        estimates.append(est)
        if on_estimate is not None:
            on_estimate(est)

    with work_policy(max_minutes, estimated):
        result = run_fit(splats, job.scene, refs, job.out, prepare_options=job.prepare, settings=job.settings,
                         progress=progress, resume=job.resume)
    side = write_fit_outputs(job.out.parent, job.out.stem, splats, result, refs, job.settings.resolved(),
                             preview=job.preview, clips=[dataclasses.asdict(c) for c in clips])
    write_record(job.scene, job.out, job.record_dir)
    return FitDone(result, side, estimates[-1] if estimates else None, clips)


@dataclass
class BakeJob:
    """A bake as a user names it.

    The material is `preset` (a name or TOML file), or the fitted `material` file, or, with
    neither, the last fit recorded in `record_dir`. `scene` defaults to the material file's
    scene. `prepare` holds only the preparation options the user set; the rest come from
    the fit (its material file) or the defaults. `camera`/`view` place the preview's and
    `frames_out`'s camera (default: an automatic view).
    """

    out: Path
    force: ForceSpec
    settings: BakeSettings = field(default_factory=BakeSettings)
    scene: Path | None = None
    material: Path | None = None
    preset: str | Path | None = None
    prepare: dict = field(default_factory=dict)
    preview: Path | None = None
    frames_out: Path | None = None
    camera: Path | None = None
    view: str | int | None = None
    record_dir: Path = Path(".")


@dataclass
class BakeInputs:
    """What a BakeJob's names resolve to."""

    scene: Path
    material: Material | None  # a preset's homogeneous material
    material_file: MaterialFile | None  # a fitted material
    material_path: Path | None
    prepare: PrepareOptions


def resolve_bake_inputs(job: BakeJob) -> BakeInputs:
    """The scene file, the material and the preparation options a BakeJob names (one line
    naming the fix when one is missing or does not match)."""
    if job.preset is not None and job.material is not None:
        raise MissingInput("give a material preset or a material file, not both")
    scene, material_path = job.scene, job.material
    material = material_file = None
    if job.preset is not None:
        material = Material.from_preset(job.preset)
    else:
        if material_path is None:
            rec = read_record(job.record_dir)
            if rec is None:
                raise MissingInput("no material: pass --scene FILE with --preset NAME (see `pdtool presets`), "
                                 "or --material FILE, or run `pdtool fit` in this folder first")
            rec_scene, material_path = rec
            scene = scene or rec_scene
        material_file = MaterialFile.load(material_path)
    if scene is None:
        scene = material_file.scene_path if material_file is not None else None
        if scene is None or not scene.is_file():
            raise MissingInput("no scene: pass --scene FILE.ply (with --preset NAME or --material FILE)")
    if material_file is not None:
        material_file.check_scene(scene, material_path)
    if job.settings.quality is not None:
        load_preset("quality", job.settings.quality)
    # a fitted material keeps the up axis it was fitted with; a preset bake guesses it
    base = (PrepareOptions.from_dict(material_file.prepare) if material_file is not None
            else PrepareOptions(up_axis="auto"))
    return BakeInputs(scene, material, material_file, material_path, base.updated(**job.prepare))


def bake(job: BakeJob, *, progress: BakeProgress | None = None, max_minutes: float | None = None,
         on_estimate: Callable[[WorkEstimate], None] | None = None,
         match_progress: BakeProgress | None = None) -> BakeResult:
    """Bake `job` to USD (and its preview and frames, when asked). Refused (WorkTooLarge)
    before any work when the run-time estimate exceeds `max_minutes`. match_progress(runs,
    at most): while a fitted material is matched to the bake's grid, before the frames."""
    got = resolve_bake_inputs(job)
    splats = load_splats(got.scene, device=job.settings.device)
    cam = None
    if job.camera is not None:

        cam = scene_camera(splats, job.camera, job.view)
    with work_policy(max_minutes, on_estimate):
        return run_bake(splats, job.out, force=job.force, material=got.material, material_file=got.material_file,
                        prepare_options=got.prepare, settings=job.settings, preview=job.preview,
                        frames_dir=job.frames_out, camera=cam, inputs={"--material": got.material_path},
                        progress=progress, match_progress=match_progress)
