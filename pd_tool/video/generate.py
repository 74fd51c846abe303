"""The reference video from a local image-to-video model (behind `pdtool generate`).

PhysDreamer's step 2 (docs: method.md): render the view (I_0), animate it with an
image-to-video model, and fit to that video. The paper used Stable Video Diffusion; the
diffusers pipelines of Wan 2.x, CogVideoX and LTX-Video image-to-video run too
(pd_tool.video.models: which one is chosen from model_index.json, with each model's own
defaults). This module runs the model from a local diffusers folder (never a download:
`local_files_only=True` and a path that must exist), measures how far the camera moved in
each generated video (pd_tool.video.camera_motion), and writes folders that `pdtool fit`
reads. It needs the optional `video` extra (diffusers, transformers, accelerate,
sentencepiece, ftfy); without it `require_video_extra` says what to install.

Output layout (`out`)::

    count 1:  out/frame_0000.png ...  out/camera.json  out/generate.json
    count K:  out/video_0/ ... out/video_{K-1}/   each frames + camera.json (a video folder)
              out/contact_sheet.png               one row per video, to choose from
              out/generate.json                   settings, seeds, camera motion per video

Video k uses seed `seed + k`. generate.json is ignored by `pdtool fit` (it reads images and
camera.json only). The whole folder is written beside its destination and renamed into
place: an error or a kill leaves no half-written output.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pd_tool.core.atomic import atomic_output, check_destination, check_outputs, check_replaceable_folder, path_kind
from pd_tool.core.cameras import Camera
from pd_tool.core.errors import PdToolError
from pd_tool.core.inputs import MiB, read_small_file
from pd_tool.render import render
from pd_tool.render.preview import save_png
from pd_tool.render.views import render_image, scene_camera
from pd_tool.video.camera_motion import CameraMotion, estimate_camera_motion
from pd_tool.video.folder import write_video_folder
from pd_tool.video.models import (CONFIG_FILES, DEFAULT_NEGATIVE, DEFAULT_PROMPT, KINDS,
                                    WEIGHT_COMPONENTS, Kind, Rules, call_arguments, frame_counts_near, rules)

VIDEO_EXTRA = 'pip install "pdtool[video]"'
PIPELINE_CLASSES = tuple(KINDS)  # model_index.json _class_name values we run
MODEL_HINT = ("--model takes a local diffusers folder with model_index.json, e.g. a download of "
              + ", ".join(k.example for k in KINDS.values()))
# Only safetensors are loaded: a .bin weight file is a pickle, which can run code when read.
WEIGHT_SUFFIXES = (".safetensors",)
SHEET_COLUMNS = 6  # frames per contact-sheet row (evenly spaced, first and last included)
SHEET_THUMB = 160  # px, long side of a contact-sheet thumbnail
SHEET_LABEL = 14  # px, height of the label strip above each row
CHANGE_GAIN = 4.0  # the contact sheet's change column shows 4x the largest grey change


class GenerateError(PdToolError):
    """The video extra is missing, or a model folder is missing, incomplete or not image-to-video."""


@dataclass
class GenerateSettings:
    """What to generate. A field left at None takes the model's default (`resolved`).

    frames: video length including frame 0. seed: seed of video 0 (video k uses seed + k).
    count: candidate videos. steps: denoising steps. fps: frame rate written to
    camera.json (what `pdtool fit` assumes between frames; LTX-Video is also conditioned
    on it). max_camera_motion: bound on the camera motion, percent of the frames' long
    side. reject_moving_camera: drop videos over the bound instead of warning.
    SVD only: motion_bucket, its motion conditioning (0-255; the paper used 5-8 so that
    the camera stays still); noise_aug, noise added to the input image (its
    noise_aug_strength); decode_chunk, frames the VAE decodes at once (memory).
    Text-conditioned models only: prompt, negative_prompt, guidance (classifier-free
    guidance scale).
    """

    frames: int | None = None
    motion_bucket: int | None = None
    seed: int = 0
    count: int = 1
    steps: int | None = None
    fps: float | None = None
    noise_aug: float | None = None
    max_camera_motion: float = 1.0
    reject_moving_camera: bool = False
    decode_chunk: int = 8
    prompt: str | None = None
    negative_prompt: str | None = None
    guidance: float | None = None

    def resolved(self, model: "ModelInfo") -> "GenerateSettings":
        """These settings with the model's defaults filled in. Raises GenerateError for a
        setting the model does not take (a prompt for SVD, a motion bucket for the others)
        and for a frame count it cannot make."""
        kind = model.kind
        name = kind.label
        if kind.text and (self.motion_bucket is not None or self.noise_aug is not None):
            raise GenerateError(f"--motion-bucket is Stable Video Diffusion's conditioning; {name} is conditioned "
                                f"on --prompt instead")
        if not kind.text and (self.prompt is not None or self.negative_prompt is not None
                              or self.guidance is not None):
            raise GenerateError(f"{name} takes no text: --prompt, --negative-prompt and --guidance are for "
                                f"Wan, CogVideoX and LTX-Video; SVD's motion is set with --motion-bucket")
        frames = self.frames if self.frames is not None else model.rules.frames
        check_frames(model, frames)
        out = dataclasses.replace(self, frames=frames, steps=self.steps or kind.steps,
                                  fps=self.fps or model.rules.fps)
        if kind.text:
            return dataclasses.replace(out, prompt=self.prompt if self.prompt is not None else DEFAULT_PROMPT,
                                       negative_prompt=(self.negative_prompt if self.negative_prompt is not None
                                                        else DEFAULT_NEGATIVE),
                                       guidance=self.guidance if self.guidance is not None else kind.guidance)
        return dataclasses.replace(out, motion_bucket=8 if self.motion_bucket is None else self.motion_bucket,
                                   noise_aug=0.02 if self.noise_aug is None else self.noise_aug)


@dataclass
class ModelInfo:
    """A checked model folder: its path, pipeline class, the multiple (px) that frame width
    and height must be (at least 8), the weights' variant, and the model's size and
    length rules (pd_tool.video.models.Rules; SVD's when not given)."""

    path: Path
    class_name: str
    multiple: int
    variant: str | None = None
    rules: Rules | None = None

    def __post_init__(self) -> None:
        if self.rules is None:
            kind = self.kind
            assert kind.frames is not None and kind.size is not None
            self.rules = Rules(self.multiple, 1, None, kind.frames, kind.size, kind.fps)

    @property
    def kind(self) -> Kind:
        return KINDS[self.class_name]

    @property
    def default_size(self) -> tuple[int, int]:
        """(width, height) px the model makes by default."""
        return self.rules.size


@dataclass
class Candidate:
    """One generated video: frames [T, H, W, 3] uint8, its seed, its camera motion, and
    where it was written (relative to the output folder; None when rejected)."""

    index: int
    seed: int
    frames: np.ndarray
    motion: CameraMotion
    over_bound: bool
    folder: str | None = None


@dataclass
class GenerateResult:
    out: Path
    camera: Camera
    candidates: list[Candidate]
    contact_sheet: Path | None
    settings: GenerateSettings
    warnings: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- checks


def require_video_extra(kind: Kind | None = None) -> None:
    """Raise GenerateError (with the pip command) unless diffusers and transformers import,
    and for a text-conditioned model also the tokeniser's sentencepiece and the prompt
    cleaning's ftfy."""
    needed = ["diffusers", "transformers"] + (["sentencepiece", "ftfy"] if kind is not None and kind.text else [])
    for module in needed:
        try:
            importlib.import_module(module)
        except ImportError as e:
            missing = getattr(e, "name", None) or module
            what = "pdtool generate" if kind is None else f"pdtool generate with {kind.label}"
            raise GenerateError(f"{what} needs the optional video extra ({missing} is not importable): "
                                f"{VIDEO_EXTRA}") from None


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(read_small_file(path, limit=16 * MiB, error=GenerateError, fix=MODEL_HINT).decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise GenerateError(f"{path}: unreadable ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}); "
                            f"{MODEL_HINT}") from None
    if not isinstance(data, dict):
        raise GenerateError(f"{path}: expected a JSON object; {MODEL_HINT}")
    return data


def inspect_model(path: str | Path) -> ModelInfo:
    """Check a model folder without loading weights (fast, before any rendering).

    Raises GenerateError when the folder is missing, has no model_index.json, holds
    another kind of pipeline, or lacks a component's config or weights.
    """
    path = Path(path)
    if not path.exists():
        raise GenerateError(f"{path}: no such folder; {MODEL_HINT}")
    if not path.is_dir():
        raise GenerateError(f"{path}: is a file, not a folder; {MODEL_HINT}")
    index_file = path / "model_index.json"
    if not index_file.is_file():
        raise GenerateError(f"{path}: no model_index.json, so this is not a diffusers model folder; {MODEL_HINT}")
    index = _read_json(index_file)
    cls = index.get("_class_name")
    if cls not in KINDS:
        raise GenerateError(f"{index_file}: the model is a {cls or 'pipeline without _class_name'}, not an "
                            f"image-to-video pipeline pdtool runs ({', '.join(PIPELINE_CLASSES)}); {MODEL_HINT}")
    kind = KINDS[cls]

    def present(comp: str) -> bool:  # model_index.json writes an absent optional part as [null, null]
        entry = index.get(comp)
        return isinstance(entry, list) and len(entry) == 2 and entry[1] is not None

    for comp in kind.components:
        if not present(comp):
            raise GenerateError(f"{index_file}: no '{comp}' component; the folder is not a complete "
                                f"{cls} (copy the whole model repository)")
    variant = None
    for comp in [c for c in index if not c.startswith("_") and present(c)]:
        cfg = CONFIG_FILES.get(comp, "config.json")
        if comp not in WEIGHT_COMPONENTS and comp not in CONFIG_FILES:
            continue  # a setting of the pipeline, not a component folder
        if not (path / comp / cfg).is_file():
            raise GenerateError(f"{path}: no {comp}/{cfg}; the folder is incomplete (copy the whole model repository)")
        if comp in WEIGHT_COMPONENTS:
            names = [p.name for p in (path / comp).iterdir()]
            weights = [n for n in names if n.endswith(WEIGHT_SUFFIXES)]
            if not weights:
                if any(n.endswith(".bin") for n in names):
                    raise GenerateError(f"{path / comp}: holds only .bin weights, which are pickles that can run code; "
                                        f"pdtool loads *.safetensors only: download the safetensors files of the "
                                        f"model repository")
                raise GenerateError(f"{path / comp}: no weights (*.safetensors); the download is incomplete "
                                    f"(git lfs pull, or copy the whole model repository)")
            plain = [n for n in weights if n.split(".")[1] == "safetensors"]
            if not plain and any(".fp16." in n for n in weights):
                variant = "fp16"  # the fp16-only download of the SVD repository
    try:
        found = rules(kind, lambda comp: _read_json(path / comp / "config.json"))
    except (KeyError, TypeError, ValueError, IndexError):
        raise GenerateError(f"{path}: a component's config.json lacks the sizes {cls} reads (vae / "
                            f"{'unet' if cls == 'StableVideoDiffusionPipeline' else 'transformer'}); the folder is "
                            f"not a {cls}") from None
    return ModelInfo(path, cls, found.multiple, variant, found)


def check_size(info: ModelInfo, width: int, height: int) -> None:
    """Frame width and height must be multiples of the model's `multiple`, or the one size
    a model with a fixed size takes."""
    fixed = info.rules.fixed_size
    if fixed is not None and (width, height) != fixed:
        raise GenerateError(f"{width}x{height}: this {info.kind.label} model makes {fixed[0]}x{fixed[1]} frames only "
                            f"(its position table was learned at that size); use --width {fixed[0]} "
                            f"--height {fixed[1]} or leave them out")
    m = info.multiple
    if width % m or height % m:
        def near(v: int) -> int:
            return max(m, round(v / m) * m)

        raise GenerateError(f"{width}x{height}: this model needs width and height in multiples of {m} px; "
                            f"use e.g. --width {near(width)} --height {near(height)}")


def check_frames(info: ModelInfo, frames: int) -> None:
    """A frame count the model makes: 1 + k x its VAE's time compression (any for SVD)."""
    t = info.rules.temporal
    if t > 1 and (frames - 1) % t:
        low, high = frame_counts_near(frames, t)
        raise GenerateError(f"--frames {frames}: {info.kind.label} makes 1 + a multiple of {t} frames; "
                            f"use --frames {low} or --frames {high}")


def check_output(out: str | Path, overwrite: bool, inputs: dict[str, str | Path | None] | None = None) -> None:
    """Refuse an output folder that cannot or must not be written: a file; an existing
    non-empty folder without overwrite; with overwrite, a folder that pdtool did not make
    (or that holds anything it did not write); the current folder or one that holds it
    or an input (`inputs`: {option: path}, e.g. the scene and --model); a destination
    that is not writable. Raises GenerateError / OutputError (one line)."""

    out = Path(out)
    if path_kind(out) in ("file", "other"):
        raise GenerateError(f"{out}: is a file; -o takes a folder")
    check_outputs({}, {"-o": out}, inputs or {})
    if path_kind(out) == "dir" and any(out.iterdir()) and not overwrite:
        raise GenerateError(f"{out}: already exists and is not empty; choose a new folder or pass --overwrite")
    check_replaceable_folder(out, "-o", fix="--overwrite replaces only folders that pdtool generate wrote")
    check_destination(out, "-o", folder=True)


# ----------------------------------------------------------------------------- camera and input


def frame_camera(camera: Camera, width: int, height: int) -> Camera:
    """`camera` at width x height with square pixels, the whole original view inside.

    The view is scaled to fit (the smaller of the two ratios) and the principal point
    moved with it; on the axis with room left the field of view grows (the renderer fills
    it). Unlike Camera.resized, a different aspect ratio does not stretch the picture,
    which the video model would see as a squashed object.
    """
    s = min(width / camera.width, height / camera.height)
    cx = camera.cx * s + 0.5 * (width - camera.width * s)
    cy = camera.cy * s + 0.5 * (height - camera.height * s)
    return Camera(width, height, camera.fx * s, camera.fy * s, cx, cy, camera.world_to_camera.copy(),
                  camera.name, camera.fps)


def generation_camera(scene, camera_path: str | Path | None, view: str | int | None, width: int, height: int,
                      up_axis: str = "+z") -> Camera:
    """The camera of I_0: a view of a camera file re-framed to width x height
    (`frame_camera`), or the automatic 3/4 view at that size."""

    if camera_path is None:
        return scene_camera(scene, None, view, width=width, height=height, up_axis=up_axis)
    return frame_camera(scene_camera(scene, camera_path, view), width, height)


def static_weight(scene, camera: Camera, static: np.ndarray) -> np.ndarray | None:
    """Where the static Gaussians (static [N] bool) cover the image: alpha [H, W] in 0-1,
    the camera-motion check's weight. None when they cover (almost) nothing."""

    if not static.any():
        return None
    mask = torch.as_tensor(static, device=scene.opacities.device)
    with torch.no_grad():
        out = render(scene.positions, scene.quats, scene.scales, scene.opacities * mask, scene.sh, camera)
    a = out.alpha[..., 0].clamp(0, 1).cpu().numpy()
    return a if a.sum() >= 64.0 else None  # fewer than ~64 covered pixels: no basis for a check


# ----------------------------------------------------------------------------- model


def _first_line(e: Exception) -> str:
    """`Type: first line` of a library's exception, at most 300 characters of it: its
    messages can span pages, and an error must stay one line."""
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0][:300] if text else ''}"


def load_pipeline(info: ModelInfo, device: str = "cpu"):
    """Load the pipeline from local files only (never a download). On CUDA it runs in its
    authors' dtype (float16 for SVD, bfloat16 for the others), on the CPU in float32."""
    require_video_extra(info.kind)
    import diffusers
    import transformers

    # load-time notices and per-file progress bars are not the user's concern (and an error
    # after them must still be the only line on stderr)
    logs = (diffusers.utils.logging, transformers.utils.logging)
    bars_were_on = [log.is_progress_bar_enabled() for log in logs]
    for log in logs:
        log.set_verbosity_error()
        log.disable_progress_bar()
    dtype = getattr(torch, info.kind.cuda_dtype) if str(device).startswith("cuda") else torch.float32
    try:
        cls = getattr(diffusers, info.class_name)
        with warnings.catch_warnings():  # newer diffusers renamed torch_dtype; older ones know only it
            warnings.simplefilter("ignore", FutureWarning)
            pipe = cls.from_pretrained(info.path, torch_dtype=dtype, local_files_only=True, variant=info.variant,
                                       use_safetensors=True)
    except Exception as e:  # a user's folder: corrupt weights, wrong shapes, missing files
        raise GenerateError(f"{info.path}: cannot load the model ({_first_line(e)}); {MODEL_HINT}") from None
    finally:
        for log, on in zip(logs, bars_were_on):
            if on:
                log.enable_progress_bar()
    pipe = pipe.to(device)
    return pipe


def animate(pipe, image: np.ndarray, settings: GenerateSettings, seed: int, kind: Kind | None = None) -> np.ndarray:
    """Run the image-to-video pipeline on image [H, W, 3] uint8 -> frames [T, H, W, 3] uint8.

    settings: resolved (GenerateSettings.resolved). kind: the pipeline's entry (default
    SVD). The noise comes from a CPU generator seeded with `seed`: the same seed gives the
    same video again (video k of a --count run is the --seed SEED+k video), and the same
    starting noise on CPU and CUDA.
    """
    from PIL import Image

    kind = kind or KINDS["StableVideoDiffusionPipeline"]
    h, w = image.shape[:2]
    gen = torch.Generator("cpu").manual_seed(int(seed))
    args = call_arguments(kind, frames=settings.frames, steps=settings.steps, fps=settings.fps,
                          guidance=settings.guidance, prompt=settings.prompt, negative_prompt=settings.negative_prompt,
                          motion_bucket=settings.motion_bucket, noise_aug=settings.noise_aug,
                          decode_chunk=settings.decode_chunk)
    try:
        out = pipe(image=Image.fromarray(image), height=h, width=w, generator=gen, **args)
    except torch.cuda.OutOfMemoryError:
        raise GenerateError(f"out of GPU memory making {settings.frames} frames of {w}x{h}; use fewer --frames "
                            f"or a smaller --width/--height") from None
    except (RuntimeError, ValueError, TypeError) as e:  # the model's own checks and shape errors
        raise GenerateError(f"{kind.label} failed on {settings.frames} frames of {w}x{h} ({_first_line(e)}); "
                            f"try the model's own --frames, --width and --height") from None
    v = np.asarray(out.frames[0], dtype=np.float32)[: settings.frames]
    if v.shape[0] != settings.frames or v.shape[1:3] != (h, w):
        raise GenerateError(f"the model made {v.shape[0]} frames of {v.shape[2]}x{v.shape[1]} px where "
                            f"{settings.frames} of {w}x{h} were asked; pass --frames and --width/--height the "
                            f"model was trained for")
    return (np.clip(v, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


# ----------------------------------------------------------------------------- contact sheet


def _thumb(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.fromarray(img).resize(size, Image.BILINEAR))


def contact_sheet(reference: np.ndarray, candidates: list[Candidate], columns: int = SHEET_COLUMNS,
                  thumb: int = SHEET_THUMB) -> np.ndarray:
    """One row per candidate: the input render, `columns` evenly spaced frames, and the
    change image (largest grey change from the input over the video, x4; camera motion
    lights up the whole frame, object motion only the object). A label above each row
    names the folder, seed and camera motion. Returns uint8 [H, W, 3]."""
    from PIL import Image, ImageDraw

    h, w = reference.shape[:2]
    f = thumb / max(h, w)
    tw, th = max(1, round(w * f)), max(1, round(h * f))
    gap = 2
    row_h = SHEET_LABEL + th + gap
    t = max(len(c.frames) for c in candidates)
    picks = sorted({round(i * (t - 1) / max(columns - 1, 1)) for i in range(columns)})
    ncols = 2 + len(picks)  # input, frames, change
    sheet = Image.new("RGB", (ncols * (tw + gap) + gap, len(candidates) * row_h + gap), (32, 32, 32))
    draw = ImageDraw.Draw(sheet)
    ref_t = _thumb(reference, (tw, th))
    for r, c in enumerate(candidates):
        change = np.abs(c.frames.astype(np.float32) - reference[None].astype(np.float32)).mean(-1).max(0)
        change = np.clip(change * CHANGE_GAIN, 0, 255).astype(np.uint8)
        tiles = [ref_t] + [_thumb(c.frames[i], (tw, th)) for i in picks]
        tiles += [_thumb(np.repeat(change[..., None], 3, -1), (tw, th))]
        y = r * row_h + gap
        where = c.folder if c.folder is not None else f"video {c.index} (not written)"
        label = (f"{where}  seed {c.seed}  camera motion {c.motion.max_px:.1f} px "
                 f"({c.motion.max_percent:.2f}%)" + ("  OVER BOUND" if c.over_bound else "")
                 + "   | input | frames " + ", ".join(str(i) for i in picks) + " | change x4")
        draw.text((gap + 2, y + 1), label, fill=(255, 120, 120) if c.over_bound else (230, 230, 230))
        for k, tile in enumerate(tiles):
            sheet.paste(Image.fromarray(tile), (gap + k * (tw + gap), y + SHEET_LABEL))
    return np.asarray(sheet)


# ----------------------------------------------------------------------------- the whole step


def generate_reference_videos(
    scene,
    camera: Camera,
    out: str | Path,
    model: ModelInfo,
    settings: GenerateSettings,
    *,
    device: str = "cpu",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    static: np.ndarray | None = None,
    overwrite: bool = False,
    say: Callable[[str], None] = print,
) -> GenerateResult:
    """Render I_0 from `camera`, animate it `settings.count` times, check the camera
    motion, and write the video folder(s) (see the module docstring for the layout).

    Args:
        scene: GaussianScene (activated values, on `device`).
        camera: the view; its size is the frames' size (a multiple of model.multiple).
        out: output folder.
        model: from `inspect_model`.
        settings: GenerateSettings (fields left at None take the model's defaults).
        device: "cpu" or "cuda" for the model (float16 on CUDA).
        background: RGB 0-1 behind the Gaussians in I_0 (use the fit's --background).
        static: optional [N] bool, the Gaussians that stay still (pot, table); the camera
            motion is then measured where they are in the image, else on the whole frame.
        overwrite: replace an existing folder that pdtool generate made (never one that
            holds anything pdtool did not write).
        say: progress lines.
    Returns:
        GenerateResult. Raises GenerateError when every video moved the camera more than
        the bound and settings.reject_moving_camera is set (nothing is written then).
    """

    out = Path(out)
    check_output(out, overwrite, {"SCENE": getattr(scene, "source", None), "--model": model.path})
    check_size(model, camera.width, camera.height)
    settings = settings.resolved(model)
    image = render_image(scene, camera, background=background)
    weight = static_weight(scene, camera, static) if static is not None else None
    if static is not None and weight is None:
        say("--static-below/--static-box select no Gaussians in view; the camera motion is measured on the "
            "whole frame")
    say(f"loading {model.kind.label} ({model.class_name}) from {model.path}")
    pipe = load_pipeline(model, device)
    candidates: list[Candidate] = []
    warnings: list[str] = []
    for k in range(settings.count):
        seed = settings.seed + k
        pipe.set_progress_bar_config(desc=f"video {k + 1}/{settings.count} (seed {seed})", leave=False)
        frames = animate(pipe, image, settings, seed, model.kind)
        motion = estimate_camera_motion(image, frames, weight)
        over = motion.max_percent > settings.max_camera_motion
        candidates.append(Candidate(k, seed, frames, motion, over))
        if over:
            warnings.append(f"video {k} (seed {seed}): the camera moved {motion.max_px:.1f} px "
                            f"({motion.max_percent:.2f}% of the long side, bound {settings.max_camera_motion:g}%); "
                            f"fit assumes a still camera: "
                            + ("not written" if settings.reject_moving_camera else
                               "pick another video, lower --motion-bucket, or pass --reject-moving-camera"))
    keep = [c for c in candidates if not (c.over_bound and settings.reject_moving_camera)]
    if not keep:
        raise GenerateError(f"all {len(candidates)} video(s) moved the camera by more than "
                            f"{settings.max_camera_motion:g}% of the frame (--max-camera-motion); "
                            f"try other seeds (--seed, --count) or a lower --motion-bucket; nothing written")
    sheet_path = None
    with atomic_output(out, directory=True, what="-o") as tmp:
        for c in keep:
            c.folder = "." if settings.count == 1 else f"video_{c.index}"
            write_video_folder(tmp if settings.count == 1 else tmp / c.folder, c.frames, camera, settings.fps,
                               overwrite=True)
        if settings.count > 1:
            save_png(tmp / "contact_sheet.png", contact_sheet(image, candidates))
            sheet_path = out / "contact_sheet.png"
        record = {
            "model": str(model.path.resolve()), "pipeline": model.class_name,
            "settings": dataclasses.asdict(settings), "width": camera.width, "height": camera.height,
            "camera": camera.name,
            "camera_motion_region": "static Gaussians" if weight is not None else "whole frame",
            "videos": [{"folder": c.folder, "seed": c.seed, "camera_motion_px": round(c.motion.max_px, 3),
                        "camera_motion_percent": round(c.motion.max_percent, 4), "over_bound": c.over_bound,
                        "shift_px": np.round(c.motion.shifts, 3).tolist(),
                        "zoom": np.round(c.motion.zooms, 6).tolist()} for c in candidates],
        }
        (tmp / "generate.json").write_text(json.dumps(record, indent=2) + "\n", encoding="utf-8")
    return GenerateResult(out, camera, candidates, sheet_path, settings, warnings)
