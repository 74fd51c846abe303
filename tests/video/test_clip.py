"""pd_tool.video.clip: the frames the fit uses of a long or fast clip, and a handheld
camera's shake undone against frames with a known motion."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from cli import main
from pd_tool.core.errors import VideoError
from pd_tool.video.clip import MAX_FPS, MAX_FRAMES, STILL_PERCENT, choose_frames, prepare_clip, stabilise
from tests.video.test_generate import move, texture

H, W = 96, 160


def scene_frames(count: int, step_px: float = 1.5) -> torch.Tensor:
    """A textured room with an object in the middle that slides right by `step_px` a frame,
    seen by a still camera: [T, H, W, 3] in 0-1."""
    room, obj = texture(H, W, seed=1), texture(H, W, seed=2)
    frames = []
    for k in range(count):
        f = room.clone()
        x = round(50 + step_px * k)
        f[25:70, x:x + 45] = obj[25:70, 50:95]
        frames.append(f)
    return torch.stack(frames)


def shaken(frames: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, list[tuple[float, float, float, float]]]:
    """The frames seen by a hand-held camera: frame k>0 shifted by up to 4 px, zoomed by up
    to 1.5% and rolled by up to 0.01 rad (frame 0 untouched). Returns (frames, motions)."""
    rng = np.random.default_rng(seed)
    out, motions = [frames[0]], [(0.0, 0.0, 1.0, 0.0)]
    for f in frames[1:]:
        dx, dy = rng.uniform(-4, 4, 2)
        zoom, roll = 1 + rng.uniform(-0.015, 0.015), rng.uniform(-0.01, 0.01)
        out.append(move(f, dx, dy, zoom=zoom, roll=roll))
        motions.append((dx, dy, zoom, roll))
    return torch.stack(out), motions


def test_stabilise_undoes_a_handheld_shake_and_masks_what_the_frames_did_not_see() -> None:
    still = scene_frames(8)
    shook, motions = shaken(still)
    frames, masks, motion, warped = stabilise(shook, None)
    assert warped and masks is not None and masks.shape == (8, H, W)
    # the measured motion is the applied one (the object's own motion does not pull it)
    np.testing.assert_allclose(motion.shifts[1:], [m[:2] for m in motions[1:]], atol=0.3)
    np.testing.assert_allclose(motion.zooms[1:], [m[2] for m in motions[1:]], atol=2e-3)
    # the stabilised frames match what a still camera saw, where they saw it; shaken, they do not
    inner = torch.zeros(H, W)
    inner[8:-8, 8:-8] = 1.0
    for k in range(1, 8):
        m = masks[k] * inner
        err = float(((frames[k] - still[k]).abs().mean(-1) * m).sum() / m.sum())
        before = float(((shook[k] - still[k]).abs().mean(-1) * inner).sum() / inner.sum())
        assert err < 0.02 and err < 0.25 * before, (k, err, before)
    # a camera turned so that the content moved right by dx did not see the dx columns at the
    # right of frame 0's view
    k = int(np.argmax([m[0] for m in motions]))
    dx = motions[k][0]
    assert dx > 1.5 and float(masks[k][H // 2, W - int(dx) + 1:].max()) == 0.0
    assert float(masks[k][H // 2, W // 2]) == 1.0
    assert float(masks[0].min()) == 1.0  # frame 0 is the view itself
    # with object masks: measured outside them, and the masks warped as the frames are (a
    # reference: each warped on its own), times where the shaken frame saw the view
    from pd_tool.video.camera_motion import undo_motion

    obj = torch.zeros(8, H, W)
    obj[:, 20:75, 45:140] = 1.0
    frames_m, masks_m, motion_m, warped_m = stabilise(shook, obj)
    assert warped_m
    np.testing.assert_allclose(motion_m.shifts[1:], [m[:2] for m in motions[1:]], atol=0.3)
    ref_frames, valid = undo_motion(shook, motion_m)
    assert torch.allclose(frames_m, ref_frames, atol=1e-6)
    assert torch.allclose(masks_m, undo_motion(obj[..., None], motion_m)[0][..., 0] * valid, atol=1e-6)


def test_a_still_clip_is_left_as_it_is() -> None:
    still = scene_frames(6, step_px=3.0)
    frames, masks, motion, warped = stabilise(still, None)
    assert not warped and frames is still and masks is None and motion.max_percent < STILL_PERCENT
    # sensor noise of 2/255 is no camera motion either
    noisy = (still + torch.randn(still.shape, generator=torch.Generator().manual_seed(0)) * 2 / 255).clamp(0, 1)
    assert not stabilise(noisy, None)[3]


def test_a_plain_background_shows_no_camera_motion_and_the_object_is_left_out(shared_data: Path) -> None:
    """A render of a real capture turning before a white background: outside the object's
    widened footprint nothing has texture, so no camera motion is read into the object's."""
    from pd_tool.core.cameras import auto_camera
    from pd_tool.io import load_splats
    from pd_tool.render.views import render_image
    from pd_tool.video.clip import OBJECT_MARGIN, TEXTURE_LEVEL, footprint, outside_object, texture

    scene = load_splats(shared_data / "udon.ply")
    pos = scene.positions.numpy()
    cams = [auto_camera(pos, 96, 72, up_axis="-y", azimuth_deg=45.0 + 3.0 * k) for k in range(4)]
    frames = torch.stack([torch.from_numpy(render_image(scene, c)).float() / 255 for c in cams])
    weight = outside_object(footprint(scene, cams[0]))
    alpha = footprint(scene, cams[0])
    # the footprint, widened by the margin, is left out; the far background is kept
    r = round(OBJECT_MARGIN * 96)
    ys, xs = np.nonzero(alpha > 0.05)
    assert weight[ys, xs].max() == 0.0 and weight[0, 0] == 1.0
    near = (ys.min() - r + 1, xs[ys.argmin()])
    assert near[0] < 0 or weight[near] == 0.0
    assert texture(frames[0], weight) < TEXTURE_LEVEL < texture(frames[0])  # the object has texture, the rest not
    # nor does pixel noise of 2/255 on the plain background
    noisy = (frames + torch.randn(frames.shape, generator=torch.Generator().manual_seed(1)) * 2 / 255).clamp(0, 1)
    assert texture(noisy[0], weight) < TEXTURE_LEVEL
    out, masks, motion, warped = stabilise(frames, None, weight)
    assert motion is None and not warped and out is frames and masks is None


def test_choose_frames_thins_and_trims_and_refuses_too_few() -> None:
    assert choose_frames(14, 30.0) == (list(range(14)), 30.0)  # the paper's clip, as it is
    idx, fps = choose_frames(240, 60.0)
    assert idx == list(range(0, 60, 2)) and fps == 30.0 and len(idx) == MAX_FRAMES
    idx, fps = choose_frames(300, 120.0, start=37, max_frames=10)
    assert idx == list(range(37, 77, 4)) and fps == 30.0
    idx, fps = choose_frames(100, 50.0, max_frames=None)  # 50 fps: every 2nd, 25 fps
    assert idx == list(range(0, 100, 2)) and fps == 25.0
    assert choose_frames(90, 29.97, max_fps=MAX_FPS, max_frames=None) == (list(range(90)), 29.97)
    assert choose_frames(20, 240.0, max_fps=None, max_frames=None)[0] == list(range(20))
    with pytest.raises(VideoError, match="--start 14: the clip has frames 0-13"):
        choose_frames(14, 30.0, start=14)
    with pytest.raises(VideoError, match="leaves 2 frame"):
        choose_frames(14, 30.0, start=12)


def _clip(folder: Path, frames: torch.Tensor, fps: float) -> Path:
    from pd_tool.core.cameras import auto_camera
    from pd_tool.video.folder import write_video_folder

    cam = auto_camera(np.array([[-1.0, -1, -1], [1, 1, 1]]), W, H)
    write_video_folder(folder, (frames.numpy() * 255 + 0.5).astype(np.uint8), cam, fps)
    return folder


def test_prepare_clip_on_a_shaky_60_fps_phone_clip(tmp_path: Path) -> None:
    from pd_tool.video.folder import load_reference_video

    shook, _ = shaken(scene_frames(50, step_px=0.5), seed=3)
    ref = load_reference_video(_clip(tmp_path / "clip", shook, 60.0), working_size=None)
    out, choice = prepare_clip(ref, start=4)
    assert (choice.start, choice.step, choice.frames, choice.fps) == (4, 2, 23, 30.0)
    assert out.num_frames == 23 and out.fps == 30.0 and out.frame_dt == pytest.approx(1 / 30)
    assert out.frame_paths == [ref.frame_paths[i] for i in range(4, 50, 2)]
    assert choice.stabilised and choice.camera_motion > 0.5 and out.masks is not None
    line = choice.line("clip")
    assert "50 frames at 60 fps" in line and "frames 4-48, every 2nd: 23 frames at 30 fps" in line
    assert "warped back onto frame 0's view" in line and "--no-stabilise" in line
    # onto frame 0's view even from --start 4: the kept frames match the clip's first, where seen
    grey = torch.tensor([0.299, 0.587, 0.114])
    keep = torch.ones(H, W)
    keep[:, 45:125] = 0.0  # where the object slides over the 49 frames
    m = out.masks[0] * keep
    first = float((((out.frames[0] - ref.frames[0]) @ grey).abs() * m).sum() / m.sum())
    shaken_first = float(((ref.frames[4] - ref.frames[0]) @ grey).abs().mean())
    assert first < 0.25 * shaken_first, (first, shaken_first)
    # as it is: nothing to say, nothing changed
    plain, same = prepare_clip(ref, max_frames=None, max_fps=None, still=False)
    assert same.line("clip") is None and torch.equal(plain.frames, ref.frames)


def test_fit_refuses_a_start_past_the_clip_in_one_line(shared_data: Path, tmp_path: Path) -> None:
    clip = _clip(tmp_path / "clip", scene_frames(5), 30.0)
    res = CliRunner().invoke(main, ["fit", str(shared_data / "udon.ply"), str(clip), "--start", "9",
                                    "-o", str(tmp_path / "m.pdmat")])
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--start 9: the clip has frames 0-4" in lines[0]
    assert not (tmp_path / "m.pdmat").exists()


def test_the_cli_defaults_are_the_modules() -> None:
    params = {p.name: p for p in main.commands["fit"].params}
    assert params["max_frames"].default == MAX_FRAMES and params["max_fps"].default == MAX_FPS
    assert params["stabilise"].default is True and params["start"].default == 0
    assert math.isclose(MAX_FPS, 30.0)


def test_a_fit_uses_the_chosen_frames_says_so_and_records_them(tmp_path: Path, one_torch_thread) -> None:
    """A real (one iteration per stage) fit through the use case: a 7-frame clip read as 60 fps,
    from frame 1, keeps frames 1, 3, 5 at 30 fps; the line and the report say so."""
    import json

    from _plant import tiny_plant_video
    from pd_tool import app
    from pd_tool.fit.settings import FitSettings
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.prepare.preparation import PrepareOptions

    tiny_plant_video(tmp_path, 300, seed=0, size=24, n_frames=7)
    lines: list[str] = []
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=1, working_long_side=24)
    job = app.FitJob(tmp_path / "plant.ply", [tmp_path / "video"], tmp_path / "fit.pdmat", settings,
                     PrepareOptions(static_below=POT_TOP, up_axis="+z"), fps=60.0, start=1, preview=False,
                     record_dir=tmp_path)
    done = app.fit(job, say=lines.append)
    (choice,) = done.clips
    assert (choice.start, choice.step, choice.frames, choice.fps, choice.stabilised) == (1, 2, 3, 30.0, False)
    assert len(lines) == 1 and "7 frames at 60 fps; the fit uses frames 1-5, every 2nd: 3 frames at 30 fps" in lines[0]
    report = json.loads(done.side["report"].read_text())
    assert report["clips"] == [json.loads(json.dumps(dataclasses.asdict(choice)))]
