"""Input sanity checks that live in the loaders: values that parse but
cannot be meant, each refused at load time with one clear line.

- a video whose frames disagree with the camera: another aspect ratio, or a camera whose
  principal point lies outside its own image (intrinsics for another image size);
- a camera with a zero or negative focal length, or a field of view outside (0, pi);
- a force preset aimed at nothing pdtool knows ('at' other than "top" / "all").
The scene-scale, static-region and force-region checks live in prepare/bake.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pd_tool.core.cameras import Camera, load_cameras, save_camera_json
from pd_tool.core.errors import CameraError, PresetError, VideoError
from pd_tool.video.folder import load_reference_video, write_video_folder
from pd_tool.materials.presets import load_preset


def _video(tmp_path: Path, cam: Camera, w: int = 32, h: int = 24) -> Path:
    frames = np.random.default_rng(0).integers(0, 256, size=(3, h, w, 3), dtype=np.uint8)
    folder = write_video_folder(tmp_path / "video", frames, Camera(w, h, 30.0, 30.0, w / 2, h / 2), fps=10.0)
    save_camera_json(folder / "camera.json", cam)  # the camera under test replaces the right one
    return folder


def test_video_camera_of_same_aspect_is_resized(tmp_path: Path) -> None:
    """Not an error: a 4x larger camera with the frames' aspect is scaled to the frames."""
    folder = _video(tmp_path, Camera(128, 96, 120.0, 120.0, 64.0, 48.0))
    ref = load_reference_video(folder, working_size=None)
    assert (ref.camera.width, ref.camera.height) == (32, 24)
    assert ref.camera.fx == pytest.approx(30.0) and ref.camera.cx == pytest.approx(16.0)


def test_video_frames_of_another_aspect(tmp_path: Path) -> None:
    folder = _video(tmp_path, Camera(64, 64, 60.0, 60.0, 32.0, 32.0))
    with pytest.raises(VideoError, match=r"frames are 32x24 .* is 64x64") as e:
        load_reference_video(folder)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("cx,cy", [(960.0, 12.0), (16.0, 540.0), (-1.0, 12.0), (0.0, 12.0)])
def test_video_principal_point_outside_the_image(tmp_path: Path, cx: float, cy: float) -> None:
    """A camera.json whose size says 32x24 but whose cx, cy belong to a 1920x1080 image."""
    folder = _video(tmp_path, Camera(32, 24, 30.0, 30.0, cx, cy))
    with pytest.raises(VideoError, match="principal point .* lies outside its 32x24 image") as e:
        load_reference_video(folder)
    assert "\n" not in str(e.value) and "camera.json" in str(e.value)


@pytest.mark.parametrize("field,value", [("fx", 0.0), ("fx", -600.0), ("fy", -1.0)])
def test_camera_focal_length_must_be_positive(tmp_path: Path, field: str, value: float) -> None:
    cam = Camera(64, 48, 50.0, 50.0, 32.0, 24.0).to_dict()
    cam[field] = value
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(cam))
    with pytest.raises(CameraError, match=f"'{field}' must be a positive focal length"):
        load_cameras(path)


@pytest.mark.parametrize("angle", [0.0, -0.5, 3.2, 1e-320])
def test_nerf_field_of_view_in_radians(tmp_path: Path, angle: float) -> None:
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"w": 64, "h": 48, "camera_angle_x": angle,
                                "frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(CameraError, match="camera_angle_x"):
        load_cameras(path)


def test_nerf_field_of_view_in_degrees_is_refused(tmp_path: Path) -> None:
    """40 (degrees by mistake) is above pi: refused instead of a nonsense focal length."""
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps({"w": 64, "h": 48, "camera_angle_x": 40,
                                "frames": [{"transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(CameraError, match="not a field of view in radians"):
        load_cameras(path)


@pytest.mark.parametrize("at,ok", [("top", True), ("all", True), ("middle", False), ("", False), ("Top", False)])
def test_force_preset_aims_at_something(tmp_path: Path, at: str, ok: bool) -> None:
    path = tmp_path / "push.toml"
    path.write_text(f'at = "{at}"\nradius = 0.1\nstart = 0.0\nduration = 0.2\nmagnitude = 1.0\n')
    if ok:
        assert load_preset("forces", path)["at"] == at
    else:
        with pytest.raises(PresetError, match="is not one of 'top', 'all'"):
            load_preset("forces", path)
