"""Tests of pd_tool.video.folder: reference video folders (frames or .mp4, camera.json, masks),
resizing to the working resolution, fps rules and the one-line errors."""
from __future__ import annotations

import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from pd_tool.core.cameras import Camera, load_cameras
from pd_tool.core.errors import CameraError, VideoError
from pd_tool.video.folder import (
    DEFAULT_FPS,
    load_reference_video,
    natural_key,
    write_video_folder,
)

W, H, T = 32, 24, 5


def _camera(w: int = W, h: int = H, fps: float | None = None) -> Camera:
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1, -0.2, 2.0]
    return Camera(w, h, 40.0, 41.0, w / 2 + 0.5, h / 2 - 0.25, w2c, name="front", fps=fps)


def _frames(t: int = T, h: int = H, w: int = W, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, size=(t, h, w, 3), dtype=np.uint8)


def _camera_json(path: Path, cam: Camera, **extra) -> None:
    """A camera.json written by hand per the schema (version, width, height, fx, fy, cx, cy,
    world_to_camera, fps)."""
    d = {"version": 1, "width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
         "cx": cam.cx, "cy": cam.cy, "world_to_camera": cam.world_to_camera.tolist(), **extra}
    path.write_text(json.dumps(d))


def test_round_trip_frames_masks_camera(tmp_path, device):
    frames = _frames()
    masks = np.zeros((T, H, W), np.uint8)
    masks[:, 5:15, 8:20] = 255
    folder = write_video_folder(tmp_path / "video", frames, _camera(), 24.0, masks=masks)
    from pd_tool.core.atomic import MANIFEST

    assert sorted(p.name for p in folder.iterdir()) == sorted(
        [MANIFEST, "camera.json", "masks"] + [f"frame_{i:04d}.png" for i in range(T)])  # the manifest: pdtool's folder
    assert not [p for p in tmp_path.iterdir() if p.name != "video"]  # no temp leftovers
    dev = "cuda" if device == "cuda" else "cpu"
    v = load_reference_video(folder, working_size=None, device=dev)
    assert v.frames.shape == (T, H, W, 3) and v.frames.dtype == torch.float32
    assert v.frames.device.type == dev
    assert torch.equal(v.frames.cpu(), torch.from_numpy(frames).float() / 255.0)  # PNG is lossless
    assert torch.equal(v.masks.cpu(), torch.from_numpy(masks).float() / 255.0)
    assert v.fps == 24.0 and v.num_frames == T and (v.width, v.height) == (W, H)
    assert v.camera.fx == 40.0 and v.camera.cx == W / 2 + 0.5
    assert np.array_equal(v.camera.world_to_camera, _camera().world_to_camera)
    assert v.camera_path == folder / "camera.json" and len(v.frame_paths) == T


def test_natural_sort_and_jpg(tmp_path):
    folder = tmp_path / "v"
    folder.mkdir()
    for i in (8, 9, 11):  # lexicographic order would be 11, 8, 9
        iio.imwrite(folder / f"frame{i}.png", np.full((H, W, 3), i * 20, np.uint8))
    iio.imwrite(folder / "frame10.jpg", np.full((H, W, 3), 200, np.uint8))
    (folder / "notes.txt").write_text("ignored")
    _camera_json(folder / "camera.json", _camera())
    v = load_reference_video(folder, working_size=None)
    assert [p.name for p in v.frame_paths] == ["frame8.png", "frame9.png", "frame10.jpg", "frame11.png"]
    levels = (v.frames[:, 0, 0, 0] * 255).round().tolist()
    assert levels == [160, 180, 200, 220]
    assert v.fps == DEFAULT_FPS  # no fps anywhere
    assert natural_key("Frame02b") < natural_key("frame10a")


def test_frames_that_would_shift_in_time_are_refused(tmp_path):
    # a frame's index is its time: a folder named like a frame, or a gap in the numbering,
    # would move every later frame to the wrong time
    folder = tmp_path / "v"
    folder.mkdir()
    for i in range(6):
        iio.imwrite(folder / f"frame_{i:04d}.png", np.full((H, W, 3), 50, np.uint8))
    _camera_json(folder / "camera.json", _camera())
    assert load_reference_video(folder, working_size=None).num_frames == 6
    (folder / "frame_0006.png").mkdir()
    with pytest.raises(VideoError, match="frame_0006.png: has a frame's name but is a folder"):
        load_reference_video(folder, working_size=None)
    (folder / "frame_0006.png").rmdir()
    (folder / "frame_0002.png").unlink()
    with pytest.raises(VideoError, match="jump from frame_0001.png to frame_0003.png"):
        load_reference_video(folder, working_size=None)
    for i in (0, 4):  # every other frame, evenly: a constant step keeps the timing
        (folder / f"frame_{i:04d}.png").unlink()
    assert [p.name for p in load_reference_video(folder, working_size=None).frame_paths] == [
        "frame_0001.png", "frame_0003.png", "frame_0005.png"]


def test_working_size_resizes_frames_masks_and_camera(tmp_path):
    frames = np.zeros((T, H, W, 3), np.uint8)
    frames[:, :, : W // 2] = 200  # left half bright
    masks = np.zeros((T, H, W), np.uint8)
    masks[:, :, W // 2:] = 255
    folder = write_video_folder(tmp_path / "v", frames, _camera(), 30.0, masks=masks)
    v = load_reference_video(folder, working_size=16)  # long side 32 -> 16
    assert v.frames.shape == (T, 12, 16, 3) and v.masks.shape == (T, 12, 16)
    assert v.native_size == (W, H)
    # a 2:1 box-like downsample keeps the halves exact away from the edge
    assert torch.allclose(v.frames[:, :, :7], torch.tensor(200 / 255.0), atol=1e-6)
    assert torch.allclose(v.frames[:, :, 9:], torch.tensor(0.0), atol=1e-6)
    assert float(v.masks[:, :, :7].max()) == 0.0 and float(v.masks[:, :, 9:].min()) == 1.0
    cam = v.camera
    assert (cam.width, cam.height) == (16, 12)
    assert cam.fx == pytest.approx(20.0) and cam.cy == pytest.approx((H / 2 - 0.25) / 2)
    # exact size with the same aspect; no upscaling for a long side above native
    assert load_reference_video(folder, working_size=(16, 12)).frames.shape[1:3] == (12, 16)
    assert load_reference_video(folder, working_size=1024).frames.shape[1:3] == (H, W)
    with pytest.raises(VideoError, match="stretch"):
        load_reference_video(folder, working_size=(16, 16))


def test_fps_priority(tmp_path):
    folder = write_video_folder(tmp_path / "v", _frames(), _camera(), 12.0)
    assert load_reference_video(folder).fps == 12.0  # camera.json
    assert load_reference_video(folder, fps=60).fps == 60.0  # argument wins
    _camera_json(folder / "camera.json", _camera())  # no fps in camera.json
    assert load_reference_video(folder).fps == DEFAULT_FPS
    with pytest.raises(VideoError, match="fps"):
        load_reference_video(folder, fps=0)


def _write_mp4(path: Path, frames: np.ndarray, fps: float) -> None:
    import imageio

    w = imageio.v2.get_writer(path, fps=fps, macro_block_size=1, quality=9)
    for f in frames:
        w.append_data(f)
    w.close()


def test_mp4_folder_and_mp4_path(tmp_path):
    folder = tmp_path / "v"
    folder.mkdir()
    # smooth content: lossy H.264 keeps it within a few levels
    yy, xx = np.mgrid[0:48, 0:64]
    frames = np.stack([np.stack([xx * 3 + k * 5, yy * 4, np.full_like(xx, 128)], -1) for k in range(6)])
    frames = frames.clip(0, 255).astype(np.uint8)
    _write_mp4(folder / "clip.mp4", frames, fps=24)
    _camera_json(folder / "camera.json", _camera(64, 48))  # no fps: the video's own is used
    v = load_reference_video(folder, working_size=None)
    assert v.frames.shape == (6, 48, 64, 3)
    assert v.fps == pytest.approx(24.0)
    assert float((v.frames - torch.from_numpy(frames).float() / 255).abs().mean()) < 0.03
    assert v.frame_paths == [folder / "clip.mp4"]
    # the video file itself may be passed; masks/ beside it apply
    (folder / "masks").mkdir()
    for i in range(6):
        iio.imwrite(folder / "masks" / f"m{i}.png", np.full((48, 64), 255, np.uint8))
    v2 = load_reference_video(folder / "clip.mp4", working_size=32)
    assert v2.frames.shape == (6, 24, 32, 3) and v2.masks.shape == (6, 24, 32)


def test_mask_channel_conventions(tmp_path):
    folder = write_video_folder(tmp_path / "v", _frames(t=3), _camera(), 30.0)
    (folder / "masks").mkdir()
    gray = np.zeros((H, W), np.uint8)
    gray[:4] = 255
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:4, :, 1] = 255  # any channel lit counts
    rgba = np.full((H, W, 4), 255, np.uint8)
    rgba[4:, :, 3] = 0  # alpha is the mask, colour ignored
    for i, m in enumerate((gray, rgb, rgba)):
        iio.imwrite(folder / "masks" / f"{i}.png", m)
    v = load_reference_video(folder, working_size=None)
    expect = torch.zeros(H, W)
    expect[:4] = 1.0
    for i in range(3):
        assert torch.equal(v.masks[i], expect)


def test_camera_from_file_and_view(tmp_path):
    folder = write_video_folder(tmp_path / "v", _frames(), _camera(), 30.0)
    (folder / "camera.json").unlink()
    with pytest.raises(VideoError, match="no camera.json.*--camera FILE --view ID"):
        load_reference_video(folder)
    other = _camera(64, 48)
    other.name = "side"
    cams = tmp_path / "cams.json"
    cams.write_text(json.dumps([_camera().to_dict(), other.to_dict()]))
    assert [c.name for c in load_cameras(cams)] == ["front", "side"]
    v = load_reference_video(folder, camera_path=cams, view="side", working_size=None)
    assert v.camera.name == "side" and (v.camera.width, v.camera.height) == (W, H)
    assert v.camera.fx == pytest.approx(other.fx / 2)  # resized 64x48 -> 32x24
    assert load_reference_video(folder, camera_path=cams, view=0).camera.name == "front"
    with pytest.raises(CameraError, match="no camera named"):
        load_reference_video(folder, camera_path=cams, view="top")


def test_errors_are_one_line_with_a_fix(tmp_path):
    cam = _camera()

    def expect(match, folder, **kw):
        with pytest.raises(VideoError, match=match) as e:
            load_reference_video(folder, **kw)
        assert "\n" not in str(e.value)

    expect("not found", tmp_path / "missing")
    empty = tmp_path / "empty"
    empty.mkdir()
    expect("no frames", empty)

    short = write_video_folder(tmp_path / "short", _frames(t=2), cam, 30.0)
    expect("2 frame.*at least 3", short)

    mixed = write_video_folder(tmp_path / "mixed", _frames(), cam, 30.0)
    iio.imwrite(mixed / "frame_0003.png", np.zeros((H + 2, W, 3), np.uint8))
    expect(r"frame_0003.png: frame is 32x26 but frame_0000.png is 32x24", mixed)

    broken = write_video_folder(tmp_path / "broken", _frames(), cam, 30.0)
    (broken / "frame_0002.png").write_bytes(b"not a png at all")
    expect(r"frame_0002.png: cannot read image", broken)

    masks = write_video_folder(tmp_path / "masks", _frames(), cam, 30.0, masks=np.ones((T, H, W), bool))
    (masks / "masks" / "mask_0004.png").unlink()
    expect("4 mask.*for 5 frames", masks)
    iio.imwrite(masks / "masks" / "mask_0004.png", np.ones((H, W + 1), np.uint8))
    expect("mask is 33x24 but the frames are 32x24", masks)

    aspect = write_video_folder(tmp_path / "aspect", _frames(), cam, 30.0)
    _camera_json(aspect / "camera.json", _camera(32, 32))
    expect(r"aspect 1.333.*aspect 1.000", aspect)

    both = write_video_folder(tmp_path / "both", _frames(), cam, 30.0)
    _write_mp4(both / "x.mp4", _frames(), 30)
    expect("both image frames", both)

    with pytest.raises(VideoError, match="already exists"):
        write_video_folder(both, _frames(), cam, 30.0)

    two = tmp_path / "two"
    two.mkdir()
    _camera_json(two / "camera.json", cam)
    _write_mp4(two / "a.mp4", _frames(), 30)
    (two / "b.mp4").write_bytes((two / "a.mp4").read_bytes())
    expect("2 videos.*one per folder", two)
    (two / "a.mp4").unlink()
    (two / "b.mp4").write_bytes(b"\x00" * 1000)
    expect("b.mp4: cannot decode video", two)


def test_write_is_atomic_and_overwrites(tmp_path, monkeypatch):
    folder = write_video_folder(tmp_path / "v", _frames(seed=1), _camera(), 30.0)
    calls = {"n": 0}
    real = iio.imwrite

    def failing(path, arr, **kw):  # a disk error on the third frame
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full")
        return real(path, arr, **kw)

    monkeypatch.setattr(iio, "imwrite", failing)
    with pytest.raises(OSError):
        write_video_folder(folder, _frames(seed=2), _camera(), 30.0, overwrite=True)
    monkeypatch.undo()
    assert [p.name for p in tmp_path.iterdir()] == ["v"]  # old folder intact, no temp dir
    v = load_reference_video(folder, working_size=None)
    assert torch.equal(v.frames, torch.from_numpy(_frames(seed=1)).float() / 255)
    write_video_folder(folder, _frames(seed=2, t=4), _camera(64, 48), 15.0, overwrite=True)
    v = load_reference_video(folder, working_size=None)
    assert v.num_frames == 4 and v.fps == 15.0 and v.camera.width == W  # camera resized to frames


def test_gray_16bit_and_rgba_frames(tmp_path):
    folder = tmp_path / "v"
    folder.mkdir()
    iio.imwrite(folder / "f0.png", np.full((H, W), 32768, np.uint16))  # 16-bit gray
    iio.imwrite(folder / "f1.png", np.full((H, W), 51, np.uint8))  # 8-bit gray
    rgba = np.zeros((H, W, 4), np.uint8)
    rgba[..., 0], rgba[..., 3] = 255, 0  # alpha is ignored in frames
    iio.imwrite(folder / "f2.png", rgba)
    _camera_json(folder / "camera.json", _camera())
    v = load_reference_video(folder, working_size=None)
    assert torch.allclose(v.frames[0], torch.tensor(32768 / 65535), atol=1e-6)
    assert torch.allclose(v.frames[1], torch.tensor(0.2), atol=1e-6)
    assert torch.equal(v.frames[2, 0, 0], torch.tensor([1.0, 0.0, 0.0]))
    assert v.masks is None
