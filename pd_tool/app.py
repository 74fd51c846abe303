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
from pd_tool.core.errors import MissingInput, OutputError, RegistrationError
from pd_tool.fit.outputs import check_fit_outputs, write_fit_outputs
from pd_tool.fit.run import FitResult, run_fit
from pd_tool.fit.settings import FitSettings
from pd_tool.io import load_splats
from pd_tool.materials.file import MaterialFile, check_record, is_material_file, read_record, write_record
from pd_tool.materials.presets import Material, load_preset
from pd_tool.prepare import PrepareOptions
from pd_tool.prepare.work import WorkEstimate, work_policy
from pd_tool.register.solve import MAX_RESIDUAL, Registration
from pd_tool.render.views import scene_camera
from pd_tool.video.clip import MAX_FPS, MAX_FRAMES, ClipChoice, prepare_clip
from pd_tool.video.folder import has_camera, load_reference_video

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
    warped back onto frame 0's view (pd_tool.video.clip). A clip without a camera (no
    `camera`, no camera.json beside it) is registered to the splat first (`register`);
    `focal_mm`: its 35 mm-equivalent focal length, when known.
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
    focal_mm: float | None = None


@dataclass
class FitDone:
    result: FitResult
    side: dict[str, Path]  # kind -> path of the side outputs (report, loss plot, E field, preview)
    estimate: WorkEstimate | None  # the last run-time estimate, None when none was made
    clips: list[ClipChoice] = field(default_factory=list)  # per video: the frames used, stabilised or not


def registered_camera_paths(job: FitJob) -> dict[int, Path]:
    """Where a fit writes the camera it registers, by the index of each clip that has no
    camera: OUT_STEM.camera.json, or OUT_STEM.camera-K.json when there are several clips."""
    if job.camera is not None:
        return {}
    many = len(job.videos) > 1
    return {i: job.out.with_name(f"{job.out.stem}.camera-{i}.json" if many else f"{job.out.stem}.camera.json")
            for i, v in enumerate(job.videos) if not has_camera(v)}


def check_fit_destinations(job: FitJob) -> None:
    """Before a fit runs: its side outputs and the last-fit record replace only pdtool's
    own files, and a material file nobody named (SCENE.pdmat) only a pdtool material file."""
    inputs = {"SCENE": job.scene, **{f"VIDEO {i}": v for i, v in enumerate(job.videos)},
              "--init-material": job.settings.init_material}
    cams = registered_camera_paths(job)
    outs = {"--out": job.out, **{f"camera {i}": p for i, p in cams.items()},
            **{f"picture {i}": register_picture_path(p) for i, p in cams.items()}}
    check_outputs(outs, {}, inputs)
    for p in list(outs.values())[1:]:
        check_destination(p)
    if not job.out_named and (job.out.exists() or job.out.is_symlink()) and not is_material_file(job.out):
        raise OutputError(f"{job.out}: exists and is not a pdtool material file, which the fit would replace; move "
                          "or rename it, or name the material file with -o", path=job.out)
    check_destination(job.out)
    check_fit_outputs(job.out.parent, job.out.stem, preview=job.preview, inputs=inputs)
    check_record(job.record_dir)


def fit(job: FitJob, *, progress: FitProgress | None = None, max_minutes: float | None = None,
        on_estimate: Callable[[WorkEstimate], None] | None = None,
        say: Callable[[str], None] | None = None,
        register_progress: Callable[[str, int, int], None] | None = None) -> FitDone:
    """Fit the material of `job.scene` to its videos and write the material file, its side
    outputs and the last-fit record. Refused (WorkTooLarge) before any work when the run-time
    estimate exceeds `max_minutes`; refused (RegistrationError) when a clip without a camera
    cannot be registered. `say` gets a line per clip that was registered, trimmed, thinned
    or stabilised; `register_progress` the registration's (stage, done, total)."""
    load_preset("quality", job.settings.quality)
    check_fit_destinations(job)
    dev = job.settings.device
    cams: dict[int, Path | None] = {i: job.camera for i in range(len(job.videos))}
    registered: dict[int, RegisterDone] = {}
    for i, path in registered_camera_paths(job).items():
        v = job.videos[i]
        got = register(RegisterJob(job.scene, v, path, up=job.prepare.up_axis, device=dev, focal_mm=job.focal_mm),
                       progress=register_progress,
                       refusal_hint="pass the clip's camera with --camera FILE (pdtool render --write-camera "
                                    "writes one for a view you choose)")
        registered[i], cams[i] = got, path
        if say is not None:
            say(f"{v}: no camera.json, so frame 0 was registered to the splat (residual {got.registration.residual:.3f}, "
                f"{got.registration.seconds:.0f} s): wrote {path} and {got.picture}; check that picture, or pass "
                f"--camera")
    refs = [load_reference_video(v, camera_path=cams[i], view=job.view if cams[i] == job.camera else None,
                                 fps=job.fps, working_size=job.settings.working_long_side, device=dev)
            for i, v in enumerate(job.videos)]
    splats = load_splats(job.scene, device=dev)
    clips = []
    for i, v in enumerate(job.videos):
        refs[i], choice = prepare_clip(refs[i], start=job.start, max_frames=job.max_frames, max_fps=job.max_fps,
                                       still=job.stabilise, scene=splats)
        line = choice.line(str(v))
        if line is not None and say is not None:
            say(line)
        clips.append(choice)
    clip_records = [dataclasses.asdict(c) for c in clips]
    for i, got in registered.items():
        clip_records[i]["registered"] = {"camera": str(got.camera), "picture": str(got.picture),
                                         "residual": got.registration.residual,
                                         "seconds": got.registration.seconds}
    estimates: list[WorkEstimate] = []

    def estimated(est: WorkEstimate) -> None:
        estimates.append(est)
        if on_estimate is not None:
            on_estimate(est)

    with work_policy(max_minutes, estimated):
        result = run_fit(splats, job.scene, refs, job.out, prepare_options=job.prepare, settings=job.settings,
                         progress=progress, resume=job.resume)
    side = write_fit_outputs(job.out.parent, job.out.stem, splats, result, refs, job.settings.resolved(),
                             preview=job.preview, clips=clip_records)
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


@dataclass
class RegisterJob:
    """A registration as a user names it: the splat, a frame (an image, a video file or a
    frame folder: its first frame, and its first mask from masks/), the camera.json to
    write, an optional mask image, the scene's up axis ("auto" guesses it), the device and
    the residual above which the frame counts as not registered. `picture`: also write
    OUT_STEM.register.png, the frame beside the render over it. `focal_mm`: the camera's
    35 mm-equivalent focal length when known (held; else it is solved for)."""

    scene: Path
    frame: Path
    out: Path
    mask: Path | None = None
    up: str = "auto"
    device: str = "cpu"
    max_residual: float = MAX_RESIDUAL
    picture: bool = True
    focal_mm: float | None = None


@dataclass
class RegisterDone:
    registration: Registration
    camera: Path
    picture: Path | None


def register_picture_path(out: Path) -> Path:
    """Where `register` puts its side-by-side picture for the camera file `out`."""
    return out.with_name(out.stem + ".register.png")


def register(job: RegisterJob, *, progress: Callable[[str, int, int], None] | None = None,
             refusal_hint: str = "give a mask of the object (--mask), or write the camera file by hand") -> RegisterDone:
    """Find the camera of `job.frame` in `job.scene`'s frame and write it as camera.json
    (with the picture). Refused (RegistrationError, nothing written) when the residual is
    over `job.max_residual`; `refusal_hint` names the way out in that message."""
    import numpy as np
    import torch

    from pd_tool.core.cameras import save_camera_json
    from pd_tool.register.solve import RegisterSettings, focal_from_35mm, register_frame, side_by_side
    from pd_tool.render.preview import save_png
    from pd_tool.render.views import auto_up
    from pd_tool.video.folder import read_first_frame, read_mask

    picture = register_picture_path(job.out) if job.picture else None
    outs = {"--out": job.out, **({"picture": picture} if picture else {})}
    check_outputs(outs, {}, {"SCENE": job.scene, "FRAME": job.frame, "--mask": job.mask})
    for p in outs.values():
        check_destination(p)
    rgb, mask, src = read_first_frame(job.frame)
    if job.mask is not None:
        mask = read_mask(job.mask, (rgb.shape[1], rgb.shape[0]), "the frame is", "give a mask of the frame's size")
    splats = load_splats(job.scene, device=job.device)
    up = auto_up(splats, job.up)[0]
    frame = torch.from_numpy(np.ascontiguousarray(rgb))
    mask_t = None if mask is None else torch.from_numpy(np.ascontiguousarray(mask))
    focal = None if job.focal_mm is None else focal_from_35mm(job.focal_mm, rgb.shape[1], rgb.shape[0])
    reg = register_frame(splats, frame, mask_t, settings=RegisterSettings(up_axis=up), focal=focal, progress=progress)
    if not reg.residual <= job.max_residual:
        raise RegistrationError(
            f"{src}: could not register {job.scene.name} to this frame: residual {reg.residual:.3f} is over "
            f"{job.max_residual:g} (the render and the frame differ by that much per covered pixel); check that the "
            f"frame shows the object, or {refusal_hint}")
    shown = side_by_side(splats, reg.camera, frame) if picture is not None else None  # before any file is written
    save_camera_json(job.out, reg.camera)
    if picture is not None:
        save_png(picture, shown)
    return RegisterDone(reg, job.out, picture)
