"""`pdtool generate` end to end on a tiny randomly initialised Stable Video Diffusion pipeline
(the real diffusers / transformers classes with tiny configs, about 8 MB, built here: no
download), its error paths, and the camera-motion check on frames with a known motion."""
from __future__ import annotations

import importlib.util
import json
import math
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from click.testing import CliRunner

from cli import main
from pd_tool.video.camera_motion import estimate_camera_motion, phase_correlation, to_gray
from pd_tool.core.cameras import Camera, auto_camera, load_cameras, save_camera_json
from pd_tool.video.generate import frame_camera

ROOT = Path(__file__).resolve().parents[2]
SIZE = ["--width", "64", "--height", "48"]  # W x H; multiples of the tiny model's 8 px
FAST = ["--frames", "4", "--steps", "2"]

needs_extra = pytest.mark.skipif(
    not all(importlib.util.find_spec(m) for m in ("diffusers", "transformers")),
    reason='needs the video extra: pip install -e ".[video]"')


def build_tiny_svd(folder: Path) -> Path:
    """A StableVideoDiffusionPipeline of the real classes with tiny random weights, saved in
    diffusers format (model_index.json + one folder per component), as a download would be."""
    from diffusers import (AutoencoderKLTemporalDecoder, EulerDiscreteScheduler, StableVideoDiffusionPipeline,
                           UNetSpatioTemporalConditionModel)
    from transformers import CLIPImageProcessor, CLIPVisionConfig, CLIPVisionModelWithProjection

    torch.manual_seed(0)
    # channel counts are multiples of 32 (GroupNorm's groups); 3 VAE levels -> 4x downscale,
    # 2 UNet levels -> 2x more: frames in multiples of 8 px
    unet = UNetSpatioTemporalConditionModel(
        block_out_channels=(32, 64), layers_per_block=1, sample_size=8, in_channels=8, out_channels=4,
        down_block_types=("CrossAttnDownBlockSpatioTemporal", "DownBlockSpatioTemporal"),
        up_block_types=("UpBlockSpatioTemporal", "CrossAttnUpBlockSpatioTemporal"),
        cross_attention_dim=16, num_attention_heads=2, projection_class_embeddings_input_dim=12,
        addition_time_embed_dim=4, num_frames=14)
    vae = AutoencoderKLTemporalDecoder(block_out_channels=[32, 32, 64], in_channels=3, out_channels=3,
                                       down_block_types=["DownEncoderBlock2D"] * 3, latent_channels=4,
                                       layers_per_block=1)
    scheduler = EulerDiscreteScheduler(  # SVD's own scheduler settings
        beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear", interpolation_type="linear",
        num_train_timesteps=1000, prediction_type="v_prediction", sigma_max=700.0, sigma_min=0.002, steps_offset=1,
        timestep_spacing="leading", timestep_type="continuous", use_karras_sigmas=True)
    # the pipeline resizes the input to 224 px for CLIP; patches of 32 px -> 49 tokens
    encoder = CLIPVisionModelWithProjection(CLIPVisionConfig(
        hidden_size=16, projection_dim=16, num_hidden_layers=1, num_attention_heads=2, image_size=224,
        intermediate_size=16, patch_size=32))
    pipe = StableVideoDiffusionPipeline(vae=vae, image_encoder=encoder, unet=unet, scheduler=scheduler,
                                        feature_extractor=CLIPImageProcessor(crop_size=224, size=224))
    pipe.save_pretrained(folder)
    return folder


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    # The tiny model is hundreds of small ops; on the shared 2-core CI box two OpenMP threads
    # spin at every op's barrier and run many times slower than one.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> Path:
    return build_tiny_svd(tmp_path_factory.mktemp("svd") / "tiny-svd")


def run_cli(*args) -> "click.testing.Result":  # noqa: F821
    return CliRunner().invoke(main, ["generate", *[str(a) for a in args]])


def read_png(path: Path) -> np.ndarray:
    import imageio.v3 as iio

    return iio.imread(path)


# ----------------------------------------------------------------------------- end to end


@needs_extra
def test_generate_writes_a_video_folder_that_fit_reads(tiny_model: Path, shared_data: Path, tmp_path: Path) -> None:
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats
    from pd_tool.render.views import scene_camera

    scene, out = shared_data / "udon.ply", tmp_path / "video"
    res = run_cli(scene, "--up", "-y", "--model", tiny_model, *SIZE, *FAST, "--fps", "24", "-o", out)
    assert res.exit_code == 0, res.output
    frames = sorted(out.glob("frame_*.png"))
    assert [f.name for f in frames] == [f"frame_{i:04d}.png" for i in range(4)]
    assert all(read_png(f).shape == (48, 64, 3) for f in frames)
    # camera.json is the rendered view (the automatic camera at 64 x 48), with --fps
    cam = load_cameras(out / "camera.json")[0]
    want = scene_camera(load_splats(scene), None, None, width=64, height=48, up_axis="-y")
    assert (cam.width, cam.height, cam.fps) == (64, 48, 24.0)
    np.testing.assert_allclose(cam.K, want.K, rtol=1e-12)
    np.testing.assert_allclose(cam.world_to_camera, want.world_to_camera, rtol=1e-12, atol=1e-12)
    # fit's reader takes it as it is
    ref = load_reference_video(out, working_size=None)
    assert tuple(ref.frames.shape) == (4, 48, 64, 3) and ref.fps == 24.0
    record = json.loads((out / "generate.json").read_text())
    assert record["videos"][0]["seed"] == 0 and record["settings"]["motion_bucket"] == 8
    assert record["camera_motion_region"] == "whole frame"
    assert "camera motion" in res.stdout and "wrote" in res.stdout


@needs_extra
def test_generate_count_two_from_a_camera_file(tiny_model: Path, shared_data: Path, tmp_path: Path) -> None:
    from pd_tool.io import load_splats

    scene, out = shared_data / "udon.ply", tmp_path / "candidates"
    # a square camera (the capture's own view, say): re-framed to 64 x 48 without stretching
    square = auto_camera(load_splats(scene).positions.numpy(), 100, 100, up_axis="-y")
    save_camera_json(tmp_path / "cams.json", square)
    res = run_cli(scene, "--camera", tmp_path / "cams.json", "--view", "0", "--model", tiny_model, *SIZE, *FAST,
                  "--count", "2", "--seed", "7", "--static-below", "2.5", "--up", "-y", "-o", out)
    assert res.exit_code == 0, res.output
    videos = [np.stack([read_png(f) for f in sorted((out / f"video_{k}").glob("frame_*.png"))]) for k in (0, 1)]
    assert all(v.shape == (4, 48, 64, 3) for v in videos)
    assert np.abs(videos[0].astype(int) - videos[1].astype(int)).mean() > 1.0  # two seeds, two videos
    want = frame_camera(square, 64, 48)
    for k in (0, 1):
        cam = load_cameras(out / f"video_{k}" / "camera.json")[0]
        np.testing.assert_allclose(cam.K, want.K, rtol=1e-12)
        assert cam.fx == pytest.approx(cam.fy)  # square pixels, not stretched
        np.testing.assert_allclose(cam.world_to_camera, square.world_to_camera, atol=1e-12)
    sheet = read_png(out / "contact_sheet.png")
    assert sheet.ndim == 3 and sheet.shape[0] > 2 * 48 // 2 and sheet.shape[1] > sheet.shape[0]
    record = json.loads((out / "generate.json").read_text())
    assert [v["seed"] for v in record["videos"]] == [7, 8]
    assert [v["folder"] for v in record["videos"]] == ["video_0", "video_1"]
    assert record["camera_motion_region"] == "static Gaussians"  # the bowl's lower part (--static-below)
    # video k is the --seed SEED+k video: a chosen candidate can be made again on its own
    again = tmp_path / "again"
    res = run_cli(scene, "--camera", tmp_path / "cams.json", "--model", tiny_model, *SIZE, *FAST, "--seed", "8",
                  "--up", "-y", "-o", again)
    assert res.exit_code == 0, res.output
    np.testing.assert_array_equal(np.stack([read_png(f) for f in sorted(again.glob("frame_*.png"))]), videos[1])


@needs_extra
def test_reject_moving_camera_writes_nothing(tiny_model: Path, shared_data: Path, tmp_path: Path) -> None:
    # A randomly initialised model's frames do not resemble the input at all, so the
    # camera-motion check must flag them; with --reject-moving-camera nothing is written.
    out = tmp_path / "video"
    res = run_cli(shared_data / "udon.ply", "--up", "-y", "--model", tiny_model, *SIZE, *FAST,
                  "--reject-moving-camera", "-o", out)
    assert res.exit_code == 2
    # after the denoising progress bars, one error line
    errors = [line for line in res.stderr.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1 and "moved the camera" in errors[0] and "Traceback" not in res.stderr
    assert not out.exists() and not list(tmp_path.glob(".video*"))


# ----------------------------------------------------------------------------- errors


def test_missing_extra_is_one_clean_line(shared_data: Path, tmp_path: Path) -> None:
    # A fresh interpreter in which `import diffusers` fails, as without the extra.
    code = "import sys; sys.modules['diffusers'] = None; from cli import main; main()"
    out = tmp_path / "video"
    proc = subprocess.run([sys.executable, "-c", code, "generate", str(shared_data / "udon.ply"),
                           "--model", str(tmp_path), "-o", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'pip install "pdtool[video]"' in lines[0] and "Traceback" not in proc.stderr
    assert not out.exists()


class _OpensOnUnpickle:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _bad_models(base: Path, tiny: Path) -> dict[str, tuple[Path, str]]:
    import shutil

    empty = base / "empty"
    empty.mkdir()
    other = base / "other"
    shutil.copytree(tiny, other)
    (other / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionPipeline"}))
    no_unet = base / "no_unet"
    shutil.copytree(tiny, no_unet)
    shutil.rmtree(no_unet / "unet")
    corrupt = base / "corrupt"
    shutil.copytree(tiny, corrupt)
    (corrupt / "unet" / "diffusion_pytorch_model.safetensors").write_bytes(b"not a safetensors file" * 10)
    pickled = base / "pickled"  # .bin weights are pickles: unpickling this one would create the marker
    shutil.copytree(tiny, pickled)
    (pickled / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    (pickled / "unet" / "diffusion_pytorch_model.bin").write_bytes(
        pickle.dumps(_OpensOnUnpickle(str(base / "pickle-ran"))))
    return {"pickled": (pickled, "pickles that can run code"),"missing": (base / "nowhere", "no such folder"), "empty": (empty, "no model_index.json"),
            "other": (other, "not an image-to-video"), "no_unet": (no_unet, "no unet/config.json"),
            "corrupt": (corrupt, "cannot load the model")}


@needs_extra
def test_bad_model_folders_are_one_clean_line(tiny_model: Path, shared_data: Path, tmp_path: Path) -> None:
    for name, (folder, words) in _bad_models(tmp_path, tiny_model).items():
        out = tmp_path / f"out_{name}"
        res = run_cli(shared_data / "udon.ply", "--up", "-y", "--model", folder, *SIZE, *FAST, "-o", out)
        assert res.exit_code == 2, (name, res.output)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0] and str(folder) in lines[0], (name, res.stderr)
        assert not out.exists(), name
    assert not (tmp_path / "pickle-ran").exists()
    # a frame size the model cannot take, before any rendering
    res = run_cli(shared_data / "udon.ply", "--model", tiny_model, "--width", "60", "--height", "48", "-o",
                  tmp_path / "odd")
    assert res.exit_code == 2 and "multiples of 8" in res.stderr and "--width 64" in res.stderr
    # an existing folder is not replaced without --overwrite
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep.txt").write_text("mine")
    res = run_cli(shared_data / "udon.ply", "--model", tiny_model, *SIZE, "-o", tmp_path / "taken")
    assert res.exit_code == 2 and "--overwrite" in res.stderr
    assert (tmp_path / "taken" / "keep.txt").read_text() == "mine"


# ----------------------------------------------------------------------------- camera motion


def texture(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """A smooth random RGB texture [H, W, 3] in 0-1 (structure at several scales)."""
    g = torch.Generator().manual_seed(seed)
    t = F.interpolate(torch.rand(1, 3, h // 8, w // 8, generator=g), size=(h, w), mode="bicubic")
    t = t + 0.5 * F.interpolate(torch.rand(1, 3, h // 2, w // 2, generator=g), size=(h, w), mode="bilinear")
    t = t - t.amin()
    return (t / t.amax())[0].permute(1, 2, 0)


def move(img: torch.Tensor, dx: float, dy: float, zoom: float = 1.0, roll: float = 0.0) -> torch.Tensor:
    """img with its content moved by (dx, dy) px, zoomed and rolled (rad) about the centre."""
    h, w, _ = img.shape
    cx, cy = (w - 1) / 2, (h - 1) / 2
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    px, py = xs - cx - dx, ys - cy - dy  # invert x = zoom R (y - c) + c + d
    c, s = math.cos(roll), math.sin(roll)
    u, v = (c * px + s * py) / zoom + cx, (-s * px + c * py) / zoom + cy
    grid = torch.stack([(2 * u + 1) / w - 1, (2 * v + 1) / h - 1], -1)[None].float()
    out = F.grid_sample(img.permute(2, 0, 1)[None], grid, mode="bicubic", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).clamp(0, 1)


def test_phase_correlation_finds_a_known_shift() -> None:
    ref = texture(96, 128)
    dx, dy, peak = phase_correlation(to_gray(ref), to_gray(move(ref, 7.0, -4.0)))[0]
    assert (dx, dy) == (pytest.approx(7.0, abs=0.25), pytest.approx(-4.0, abs=0.25)) and peak > 0.3


def test_camera_motion_recovers_shift_zoom_and_roll() -> None:
    ref = texture(144, 256)
    r = math.hypot(127.5, 71.5)  # corner radius, px
    frames = torch.stack([ref, move(ref, 3.4, -1.7), move(ref, 0, 0, zoom=1.02), move(ref, -5.25, 2.5, roll=0.01)])
    m = estimate_camera_motion(ref, frames)
    assert m.displacement[0] < 0.05
    np.testing.assert_allclose(m.shifts[1], [3.4, -1.7], atol=0.1)
    assert m.displacement[1] == pytest.approx(math.hypot(3.4, 1.7), abs=0.1)
    assert m.zooms[2] == pytest.approx(1.02, abs=1e-3) and m.displacement[2] == pytest.approx(0.02 * r, abs=0.2)
    np.testing.assert_allclose(m.shifts[3], [-5.25, 2.5], atol=0.1)
    assert m.rolls[3] == pytest.approx(0.01, abs=1e-3)
    assert m.long_side == 256 and m.max_percent == pytest.approx(100 * m.displacement.max() / 256)


def test_camera_motion_ignores_a_moving_object_and_follows_the_weight() -> None:
    background, obj = texture(144, 256, seed=1), texture(144, 256, seed=2)
    frames = []
    for k in range(4):  # an object in the middle moves right by 6 px a frame, the camera stays
        f = background.clone()
        f[30:110, 60 + 6 * k:140 + 6 * k] = obj[30:110, 60:140]
        frames.append(f)
    still = estimate_camera_motion(frames[0], torch.stack(frames))
    assert still.max_px < 0.5, still.displacement
    # the same video seen through a camera that moved by (2.5, 1) px
    panned = estimate_camera_motion(frames[0], torch.stack([move(f, 2.5, 1.0) for f in frames]))
    np.testing.assert_allclose(panned.shifts[1:], [[2.5, 1.0]] * 3, atol=0.25)
    # left half static, right half shifted by 5 px: the weight picks which half is "the scene"
    half = move(background, 5.0, 0.0)
    split = background.clone()
    split[:, 128:] = half[:, 128:]
    left = torch.zeros(144, 256)
    left[:, :120] = 1.0
    assert estimate_camera_motion(background, split[None], weight=left).max_px < 0.2
    right = torch.zeros(144, 256)
    right[:, 136:] = 1.0
    assert estimate_camera_motion(background, split[None], weight=right).shifts[0, 0] == pytest.approx(5.0, abs=0.2)


def test_frame_camera_fits_the_view_without_stretching() -> None:
    cam = Camera(200, 100, 180.0, 180.0, 101.0, 48.0, np.eye(4), "v")
    framed = frame_camera(cam, 64, 64)  # 2:1 into 1:1 -> scale 0.32, 20.8 px bands above and below
    assert framed.fx == pytest.approx(framed.fy) and framed.fx == pytest.approx(180 * 0.32)
    pts = np.array([[0.1, -0.05, 2.0], [-0.3, 0.1, 3.0]])
    a, b = cam.project(pts), framed.project(pts)
    np.testing.assert_allclose(b[:, 0], a[:, 0] * 0.32, atol=1e-9)
    np.testing.assert_allclose(b[:, 1], a[:, 1] * 0.32 + 0.5 * (64 - 100 * 0.32), atol=1e-9)


def test_camera_motion_on_rendered_views(shared_data: Path) -> None:
    # Real renders of the udon capture (white background, texture only on the object): the
    # camera's principal point moved by (3, -2) px and its focal length by 2% -> the image
    # content shifts by (3, -2) px and zooms by 1.02 about the principal point.
    import dataclasses

    from pd_tool.io import load_splats
    from pd_tool.render.views import render_image, scene_camera

    scene = load_splats(shared_data / "udon.ply")
    cam = scene_camera(scene, None, None, width=160, height=120, up_axis="-y")
    moved = dataclasses.replace(cam, cx=cam.cx + 3.0, cy=cam.cy - 2.0)
    zoomed = dataclasses.replace(cam, fx=cam.fx * 1.02, fy=cam.fy * 1.02)
    frames = np.stack([render_image(scene, c) for c in (cam, moved, zoomed)])
    m = estimate_camera_motion(frames[0], frames)
    assert m.displacement[0] < 0.05
    np.testing.assert_allclose(m.shifts[1], [3.0, -2.0], atol=0.15)
    assert m.zooms[2] == pytest.approx(1.02, abs=2e-3)


@needs_extra
def test_fp16_only_download_loads(tiny_model: Path, tmp_path: Path) -> None:
    # `huggingface-cli download ... --include "*.fp16.safetensors"` leaves only the fp16
    # variant files; inspect_model notices and the pipeline loads them (local files only).
    import shutil

    from pd_tool.video.generate import inspect_model, load_pipeline

    folder = tmp_path / "fp16"
    shutil.copytree(tiny_model, folder)
    for f in folder.glob("*/*.safetensors"):
        f.rename(f.with_name(f.name.replace(".safetensors", ".fp16.safetensors")))
    info = inspect_model(folder)
    assert (info.variant, info.multiple, info.class_name) == ("fp16", 8, "StableVideoDiffusionPipeline")
    pipe = load_pipeline(info, "cpu")
    assert pipe.unet.dtype == torch.float32 and pipe.vae_scale_factor == 4
    assert inspect_model(tiny_model).variant is None


def test_overwrite_of_a_folder_holding_someone_elses_file_says_what_overwrite_replaces(tmp_path: Path) -> None:
    from pd_tool.core.errors import OutputError
    from pd_tool.video.generate import check_output

    out = tmp_path / "videos"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="notes.txt, which pdtool did not write.*--overwrite replaces only folders "
                                          "that pdtool generate wrote"):
        check_output(out, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine"
