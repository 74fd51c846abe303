"""pdtool command line: thin. Parses, validates, calls pd_tool, maps errors to exit code 2.

Every option is checked where it enters (pd_tool/cli_types.py: finite numbers in documented
ranges, colours, vectors, boxes with a volume, output names with their format's
extension). Every refusal is one stderr line `Error: ...` with exit code 2, click's usage
errors included (PdtoolGroup). Heavy imports (torch, warp, pxr) happen inside the
commands, after the argument checks.
"""
from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import re
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Iterator

import click

from pd_tool import cli_types as T


class InputError(click.ClickException):
    """Bad input the user can fix: one line on stderr, exit code 2, no traceback."""

    exit_code = 2

    def format_message(self) -> str:
        # One line, always: multi-line library messages would break scripts that grep stderr.
        return " ".join(self.message.split())


# The writers' hidden temporaries: `.NAME.XXXXXXXX.part[.EXT]` (pd_tool.core.atomic) and
# `.NAME.tmp-XXXXXXXX.usd[ac]` (the USD writer). A message names NAME, the user's file.
_TEMP_SUFFIX = r"\.(?:[a-z0-9_]{8}\.part(?:\.[A-Za-z0-9]+)?|tmp-[0-9]+-[0-9a-f]{8}\.usd[ac]?|[a-z0-9_]{8}\.old)"
_TEMP_NAME = re.compile(r"^\.(?P<name>.+)" + _TEMP_SUFFIX + "$")
_TEMP_IN_TEXT = re.compile(r"(?P<dir>[^\s'\"(]*/)?\.(?P<name>[^/\s'\"]+?)" + _TEMP_SUFFIX + r"(?=$|[\s'\":;,)])")

_OS_REASONS = {
    errno.ENOSPC: ("the disk is full", "free some space or write to another disk"),
    errno.EDQUOT: ("the disk quota is exhausted", "free some space or write to another disk"),
    errno.EROFS: ("the file system is read-only", "write to a folder you can write to"),
    errno.EACCES: ("permission denied", "write to a folder you can write to, or change its permissions"),
    errno.EPERM: ("not permitted", "write to a folder you can write to, or change its permissions"),
    errno.ENAMETOOLONG: ("the name is too long for the file system", "choose a shorter name"),
    errno.ENOENT: ("no such file or folder", "check the path"),
    errno.ENOTDIR: ("a part of the path is a file, not a folder", "check the path"),
    errno.EISDIR: ("is a folder", "give a file name"),
    errno.EEXIST: ("already exists", "choose another name"),
}


def user_file(path: str | os.PathLike) -> str:
    """The name to show for `path`: the user's file for one of the writers' hidden temporaries."""
    p = Path(os.fsdecode(path))
    m = _TEMP_NAME.match(p.name)
    return str(p.with_name(m.group("name"))) if m else str(p)


def untemp(text: str) -> str:
    """`text` with every hidden temporary's path replaced by the output it stands for."""
    return _TEMP_IN_TEXT.sub(lambda m: (m.group("dir") or "") + m.group("name"), text)


def os_error_line(e: OSError) -> str:
    """One line for an OSError that carries a file name: the user's file, why, the fix."""
    why, fix = _OS_REASONS.get(e.errno, (e.strerror or type(e).__name__, "check the path and the disk"))
    return f"{user_file(e.filename)}: {why}; {fix}"


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn library errors a user can fix into InputError (exit 2, one line). An OSError
    that names a file (a full disk, a read-only folder, a name too long) is the last resort:
    one line naming the user's file, not a traceback."""
    from pd_tool.core.device import out_of_memory_line
    from pd_tool.core.errors import PdToolError

    try:
        yield
    except PdToolError as e:
        raise InputError(untemp(str(e))) from None
    except (MemoryError, RuntimeError) as e:  # torch.OutOfMemoryError is a RuntimeError
        line = out_of_memory_line(e)
        if line is None:
            raise
        raise InputError(line) from None
    except OSError as e:
        if e.filename is None:
            raise
        raise InputError(os_error_line(e)) from None


# ----------------------------------------------------------------------------- one line per refusal
class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C, so that every writer's cleanup runs."""


class _Stopped(Exception):
    """Ctrl-C or SIGTERM reached the command: exit `code` with one line."""

    def __init__(self, code: int, line: str) -> None:
        super().__init__(line)
        self.code, self.line = code, line


def _on_sigterm(signum: int, frame: Any) -> None:
    # a second SIGTERM must not interrupt the cleanup that the first one started
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise _Terminated()


def error_line(e: click.ClickException) -> str:
    """click's error as one line: the message, and for a usage error where to read the
    command's options (click prints usage, a hint, a blank line and the message)."""
    msg = " ".join(e.format_message().split())
    if isinstance(e, click.UsageError) and (not isinstance(e, click.BadParameter)
                                            or isinstance(e, click.MissingParameter)):
        ctx = e.ctx
        if ctx is not None and "--help" not in msg:
            msg = msg.rstrip(".") + f" (see `{ctx.command_path} --help`)"
    return f"Error: {msg}"


class PdtoolGroup(click.Group):
    """click.Group whose refusals are one stderr line `Error: ...`, and which handles
    SIGTERM as Ctrl-C (exit 143 and 130, one line, temporaries removed).

    Called with standalone_mode=False (batch's workers) it behaves as click.Group."""

    _standalone = False

    def main(self, args: Any = None, prog_name: str | None = None, complete_var: str | None = None,
             standalone_mode: bool = True, **extra: Any) -> Any:
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        sys.exit(self._run(args, prog_name, complete_var, **extra))

    def _run(self, args: Any, prog_name: str | None, complete_var: str | None, **extra: Any) -> int:
        main_thread = threading.current_thread() is threading.main_thread()
        old = signal.signal(signal.SIGTERM, _on_sigterm) if main_thread else None
        self._standalone = True
        try:
            try:
                rv = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
            except _Stopped as e:
                click.echo(f"Error: {e.line}", err=True)
                return e.code
            except click.exceptions.NoArgsIsHelpError as e:  # bare `pdtool`: the help, on stdout
                click.echo(e.ctx.get_help())
                return 0
            except click.ClickException as e:
                click.echo(error_line(e), err=True)
                return e.exit_code
            except click.exceptions.Abort:
                click.echo("Error: aborted", err=True)
                return 1
            return rv if isinstance(rv, int) else 0
        finally:
            self._standalone = False
            if main_thread:
                signal.signal(signal.SIGTERM, old if old is not None else signal.SIG_DFL)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as e:
            # click would print a blank line and "Aborted!": one line instead, after the
            # writers' cleanup (it ran while the interrupt unwound)
            if not self._standalone:
                raise
            if isinstance(e, _Terminated):
                raise _Stopped(143, "stopped by SIGTERM; unfinished outputs were not written") from None
            raise _Stopped(130, "interrupted; unfinished outputs were not written") from None


# ----------------------------------------------------------------------------- progress
def progress_enabled() -> bool:
    """Progress bars go to a terminal only: on a pipe or file the bar's carriage-return
    updates would be lines before an `Error:` line. PDTOOL_PROGRESS=1 forces them on (the
    Blender add-on reads them), =0 off."""
    force = os.environ.get("PDTOOL_PROGRESS", "").strip().lower()
    if force in ("1", "on", "yes", "true"):
        return True
    if force in ("0", "off", "no", "false"):
        return False
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):
        return False


class LazyBar:
    """A tqdm bar that appears on its first update (after every check has passed) and, when
    closed after an error, is erased instead of left on the screen."""

    def __init__(self, desc: str, unit: str) -> None:
        self.desc, self.unit = desc, unit
        self.note = ""
        self._bar = None

    def update_to(self, n: int, total: int, **postfix: str) -> None:
        if self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=self.desc + self.note, unit=self.unit, dynamic_ncols=True,
                             leave=True, disable=not progress_enabled(), file=sys.stderr)
        if postfix:
            self._bar.set_postfix(**postfix, refresh=False)
        self._bar.update(n - self._bar.n)

    def close(self, ok: bool = True) -> None:
        if self._bar is not None:
            if not ok:
                self._bar.leave = False
            self._bar.close()
            self._bar = None


@contextlib.contextmanager
def bars() -> Iterator[dict[str, LazyBar]]:
    """Bars by name, closed on the way out: kept on success, erased on an error."""
    held: dict[str, LazyBar] = {}
    ok = False
    try:
        yield held
        ok = True
    finally:
        for b in held.values():
            b.close(ok)


def parse_view(view: str | None) -> str | int | None:
    """--view: a camera index when it is a number, else an image/camera name."""
    return int(view) if view is not None and view.isdigit() else view


class _PointOrTop(click.ParamType):
    name = "x,y,z|top"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, str) and value.strip().lower() == "top":
            return "top"
        return T.POINT.convert(value, param, ctx)


SCENE_PATH = click.Path(exists=True, dir_okay=False, path_type=Path)
UP_CHOICE = click.Choice(["auto", "+x", "-x", "+y", "-y", "+z", "-z"])
UP_HELP = ("Scene up axis. auto guesses it from the splats (`pdtool info` shows the guess) and says when it "
           "is not sure; COLMAP captures are often -y, Blender scenes +z.")
DEVICE_OPTION = click.option(
    "--device", type=click.Choice(["auto", "cpu", "cuda"]), default="auto", show_default=True,
    help="Where kernels run; auto picks CUDA when a GPU is visible.",
)
MAX_MINUTES_OPTION = click.option(
    "--max-minutes", type=T.MAX_MINUTES, default=60.0, show_default=True,
    help="Refuse the run when its work estimate (shown with the progress bar) is longer than this. "
         "PDTOOL_SKIP_WORK_CHECK=1 turns the refusal off.",
)
PNG_OUT = T.OutputFile([".png"], "a PNG image")


@click.group(cls=PdtoolGroup, name="pdtool",
             context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="pdtool")
def main() -> None:
    """pdtool: make a static Gaussian-splat scan move like the real object.

    \b
    Typical session:
      pdtool demo                               # whole pipeline on a built-in plant
      pdtool info scene.ply                     # what is in a splat file
      pdtool render scene.ply -o view.png       # first frame for a video model
      pdtool generate scene.ply --model svd/ -o video/   # or the whole video, with a local model
      pdtool fit scene.ply video/               # stiffness from a reference video
      pdtool bake --force 0,0,1 out.usd         # force-driven animation to USD

    Run `pdtool COMMAND --help` for each command's options and defaults.
    """


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of text.")
def info(scene: Path, as_json: bool) -> None:
    """Show what is in a splat file (.ply or .splat).

    Count, SH degree, bounding box and a robust box that ignores the 1% outliers
    per axis, opacity and scale statistics, memory size and format.

    \b
    Example:
      pdtool info ../shared/data/udon.ply --json
    """
    with user_errors():
        from pd_tool.io.info import format_summary, scene_summary
        from pd_tool.io import load_splats

        summary = scene_summary(load_splats(scene))
    click.echo(json.dumps(summary) if as_json else format_summary(summary))


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.option("-o", "--out", type=PNG_OUT, required=True, help="Output image (.png).")
@click.option("--camera", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="cameras.json (INRIA 3DGS), transforms.json (NeRF) or camera.json (pdtool). "
                   "Default: an automatic 3/4 view that frames the object.")
@click.option("--view", help="Camera id (index) or image name in the camera file. Default: the first.")
@click.option("--width", type=T.BoundedInt(8, 8192), help="Output width, pixels (keeps the field of view).")
@click.option("--height", type=T.BoundedInt(8, 8192), help="Output height, pixels.")
@click.option("--up", type=UP_CHOICE, default="auto", show_default=True,
              help=UP_HELP + " For the automatic camera, e.g. --up -y.")
@click.option("--background", type=T.COLOUR, default="1,1,1", show_default=True, help="Background colour r,g,b in 0-1.")
@click.option("--write-camera", type=T.OutputDir(),
              help="Also write the camera as DIR/camera.json, ready for the reference-video folder.")
@click.option("--fps", type=T.FPS, default=30.0, show_default=True,
              help="Frame rate stored in the written camera.json (the reference video's rate).")
@DEVICE_OPTION
def render(scene: Path, out: Path, camera: Path | None, view: str | None, width: int | None,
           height: int | None, up: str, background: tuple[float, float, float], write_camera: Path | None,
           fps: float, device: str) -> None:
    """Render one view of a splat to a PNG.

    This is how you make frame I_0 for an image-to-video model: render the view, animate
    the picture with the model, and put the frames in a folder with the camera.json that
    --write-camera writes.

    \b
    Examples:
      pdtool render ../shared/data/udon.ply --up -y -o udon.png
      pdtool render scene.ply --camera cameras.json --view 0 --width 1024 --height 576 \\
          -o video/frame_0000.png --write-camera video/
    """
    with user_errors():
        import dataclasses

        from pd_tool.core.cameras import save_camera_json
        from pd_tool.core.device import resolve_device
        from pd_tool.io import load_splats
        from pd_tool.render.preview import save_png
        from pd_tool.render.views import render_image, scene_camera

        from pd_tool.core.atomic import check_destination, check_outputs, check_own_file

        check_outputs({"--out": out}, {}, {"SCENE": scene, "--camera": camera})
        check_destination(out)
        if write_camera is not None:  # the camera.json nobody named replaces only pdtool's own
            check_own_file(write_camera / "camera.json", "pdtool's camera",
                           "move or rename it, or give --write-camera another folder")
            check_destination(write_camera / "camera.json")
        dev = resolve_device(device)
        splats = load_splats(scene, device=dev)
        view_id = parse_view(view)
        up = _resolved_up(splats, up)
        cam = scene_camera(splats, camera, view_id, width=width, height=height, up_axis=up)
        save_png(out, render_image(splats, cam, background=background))
        click.echo(f"wrote {out} ({cam.width}x{cam.height}, camera '{cam.name}')")
        if write_camera is not None:
            save_camera_json(write_camera / "camera.json", dataclasses.replace(cam, fps=fps))
            click.echo(f"wrote {write_camera / 'camera.json'}")


FOCAL_MM_OPTION = click.option(
    "--focal-mm", type=T.FiniteFloat(4.0, 2000.0, unit="mm"), default=None,
    help="The camera's 35 mm-equivalent focal length, when known (a phone's main camera: about 24-28; a photo's "
         "EXIF FocalLengthIn35mmFilm). Registration then solves the pose alone. Default: solved for.")


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.argument("frame", type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--out", type=T.OutputFile([".json"], "a camera.json"), required=True,
              help="The camera file to write (pdtool camera.json); a picture OUT_STEM.register.png goes beside it.")
@click.option("--mask", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="A mask of the object in the frame (white = object), the frame's size. Default: masks/ of a "
                   "frame folder, else what differs from a plain background, else the object's colours.")
@click.option("--up", type=UP_CHOICE, default="auto", show_default=True, help=UP_HELP)
@click.option("--max-residual", type=T.FiniteFloat(0.0, 1.0, lo_open=True), default=None,
              help="Refuse when the render and the frame differ by more than this per covered pixel "
                   "(colour 0-1). Default: 0.06.")
@FOCAL_MM_OPTION
@DEVICE_OPTION
def register(scene: Path, frame: Path, out: Path, mask: Path | None, up: str, max_residual: float | None,
             focal_mm: float | None, device: str) -> None:
    """Find the camera of a frame in the splat's frame, and write it as camera.json.

    FRAME is a picture of the object (PNG or JPG), a video file or a frame folder (its first
    frame). The object should be near the middle of the picture, upright or nearly so. pdtool
    searches views all around the object, then refines the pose and the focal length until
    its render lies on the frame. The principal point is taken at the image centre. Check
    the picture: the rotation is usually within a degree on a plain background, less often
    over clutter, and the focal length is the least sure part: give --focal-mm when known
    (docs/benchmarks.md, camera registration).

    \b
    Examples:
      pdtool register scene.ply clip.mp4 -o clip/camera.json
      pdtool register scene.ply photo.jpg --mask photo_mask.png -o camera.json
    """
    with user_errors():
        from pd_tool import app
        from pd_tool.core.device import resolve_device
        from pd_tool.register.solve import MAX_RESIDUAL

        job = app.RegisterJob(scene, frame, out, mask=mask, up=up, device=resolve_device(device),
                              max_residual=MAX_RESIDUAL if max_residual is None else max_residual, focal_mm=focal_mm)
        with bars() as held:
            def progress(stage: str, done: int, total: int) -> None:
                name = {"search": "search views", "refine": "refine"}[stage]
                bar = held.setdefault(stage, LazyBar(name, "step"))
                bar.update_to(done, total)

            done = app.register(job, progress=progress)
        r, cam = done.registration, done.registration.camera
        fov = 2.0 * math.degrees(math.atan(0.5 * cam.height / cam.fy))
        click.echo(f"registered in {r.seconds:.0f} s: residual {r.residual:.3f} (refused over {job.max_residual:g}); "
                   f"focal {cam.fx:.0f} px ({fov:.1f} deg vertical), camera at "
                   f"{', '.join(f'{v:.3g}' for v in cam.center)}")
        click.echo(f"wrote {out}" + (f" and {done.picture} (frame | render over it | difference x4)" if done.picture else ""))


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.option("--model", type=click.Path(path_type=Path), required=True,
              help="Local diffusers folder of an image-to-video model (model_index.json inside): Stable Video "
                   "Diffusion, Wan 2.x image-to-video, CogVideoX image-to-video or LTX-Video, e.g. a download of "
                   "stabilityai/stable-video-diffusion-img2vid or Wan-AI/Wan2.1-I2V-14B-480P-Diffusers. The "
                   "pipeline is chosen from model_index.json. Read from disk only, never downloaded.")
@click.option("-o", "--out", type=T.OutputDir(), required=True,
              help="Output folder: a video folder for pdtool fit, or with --count K the folders video_0/ ... "
                   "video_{K-1}/ and contact_sheet.png.")
@click.option("--camera", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="cameras.json (INRIA 3DGS), transforms.json (NeRF) or camera.json (pdtool). "
                   "Default: an automatic 3/4 view that frames the object.")
@click.option("--view", help="Camera id (index) or image name in the camera file. Default: the first.")
@click.option("--width", type=T.BoundedInt(8, 8192), default=None,
              help="Frame width, px; a multiple of the model's (64 for SVD, 16 for Wan and CogVideoX, 32 for "
                   "LTX-Video). A camera of another aspect is widened, not stretched.  [default: the model's: "
                   "SVD 1024, Wan 832, CogVideoX 720 (1.5: 1360), LTX-Video 704]")
@click.option("--height", type=T.BoundedInt(8, 8192), default=None,
              help="Frame height, px.  [default: the model's: SVD 576, Wan 480, CogVideoX 480 (1.5: 768), "
                   "LTX-Video 512]")
@click.option("--frames", type=T.BoundedInt(3, 1024), default=None,
              help="Frames per video, frame 0 included; Wan and CogVideoX make 1 + 4k, LTX-Video 1 + 8k.  "
                   "[default: the model's: SVD 14 (the paper's), Wan 81, CogVideoX 49 (1.5: 81), "
                   "LTX-Video 161]")
@click.option("--motion-bucket", type=T.BoundedInt(0, 255), default=None,
              help="SVD's motion conditioning; low values keep the camera still (the paper used 5-8).  "
                   "[default: 8]")
@click.option("--prompt", default=None,
              help="What the video shows, for Wan, CogVideoX and LTX-Video (SVD takes no text).  [default: the "
                   "object sways gently after a light push, then settles; static camera]")
@click.option("--negative-prompt", default=None,
              help="What the video must not show (Wan, CogVideoX, LTX-Video).  [default: camera movement, "
                   "zoom, pan, shake, cuts, blur, distortion]")
@click.option("--guidance", type=T.FiniteFloat(0.0, 50.0), default=None,
              help="Classifier-free guidance scale (Wan, CogVideoX, LTX-Video).  [default: the model's: 5, 6, 3]")
@click.option("--seed", type=T.SEED, default=0, show_default=True, help="Seed of the first video; video k uses SEED+k.")
@click.option("--count", type=T.BoundedInt(1, 64), default=1, show_default=True,
              help="Candidate videos to choose from (video_0/ ... and a contact sheet).")
@click.option("--steps", type=T.BoundedInt(1, 1000), default=None,
              help="Denoising steps.  [default: SVD 25, the others 50]")
@click.option("--fps", type=T.FPS, default=None,
              help="Frame rate written to camera.json (the time between frames that fit assumes); LTX-Video is "
                   "also conditioned on it.  [default: the model's: SVD 30 (the paper's), Wan 16, CogVideoX 8 "
                   "(1.5: 16), LTX-Video 25]")
@click.option("--max-camera-motion", type=T.FiniteFloat(0.0, 100.0, unit="%"), default=1.0, show_default=True,
              metavar="PCT",
              help="Bound on the camera motion against the rendered view, % of the frame's long side.")
@click.option("--reject-moving-camera", is_flag=True,
              help="Leave out videos over --max-camera-motion (default: write them and warn).")
@click.option("--static-below", type=T.STATIC_BELOW, metavar="H|PCT%",
              help="Gaussians below H stay still (a pot, a table): the camera motion is measured where they "
                   "are. H: a coordinate along --up (with --up -y, a rim at y=+0.15 is -0.15), or a share of "
                   "the height from the bottom, e.g. 15%. Default: on the whole frame.")
@click.option("--static-box", type=T.BOX, metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Gaussians in this box stay still (low corner, then high corner). Scene units.")
@click.option("--up", type=UP_CHOICE, default="auto", show_default=True,
              help=UP_HELP + " For the automatic camera and --static-below.")
@click.option("--background", type=T.COLOUR, default="1,1,1", show_default=True,
              help="Background colour r,g,b in 0-1.")
@click.option("--overwrite", is_flag=True, help="Replace an existing output folder.")
@DEVICE_OPTION
def generate(scene: Path, model: Path, out: Path, camera: Path | None, view: str | None, width: int | None,
             height: int | None, frames: int | None, motion_bucket: int | None, prompt: str | None,
             negative_prompt: str | None, guidance: float | None, seed: int, count: int, steps: int | None,
             fps: float | None, max_camera_motion: float, reject_moving_camera: bool, static_below: float | None,
             static_box: tuple[float, ...] | None, up: str, background: tuple[float, float, float], overwrite: bool,
             device: str) -> None:
    """Make the reference video with a local image-to-video model.

    Renders the view as `pdtool render` does, animates it with the model (Stable Video
    Diffusion as in the paper, or Wan 2.x, CogVideoX or LTX-Video image-to-video, chosen
    from the folder's model_index.json, each with its own defaults), measures how far the
    camera moved in each video (fit assumes a still camera), and writes the frames with
    their camera.json, ready for `pdtool fit`. Needs `pip install "pdtool[video]"` and the
    model on disk. Also writes generate.json (seeds, settings, camera motion).

    \b
    Examples:
      # the paper's settings (SVD), four candidates to choose from
      pdtool generate plant.ply --camera cameras.json --view 0 --model models/svd \\
          --frames 14 --motion-bucket 8 --count 4 -o video/
      pdtool fit plant.ply video/video_2/
      # Wan 2.1 image-to-video, a 33-frame clip and a prompt of your own
      pdtool generate plant.ply --model models/wan-i2v-480p --frames 33 \\
          --prompt "a potted plant swaying in a light breeze, static camera" -o video/
    """
    if seed + count - 1 > T.SEED_MAX:
        raise T.OptionError(f"with --count {count} the last video's seed passes {T.SEED_MAX}; give a smaller --seed",
                            None, None, seed, "--seed")
    with user_errors():
        from pd_tool.video.generate import (GenerateSettings, check_output, check_size, generate_reference_videos,
                                            generation_camera, inspect_model, require_video_extra)

        # cheap checks first: no rendering or loading before the extra, folder, size and settings are right
        require_video_extra()
        info = inspect_model(model)
        require_video_extra(info.kind)
        width = width if width is not None else info.default_size[0]
        height = height if height is not None else info.default_size[1]
        check_size(info, width, height)
        settings = GenerateSettings(frames=frames, motion_bucket=motion_bucket, seed=seed, count=count, steps=steps,
                                    fps=fps, max_camera_motion=max_camera_motion,
                                    reject_moving_camera=reject_moving_camera, prompt=prompt,
                                    negative_prompt=negative_prompt, guidance=guidance).resolved(info)
        check_output(out, overwrite)
        from pd_tool.core.device import resolve_device
        from pd_tool.io import load_splats

        dev = resolve_device(device)
        splats = load_splats(scene, device=dev)
        up = _resolved_up(splats, up)
        cam = generation_camera(splats, camera, parse_view(view), width, height, up)
        static = None
        if static_below is not None or static_box is not None:
            from pd_tool.prepare.preparation import PrepareOptions, select_static

            opts = PrepareOptions().updated(**prepare_changes(static_below=static_below, static_box=static_box, up=up))
            static = select_static(splats.positions.detach().cpu().numpy(), opts)
        result = generate_reference_videos(splats, cam, out, info, settings, device=dev, background=background,
                                           static=static, overwrite=overwrite, say=click.echo)
    for c in result.candidates:
        where = "not written" if c.folder is None else out if c.folder == "." else out / c.folder
        click.echo(f"video {c.index}  seed {c.seed}  camera motion {c.motion.max_px:.1f} px "
                   f"({c.motion.max_percent:.2f}%)  {where}")
    for w in result.warnings:
        click.echo(f"warning: {w}", err=True)
    written = [c for c in result.candidates if c.folder is not None]
    click.echo(f"wrote {out}: {len(written)} video(s) of {result.settings.frames} frames at {cam.width}x{cam.height}, "
               f"{result.settings.fps:g} fps, {info.kind.label}, camera '{cam.name}'"
               + (f"; contact sheet {result.contact_sheet}" if result.contact_sheet else ""))


def prepare_options_decorator(f):
    """Foreground, static-region and scale options shared by bake and fit."""
    opts = [
        click.option("--foreground-box", type=T.BOX, metavar="X0,Y0,Z0,X1,Y1,Z1",
                     help="Simulate only the Gaussians in this box (low corner, then high corner; scene units). "
                          "Default: all."),
        click.option("--min-opacity", type=T.UNIT_INTERVAL, default=None,
                     help="Leave out Gaussians fainter than this.  [default: 0.02]"),
        click.option("--static-box", type=T.BOX, metavar="X0,Y0,Z0,X1,Y1,Z1",
                     help="Gaussians in this box stay fixed (a pot, a table). Low corner, then high corner; "
                          "scene units."),
        click.option("--static-below", type=T.STATIC_BELOW, metavar="H|PCT%",
                     help="Gaussians below H stay fixed. H is a coordinate along the up axis, signed as that axis "
                          "points: with --up -y, a pot rim at y=+0.15 is --static-below -0.15 (`pdtool info` "
                          "shows the bottom and top). Or a share of the object's height from its bottom: "
                          "--static-below 15%."),
        click.option("--pin", type=click.Choice(["auto"]), default=None,
                     help="--pin auto fixes the base the object stands on: the part below where its shape "
                          "narrows (a pot under a stem), else the lowest 5% of its height; the report says what "
                          "it pinned."),
        click.option("--up", type=UP_CHOICE, default=None,
                     help=UP_HELP + "  [default: auto; a bake of a fitted material: the fit's axis]"),
        click.option("--meters-per-unit", type=T.METERS_PER_UNIT, default=None,
                     help="Real size of one scene unit, metres (a micrometre to a thousand kilometres). "
                          "Default: the object's longest side is 1 m."),
        click.option("--fill", type=click.Choice(["auto", "on", "off"]), default=None,
                     help="Fill the inside of closed shells with simulated particles (a scan is a shell; a solid "
                          "object would move like a balloon). auto decides from how closed the shell is and "
                          "reports it.  [default: auto]"),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _resolved_up(splats, up: str) -> str:
    """The up axis to use; for --up auto, the guess, with a line on stderr when it is not sure."""
    from pd_tool.prepare.orient import up_line
    from pd_tool.render.views import auto_up

    axis, guess = auto_up(splats, up)
    if guess is not None and not guess.sure:
        click.echo(up_line(guess))  # information, not an error: stderr keeps only errors
    return axis


def _echo_report(lines) -> None:
    """Report lines on stdout; `warning:` lines on stderr."""
    for line in lines:
        click.echo(line, err=line.startswith("warning:"))


def prepare_changes(**kw) -> dict:
    """The preparation options a user set on the command line, as PrepareOptions fields."""
    names = {"up": "up_axis"}
    return {names.get(k, k): v for k, v in kw.items() if v is not None}


def _fmt_size(n: int) -> str:
    from pd_tool.io.info import format_bytes

    return format_bytes(n)


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.option("-o", "--out", type=T.OutputFile([".ply"], "a splat PLY"), required=True,
              help="Coloured copy of the scene (.ply): red = left out, blue = static, others as they are.")
@click.option("--png", type=PNG_OUT, help="Also render it to this PNG.")
@click.option("--quality", default="default", show_default=True,
              help="draft | default | final or a TOML file: the quality whose preparation (grid, fill decision, "
                   "static set) select shows.")
@click.option("--for", "stage", type=click.Choice(["fit", "bake"]), default="fit", show_default=True,
              help="fit: as `pdtool fit --quality Q` prepares the scene, which a bake of the fitted material "
                   "repeats; bake: as `pdtool bake --preset NAME --quality Q` does, on the quality's bake grid, "
                   "raised for thin parts as the bake raises it.")
@click.option("--grid-res", type=T.BoundedInt(10, 256), default=None,
              help="Grid cells along the simulation box's longest side, e.g. 64.  [default: the grid --quality "
                   "and --for give]")
@prepare_options_decorator
@DEVICE_OPTION
def select(scene: Path, out: Path, png: Path | None, quality: str, stage: str, grid_res: int | None, device: str,
           **prep_kw) -> None:
    """Show which Gaussians a fit or bake would move, fix or leave out.

    Takes the same foreground and static-region options as fit and bake, prints what
    they select, and writes a coloured copy of the scene to look at (in pdtool render,
    a splat viewer or a DCC). The grid, the fill decision and the static set are those of
    the fit at --quality (a bake of its material simulates the same), or with --for bake
    those of a bake with a material preset.

    \b
    Example:
      pdtool select donut.ply --static-below 0.005 -o selection.ply --png selection.png
      pdtool select plant.ply --pin auto --quality draft -o selection.ply --png selection.png
      pdtool select tree.splat --pin auto --for bake -o selection.ply --png selection.png
    """
    with user_errors():
        from pd_tool.core.device import resolve_device
        from pd_tool.io import load_splats, save_ply
        from pd_tool.prepare import PrepareOptions, prepare_scene, refine_for_thin
        from pd_tool.core.atomic import check_destination, check_outputs
        from pd_tool.prepare.selection import selection_scene

        check_outputs({"--out": out, "--png": png}, {}, {"SCENE": scene})
        for path in (out, png):
            if path is not None:
                check_destination(path)
        from pd_tool.materials.presets import fit_simulation, load_preset

        preset = load_preset("quality", quality)
        stage_grid = fit_simulation(preset)[0] if stage == "fit" else int(preset["grid_res"])
        dev = resolve_device(device)
        splats = load_splats(scene, device=dev)
        opts = PrepareOptions(up_axis="auto", grid_res=grid_res or stage_grid).updated(**prepare_changes(**prep_kw))
        prep = prepare_scene(splats, opts)
        if stage == "bake" and grid_res is None:  # the bake's raise for thin parts (before its time check)
            prep = refine_for_thin(prep, int(preset.get("thin_grid_res", stage_grid))) or prep
        coloured = selection_scene(prep)
        save_ply(coloured, out)
        if png is not None:
            from pd_tool.render.preview import save_png
            from pd_tool.render.views import render_image, scene_camera

            save_png(png, render_image(coloured, scene_camera(coloured, up_axis=prep.options.up_axis)))
    as_run = (f"`pdtool fit --quality {quality}` and a bake of its material prepare it" if stage == "fit" else
              f"`pdtool bake --preset NAME --quality {quality}` prepares it")
    click.echo(f"quality {quality}: " + (f"prepared as {as_run}, on a {max(prep.grid_dims)}-cell grid"
                                        if grid_res is None else
                                        f"--grid-res {grid_res} instead of the {stage_grid}-cell grid on which {as_run}"))
    _echo_report(prep.report)
    loose = ", orange: loose parts" if prep.detached().any() else ""
    click.echo(f"wrote {out}" + (f" and {png}" if png else "") + f" (red: left out, blue: static{loose})")


@main.command()
@click.argument("out", type=T.OutputPath())
@click.option("--scene", type=SCENE_PATH, help="Splat to animate (.ply/.splat). Default: the last fit's scene.")
@click.option("--material", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Fitted material file (.pdmat) from `pdtool fit`. Default: the last fit in this folder.")
@click.option("--preset", help="Material preset instead of a fit: flower, leafy-plant, fabric-hat, rubber-cord, "
                               "jelly, or your own TOML file (see `pdtool presets materials`).")
@click.option("--force", "force_vec", type=T.FORCE, required=True, metavar="FX,FY,FZ",
              help="Acceleration along the scene's axes, in object sizes per s^2 by default: 0,0,1 pushes along +z "
                   "so that a free object would travel 3% of its size during a 0.25 s push, on any capture "
                   "whatever its scale. Each component within +-1e9.")
@click.option("--force-units", type=click.Choice(["size", "g", "scene"]), default="size", show_default=True,
              help="Units of --force: size (the object's longest side per s^2); g (9.81 m/s^2 at the simulated "
                   "size: --meters-per-unit, or a longest side of 1 m); scene (scene units per s^2, which depend "
                   "on the capture's scale).")
@click.option("--interaction", metavar="NAME|FILE",
              help="Force preset: poke (short tap at the top), gust (whole object), drag (long pull), "
                   "or a TOML file. Sets --at/--radius/--start/--duration; explicit options win.")
@click.option("--at", "at_point", type=_PointOrTop(), metavar="X,Y,Z|top",
              help="Centre of the pushed region, scene units, or 'top'. Default: the whole free object.")
@click.option("--radius", type=T.RADIUS,
              help="Radius of the pushed region around --at, scene units.  [default: 0.15 x object size]")
@click.option("--box", "force_box", type=T.BOX, metavar="X0,Y0,Z0,X1,Y1,Z1",
              help="Push the free particles in this box instead (low corner, then high corner).")
@click.option("--start", type=T.TIME, default=None, help="When the force starts, s.  [default: 0]")
@click.option("--duration", type=T.FiniteFloat(0.0, T.SECONDS_MAX, lo_open=True, unit="s"), default=None,
              help="How long the force lasts, s.  [default: 0.25]")
@click.option("--seconds", type=T.SECONDS, default=None,
              help="Animation length, s (ten minutes at most).  [default: 2]")
@click.option("--frames", type=T.FRAMES, default=None,
              help="Animation length in frames instead of --seconds (frame 0 included; ten minutes at most).")
@click.option("--fps", type=T.FPS, default=30.0, show_default=True, help="Frames per second.")
@click.option("--quality", default=None,
              help="draft | default | final, or a TOML file: grid resolution, CFL safety, driver ratio, the floor "
                   "of drivers a cell (min_drivers_per_cell; see `pdtool presets quality`). Default: "
                   "with a fitted material, the fit's own (its E is calibrated to them; another quality matches "
                   "the fit's motion first, see --match-fit); with --preset, default.")
@click.option("--format", "fmt", type=T.FormatList(), default="both", show_default=True,
              help="What to write, comma-separated. USD, in OUT (.usd/.usdc/.usda), at most one of: instancer "
                   "(UsdGeom.PointInstancer of spheres, every DCC), splat (UsdVol 3D Gaussian splat schema, usd "
                   "26.03+), both. Splat files, for 3DGS viewers and Blender's 3DGS add-ons: ply-seq (a folder of "
                   "3DGS .ply frames), spz-seq (a folder of .spz frames), gltf (a .glb with KHR_gaussian_splatting). "
                   "One format: OUT is that output; several: the splat outputs go beside OUT (OUT.usd -> OUT_ply/, "
                   "OUT_spz/, OUT.glb). All are written in one pass.")
@click.option("--preview", type=T.OutputFile([".mp4", ".gif"], "a video"),
              help="Also render the animation to a video (.mp4 or .gif) from an automatic camera.")
@click.option("--frames-out", type=T.OutputDir(),
              help="Also write the rendered frames and their camera.json into this folder "
                   "(a reference-video folder that `pdtool fit` reads).")
@click.option("--camera", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Camera file for --preview/--frames-out. Default: an automatic view.")
@click.option("--view", help="View id or name in --camera.")
@click.option("--gravity/--no-gravity", default=False, show_default=True,
              help="Simulate gravity. Off by default: a scan already shows the object at rest under gravity.")
@click.option("--substeps", type=T.SUBSTEPS, help="Fix the substeps per frame. Default: from the CFL bound.")
@click.option("--seed", type=T.SEED, default=0, show_default=True, help="Seed for driver selection.")
@click.option("--refine-thin/--no-refine-thin", default=True, show_default=True,
              help="When moving parts (leaves, petals, brims) are thinner than a quarter of the quality's grid "
                   "cell, simulate on a finer grid, up to the quality's thin_grid_res (draft 64, default 128, "
                   "final 192 cells), so that they bend as a converged simulation does. Not for a fitted material "
                   "simulated as its fit was.")
@click.option("--match-fit/--no-match-fit", default=True, show_default=True,
              help="With a fitted material and a --quality that simulates on another grid or driver count than the "
                   "fit did, first scale E by one factor (up to five short runs under this force) so that the bake "
                   "swings as far as the fit's simulation did, the motion it matched to the video. Off: the fitted E "
                   "as it is, which moves differently where parts are thin or drivers sparse.")
@MAX_MINUTES_OPTION
@prepare_options_decorator
@DEVICE_OPTION
def bake(out: Path, scene: Path | None, material: Path | None, preset: str | None, force_vec: tuple[float, ...],
         force_units: str,
         interaction: str | None, at_point: tuple[float, ...] | str | None, radius: float | None,
         force_box: tuple[float, ...] | None, start: float | None, duration: float | None, seconds: float | None,
         frames: int | None, fps: float, quality: str | None, fmt: tuple, preview: Path | None,
         frames_out: Path | None, camera: Path | None, view: str | None, gravity: bool, substeps: int | None,
         seed: int, refine_thin: bool, match_fit: bool, max_minutes: float, device: str, **prep_kw) -> None:
    """Simulate the object under a force and write the animation to OUT (USD, or splat
    files with --format).

    The material comes from --preset, from --material, or, with neither, from the
    last `pdtool fit` run in this folder. The force is an acceleration, in object sizes
    per s^2 unless --force-units says otherwise, applied to the free particles within
    --radius of --at (or in --box, or the whole object) from --start for --duration
    seconds: --force 0,0,1 moves any capture a few percent of its size. The output
    appears whole or not at all. A bake whose work estimate exceeds --max-minutes is
    refused before it starts.

    \b
    Examples:
      pdtool bake --scene plant.ply --preset flower --force 0,0,1 --seconds 1 out.usd
      pdtool bake --force 0,0,1 out.usd          # uses the last fit in this folder
      pdtool bake --scene donut.ply --preset jelly --pin auto \\
          --interaction poke --force 0,0,-3 --preview poke.mp4 poke.usd
      pdtool bake --force 0,0,1 --format both,ply-seq out.usd   # also out_ply/
      pdtool bake --force 0,0,1 --format gltf out.glb
    """
    if material is not None and preset is not None:
        raise click.UsageError("give --material or --preset, not both")
    if seconds is not None and frames is not None:
        raise click.UsageError("give --seconds or --frames, not both")
    if force_box is not None and (at_point is not None or radius is not None):
        raise click.UsageError("give --box or --at/--radius, not both")
    n_seconds = (frames - 1) / fps if frames is not None else (seconds if seconds is not None else 2.0)
    if n_seconds > T.SECONDS_MAX:
        raise T.OptionError(f"at --fps {fps:g} that is {n_seconds:,.0f} s of animation, over {T.SECONDS_MAX:g} s; "
                            "give fewer --frames or a higher --fps", None, None, frames, "--frames")
    usd_fmt, splat_formats = fmt
    from pd_tool.core.errors import OutputError
    from pd_tool.io.formats import output_paths

    try:
        output_paths(out, usd_fmt, splat_formats)
    except OutputError as e:
        raise click.BadParameter(str(e).removeprefix(f"OUT {out}: "), param_hint="OUT") from None
    if start is not None and start >= n_seconds:
        raise T.OptionError(f"the force would start at or after the animation's end ({n_seconds:g} s); start it "
                            "earlier or make the animation longer", None, None, start, "--start")
    with user_errors():
        from pd_tool import app
        from pd_tool.bake import BakeSettings, ForceSpec
        from pd_tool.core.device import resolve_device

        overrides = dict(at=at_point, radius=radius, start=start, duration=duration, box=force_box)
        if interaction is not None:
            spec = ForceSpec.from_interaction(interaction, force_vec, units=force_units, **overrides)
        else:
            spec = ForceSpec(accel=force_vec, units=force_units)
            for k, v in overrides.items():
                if v is not None:
                    setattr(spec, k, v)
        settings = BakeSettings(seconds=n_seconds, fps=fps, quality=quality, fmt=usd_fmt, splat_formats=splat_formats,
                                device=resolve_device(device),
                                gravity=gravity, substeps=substeps, seed=seed, refine_thin=refine_thin,
                                match_fit=match_fit)
        job = app.BakeJob(out, spec, settings, scene=scene, material=material, preset=preset,
                          prepare=prepare_changes(**prep_kw), preview=preview, frames_out=frames_out, camera=camera,
                          view=parse_view(view))
        with bars() as held:
            bar = held["bake"] = LazyBar("bake", "frame")

            def on_estimate(est) -> None:
                bar.note = f" (up to {est.describe()})"

            def frames_done(done: int, total: int) -> None:
                if "match" in held:  # the match's bar ends where the frames begin
                    held.pop("match").close()
                bar.update_to(done, total)

            def match_runs(done: int, total: int) -> None:
                held.setdefault("match", LazyBar("matching the fitted E to this grid", "run")).update_to(done, total)

            result = app.bake(job, progress=frames_done, max_minutes=max_minutes, on_estimate=on_estimate,
                              match_progress=match_runs)
    for line in result.report:
        click.echo(line)
    est = result.work_estimate  # the whole run's, a fitted material's match included
    if est is not None:
        click.echo(f"work estimate up to {est.describe()} on {est.device} (--max-minutes {max_minutes:g})")
    first = next(iter(result.outputs))
    click.echo(
        f"wrote {result.out}{'/' if first.endswith('-seq') else ''}: {result.frames} frames "
        f"({result.simulated_frames} simulated), {result.substeps_per_frame} substeps/frame, {result.gaussians:,} "
        f"Gaussians driven by {result.drivers:,} particles, {result.seconds_elapsed:.1f} s, "
        f"{_fmt_size(result.output_bytes[first])}"
    )
    for name, path in list(result.outputs.items())[1:]:
        click.echo(f"wrote {path}{'/' if name.endswith('-seq') else ''}: {name}, {_fmt_size(result.output_bytes[name])}")
    disp = result.displacement_per_frame
    click.echo(f"peak motion {100 * result.peak_displacement / max(result.object_size, 1e-30):.2g}% of the object's "
               f"size, at frame {max(range(len(disp)), key=disp.__getitem__)}")


@main.command()
@click.argument("scene", type=SCENE_PATH)
@click.argument("videos", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("-o", "--out", type=T.OutputFile([".pdmat"], "a pdtool material file"),
              help="Material file to write (.pdmat). Default: SCENE's name + .pdmat beside it.")
@click.option("--camera", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Camera file to use instead of each video folder's camera.json. A clip with neither is "
                   "registered to the splat (pdtool register), which is slower and less exact.")
@click.option("--view", help="View id or name in --camera.")
@FOCAL_MM_OPTION
@click.option("--fps", type=T.FPS, help="Video frame rate. Default: camera.json's, else the .mp4's own, else 30.")
@click.option("--start", type=T.BoundedInt(0, T.FRAMES_MAX), default=0, show_default=True,
              help="The frame each clip starts at: the object still at rest just before the push (a phone clip "
                   "that films the flick starts later than frame 0).")
@click.option("--max-frames", type=T.BoundedInt(3, T.FRAMES_MAX), default=30, show_default=True,
              help="The most frames the fit uses of each clip, from --start; the fit's time grows with them.")
@click.option("--max-fps", type=T.FPS, default=30.0, show_default=True,
              help="Faster clips keep every k-th frame, so that the rate is at most this (a 60 fps clip: every "
                   "2nd frame).")
@click.option("--stabilise/--no-stabilise", default=True, show_default=True,
              help="Measure each clip's camera motion against its first frame and, over 0.5% of the frame, warp "
                   "the frames back onto that view (a handheld clip); the edges a frame did not see are left "
                   "out of the fit.")
@click.option("--quality", default="default", show_default=True,
              help="draft | default | final or a TOML file: grid, CFL safety, driver ratio, iterations.")
@click.option("--velocity-iters", type=T.ITERATIONS, help="Stage 1 iterations. Default: from --quality.")
@click.option("--material-iters", type=T.ITERATIONS, help="Stage 2 iterations. Default: from --quality.")
@click.option("--rounds", type=T.BoundedInt(1, 20), default=1, show_default=True,
              help="Rounds of (stage 1, stage 2); each later round refits the initial velocity under the fitted "
                   "stiffness. With two videos, 2 brought every region of the recovery benchmark within 10% "
                   "on every seed, and moved worse under a new force than 1; see docs/benchmarks.md.")
@click.option("--horizon", type=T.BoundedInt(0, 1024), default=0, show_default=True,
              help="Frames each stage-2 loss back-propagates through (0 = every frame; the paper's 1). Every "
                   "frame, with stage 1 on six frames, brings E closer to a converged truth than the paper's "
                   "settings on nine rows of ten; see docs/benchmarks.md.")
@click.option("--polish", type=T.ITERATIONS, default=0, show_default=True,
              help="With a --horizon above 0, the last N stage-2 iterations back-propagate through every "
                   "frame; see docs/fitting.md.")
@click.option("--keep-best", type=T.BoundedInt(0, 10000), default=10, show_default=True,
              help="Every N stage-2 iterations, and at the stage's end, measure the loss over every frame of "
                   "the videos and end in the state that explained them best, stage 2's start included: a step "
                   "can overshoot, and one-frame steps can each improve while the clip as a whole drifts. With "
                   "every frame back-propagated (--horizon 0) only the end costs a pass of its own. A stage 2 "
                   "that keeps its start runs once more from it at half its step. 0 keeps the last state.")
@click.option("--level/--no-level", "level", default=True, show_default=True,  # = FitSettings.stage1_level
              help="Stage 1 also fits one overall stiffness scale along with the initial velocity; the "
                   "field's shape stays frozen (--no-level freezes E entirely, as the paper does). Under a "
                   "new force it moved the recovery benchmark closer on eight of nine seeds; see "
                   "docs/benchmarks.md.")
@click.option("--diffusion", type=T.FiniteFloat(0.0, 10.0, unit="grid cells squared"), default=0.02, show_default=True,
              help="How strongly neighbouring parts share their stiffness: smoothing of the per-part "
                   "stiffness after every stage-2 iteration, in fit-grid cells squared (0 = off). It keeps a "
                   "few parts from turning much stiffer than their neighbours, and carries a change out to parts "
                   "the video hardly shows (leaf tips). See docs/fitting.md.")
@click.option("--working-size", type=T.BoundedInt(16, 4096), default=256, show_default=True,
              help="Long side, px, that reference frames are resized to.")
@click.option("--init-e", "init_e", type=T.FiniteFloat(1e3, 1e8, unit="Pa"), default=1e6, show_default=True,
              help="Starting Young's modulus, Pa (uniform), within the fitted field's bounds; stage 1 rescales "
                   "it unless --no-level.")
@click.option("--init-material", type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Start from this material file's E (an earlier fit of the same scene) instead of a uniform "
                   "--init-e: each part takes the E of the nearest part of that fit. With --material-iters 0 "
                   "--no-level only the initial velocity is fitted, under that E, and the report's final loss "
                   "says how well that E explains these videos.")
@click.option("--match-exposure/--no-match-exposure", default=True, show_default=True,
              help="Scale each video's renders by a gain per colour channel, fitted at rest (frame 0), so that the "
                   "camera's exposure and white balance do not count as motion.")
@click.option("--nu", type=T.FiniteFloat(0.0, 0.49), default=0.3, show_default=True, help="Poisson's ratio.")
@click.option("--density", type=T.FiniteFloat(1e-3, 1e5, unit="kg/m^3"), default=1000.0, show_default=True,
              help="Density, kg/m^3 (the material presets' range).")
@click.option("--background", type=T.COLOUR, default="1,1,1", show_default=True,
              help="Background colour r,g,b in 0-1 behind the Gaussians.")
@click.option("--resume", is_flag=True, help="Continue from the checkpoint an interrupted fit left beside --out.")
@click.option("--no-preview", is_flag=True, help="Skip the side-by-side preview video.")
@click.option("--seed", type=T.SEED, default=0, show_default=True, help="Seed of the drivers and the fields.")
@MAX_MINUTES_OPTION
@prepare_options_decorator
@DEVICE_OPTION
def fit(scene: Path, videos: tuple[Path, ...], out: Path | None, camera: Path | None, view: str | None,
        focal_mm: float | None, fps: float | None, start: int, max_frames: int, max_fps: float, stabilise: bool, quality: str, velocity_iters: int | None, material_iters: int | None,
        rounds: int, horizon: int, polish: int, keep_best: int, level: bool, diffusion: float, working_size: int,
        init_e: float, init_material: Path | None, match_exposure: bool, nu: float, density: float,
        background: tuple[float, float, float], resume: bool, no_preview: bool, seed: int, max_minutes: float,
        device: str, **prep_kw) -> None:
    """Estimate the stiffness field of SCENE from reference VIDEOS of it moving.

    Each VIDEO is a folder of frames (PNG/JPG, frame 0 = the object at rest) or one
    .mp4, with a camera.json (see `pdtool render --write-camera`); optional masks/ hold
    one PNG per frame. Several folders = several views sharing one material. A clip
    without a camera (a phone video) is registered to the splat first, as `pdtool
    register` does: the camera found is written beside the material file with a
    picture to check; --focal-mm helps when the lens is known.

    Writes the material file (.pdmat), a report (.report.json), a loss plot, the E field
    as a coloured .ply and a picture, and a side-by-side preview, and records the fit
    so that a plain `pdtool bake --force ...` in this folder uses it.

    A clip of any length and rate works: the fit uses at most --max-frames of it from
    --start, thinned to --max-fps, and warps a handheld camera's shake back onto frame
    0's view (--no-stabilise to keep the frames); it prints what it did.

    \b
    Examples:
      pdtool fit plant.ply video/ --quality draft
      pdtool bake --force 0,0,1 out.usd
      # a 60 fps handheld phone clip whose flick starts at frame 40, camera found
      pdtool fit plant.ply phone.mp4 --start 40 --focal-mm 26
    """
    out_given = out is not None
    out = out or T.OutputFile([".pdmat"], "a pdtool material file").convert(scene.with_suffix(".pdmat"), None, None)
    with user_errors():
        from pd_tool import app
        from pd_tool.core.device import resolve_device
        from pd_tool.fit.settings import FitSettings
        from pd_tool.prepare import PrepareOptions

        settings = FitSettings(quality=quality, velocity_iters=velocity_iters, material_iters=material_iters,
                               rounds=rounds, material_horizon=horizon or None, polish_iters=polish,
                               keep_best_every=keep_best, stage1_level=level, residual_diffusion=diffusion,
                               init_E=init_e,
                               init_material=None if init_material is None else str(init_material),
                               match_exposure=match_exposure, nu=nu, density=density,
                               working_long_side=working_size, background=background, seed=seed,
                               device=resolve_device(device))
        job = app.FitJob(scene, videos, out, settings,
                         PrepareOptions(up_axis="auto").updated(**prepare_changes(**prep_kw)),
                         camera=camera, view=parse_view(view), fps=fps, preview=not no_preview, resume=resume,
                         out_named=out_given, start=start, max_frames=max_frames, max_fps=max_fps,
                         stabilise=stabilise, focal_mm=focal_mm)
        estimates = []
        with bars() as held:
            def progress(stage: str, it: int, total: int, loss: float) -> None:
                if stage not in held:
                    for b in held.values():
                        b.close()
                    held[stage] = LazyBar(f"fit {stage}", "it")
                    if estimates:
                        held[stage].note = f" (whole fit about {estimates[-1].describe()})"
                held[stage].update_to(it, total, loss=f"{loss:.4f}")

            def register_progress(stage: str, done: int, total: int) -> None:
                name = {"search": "register: search views", "refine": "register: refine"}[stage]
                held.setdefault(name, LazyBar(name, "step")).update_to(done, total)

            done = app.fit(job, progress=progress, max_minutes=max_minutes, on_estimate=estimates.append,
                           say=click.echo, register_progress=register_progress)
    result, side, estimate = done.result, done.side, done.estimate
    import numpy as np

    from pd_tool.fit.run import whole_clip_text

    for line in result.report:
        click.echo(line)
    if estimate is not None:
        click.echo(f"work estimate about {estimate.describe()} on {estimate.device} (--max-minutes {max_minutes:g})")
    E = result.gaussian_E
    click.echo(f"wrote {out}: {len(result.driver_E):,} drivers, E median {np.median(E):.3g} Pa "
               f"(5%-95%: {np.percentile(E, 5):.3g}-{np.percentile(E, 95):.3g}), "
               f"whole-clip loss {whole_clip_text(result.losses)}, "
               f"{sum(result.seconds.values()):.0f} s")
    for kind, path in side.items():
        click.echo(f"  {kind:<12} {path}")


@main.command()
@click.option("--out", "out_dir", type=T.OutputDir(), default=Path("pdtool-demo"),
              show_default=True, help="Folder for everything the demo writes.")
@click.option("--quality", type=click.Choice(["draft", "default"]), default="default", show_default=True,
              help="draft: about a minute on a laptop CPU; default: a few minutes.")
@DEVICE_OPTION
def demo(out_dir: Path, quality: str, device: str) -> None:
    """Run the whole pipeline on a built-in plant: no data or GPU needed.

    Writes the plant (.ply), renders reference videos of it swaying with a hidden
    stiffness per region (stem stiff, flower soft; two videos pushed two ways and seen
    from two sides, one at draft), fits the stiffness back from them, bakes a poke with
    the fitted material to USD, and writes previews and a picture of the fitted E field.
    It ends with the paths and how close the fit got.

    \b
    Example:
      pdtool demo --out demo/
    """
    with user_errors():
        from pd_tool.demo import run_demo
        from pd_tool.core.device import resolve_device

        dev = resolve_device(device)
        with bars() as held:
            def bar(name: str, desc: str, unit: str) -> LazyBar:
                if name not in held:
                    for b in held.values():
                        b.close()
                    held[name] = LazyBar(desc, unit)
                return held[name]

            def fit_progress(stage: str, it: int, total: int, loss: float) -> None:
                bar(stage, f"fit {stage}", "it").update_to(it, total, loss=f"{loss:.4f}")

            def bake_progress(done: int, total: int) -> None:
                bar("bake", "bake", "frame").update_to(done, total)

            result = run_demo(out_dir, quality=quality, device=dev, say=click.echo,
                              fit_progress=fit_progress, bake_progress=bake_progress)
    click.echo("")
    for kind, path in result.paths.items():
        click.echo(f"{kind:<16} {path}")
    click.echo("")
    for line in result.lines:
        click.echo(line)


@main.command()
@click.argument("jobs_file", metavar="JOBS.toml", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--workers", type=click.IntRange(min=1), help="CPU worker processes.  [default: the CPU count]")
@click.option("--ray", "ray_address", metavar="ADDRESS|auto|local",
              help="Run the jobs as Ray tasks on this cluster (auto: the one `ray start` made here; "
                   "local: a fresh single-node one). Needs `pip install 'pdtool[ray]'`.")
@click.option("--resume", is_flag=True, help="Skip jobs whose outputs exist and whose inputs and args are unchanged.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path), help="Also write the summary here.")
@click.option("--allow-outside", is_flag=True,
              help="Let the jobs write outside the jobs file's folder (absolute or ../ output paths). "
                   "Only for jobs files you trust.")
def batch(jobs_file: Path, workers: int | None, ray_address: str | None, resume: bool, json_out: Path | None,
          allow_outside: bool) -> None:
    """Run many bake/fit jobs from a TOML file, on local processes or a Ray cluster.

    Each [[job]] has a name, a command (bake or fit), args exactly as on the command
    line, optional after = ["other job"], and optional [job.sweep] lists that expand into
    every combination. Templates take {key} (the raw value), {key:slug} (file-safe) and
    {name}; {{ and }} are literal braces; nothing else. Relative paths are read from the
    jobs file's folder, and every output must stay inside it (unless --allow-outside). A
    failed job does not stop the others; a job whose args hold --help, -h or --version
    fails. Exit code 1 when any job failed, 2 for a refused jobs file.

    Limits: the file at most 1 MiB and nested at most 16 deep; at most 10,000 jobs after
    sweeps, 512 args per job, 4,096 characters per argument, 200 per job name.

    Ctrl-C or SIGTERM stops the running jobs and removes their temporaries (exit 130 or
    143); finished jobs keep their outputs, so `--resume` goes on from there. Workers
    die with this process, also when it is killed.

    \b
    Example (4 bakes):
      [[job]]
      name = "poke_{preset}_{force}"
      command = "bake"
      args = ["--scene", "plant.ply", "--preset", "{preset}", "--force", "{force}", "out/{name}.usd"]
      [job.sweep]
      preset = ["flower", "jelly"]
      force = ["0,0,1", "1,0,0"]
    """
    if workers is not None and ray_address is not None:
        raise click.UsageError("give --workers or --ray, not both (Ray places the jobs itself)")
    with user_errors():
        from pd_tool.core.atomic import check_destination
        from pd_tool.batch import BatchInterrupted, CommandLines, load_jobs, run_batch, write_summary

        BATCH_COMMANDS = CommandLines(parse=batch_parse, run=batch_run)

        jobs = load_jobs(jobs_file)
        if json_out is not None:
            check_destination(json_out, "--json")  # before the jobs run, not after
        try:
            result = run_batch(jobs, BATCH_COMMANDS, workers=workers, ray_address=ray_address, resume=resume,
                               allow_outside=allow_outside)
        except BatchInterrupted as e:
            click.echo(f"Error: pdtool batch stopped by {e.args[0]}: the running jobs were stopped and their "
                       "temporaries removed; finished jobs keep their outputs (run it again with --resume for "
                       "the rest)", err=True)
            raise click.exceptions.Exit(128 + e.signum) from None
    click.echo(result.table())
    if json_out is not None:
        with user_errors():
            write_summary(result, json_out)
    if not result.ok:
        raise click.exceptions.Exit(1)


def batch_parse(command: str, args: list[str]) -> dict[str, Any] | None:
    """A batch job's parameters, parsed by the command itself; None when they do not parse."""
    cmd = main.commands[command]
    try:
        return dict(cmd.make_context(command, list(args), resilient_parsing=True).params)
    except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort):
        return None


def batch_run(command: str, args: list[str]) -> str | None:
    """Run a batch job's command line in this process, as typed; its error as one line, or
    None when it ran."""
    try:
        rc = main.main([command, *args], prog_name="pdtool", standalone_mode=False)
    except click.UsageError as e:
        return f"usage: {e.format_message()}"
    except click.ClickException as e:
        return e.format_message()
    except click.exceptions.Abort:
        return "aborted"
    # With standalone_mode=False click returns an exit code only when the command ended
    # early (help, version, Exit); bake and fit return None when they ran.
    if isinstance(rc, int):
        return (f"exited with code {rc}" if rc else
                "the command exited without running (did its args ask for help or the version?)")
    return None


@main.command()
@click.argument("kind", required=False, type=click.Choice(["materials", "quality", "forces"]))
def presets(kind: str | None) -> None:
    """List the shipped presets (materials, quality levels, forces).

    Wherever a preset name is accepted you may pass your own TOML file with the
    same keys instead.

    \b
    Example:
      pdtool presets materials
    """
    from pd_tool.materials.presets import KINDS, builtin, load_preset

    with user_errors():
        for k in [kind] if kind else KINDS:
            click.echo(click.style(k, bold=True))
            for name in builtin(k):
                p = load_preset(k, name)
                note = p.pop("note", "")
                values = "  ".join(f"{key}={val:g}" if isinstance(val, float) else f"{key}={val}"
                                   for key, val in p.items())
                click.echo(f"  {name:<12} {values}\n  {'':<12} {note}")


@main.command("blender-addon")
@click.option("--install-to", type=T.OutputDir(), metavar="DIR",
              help="Copy the add-on to DIR/pdtool_blender (e.g. Blender's scripts/addons folder).")
@click.option("--zip", "zip_out", type=T.OutputFile([".zip"], "a zip archive"), metavar="OUT.zip",
              help="Write the add-on as a zip for Blender's Install from Disk (extension, 4.2+).")
def blender_addon(install_to: Path | None, zip_out: Path | None) -> None:
    """Package the Blender add-on (panel in the 3D view sidebar that runs pdtool bake).

    \b
    Examples:
      pdtool blender-addon --zip pdtool_blender.zip     # Blender: Preferences > Get Extensions > Install from Disk
      pdtool blender-addon --install-to ~/.config/blender/5.0/scripts/addons
    """
    if install_to is None and zip_out is None:
        raise click.UsageError("give --install-to DIR or --zip OUT.zip (or both)")
    with user_errors():
        from pd_tool.addon import install_addon, zip_addon

        if install_to is not None:
            click.echo(f"installed {install_addon(install_to)}")
        if zip_out is not None:
            click.echo(f"wrote {zip_addon(zip_out)}")


if __name__ == "__main__":
    main()
