"""pd_tool.core.cameras: loaders (INRIA cameras.json, NeRF transforms.json, pdtool camera.json),
conventions, resizing, view selection, atomic save, auto framing and error messages."""
from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from pd_tool.core.cameras import (
    Camera, auto_camera, load_cameras, look_at, save_camera_json, select_view,
)
from pd_tool.core.errors import CameraError


def rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def write(path, obj):
    path.write_text(json.dumps(obj))
    return path


def test_inria_cameras_json(tmp_path):
    # Camera at (1, 2, 3) whose camera-to-world rotation turns the OpenCV axes by 30 deg about z.
    c2w = rot_z(30.0)
    p = write(tmp_path / "cameras.json", [
        {"id": 0, "img_name": "00001", "width": 64, "height": 48, "position": [1.0, 2.0, 3.0],
         "rotation": c2w.tolist(), "fx": 50.0, "fy": 55.0},
        {"id": 1, "img_name": "00002", "width": 64, "height": 48, "position": [0.0, 0.0, 0.0],
         "rotation": np.eye(3).tolist(), "fx": 50.0, "fy": 50.0},
    ])
    cams = load_cameras(p)
    assert [c.name for c in cams] == ["00001", "00002"]
    cam = cams[0]
    np.testing.assert_allclose(cam.center, [1.0, 2.0, 3.0], atol=1e-12)
    assert (cam.cx, cam.cy, cam.fx, cam.fy) == (32.0, 24.0, 50.0, 55.0)
    # A point 2 units along the camera's forward axis projects onto the principal point.
    fwd = np.array([1.0, 2.0, 3.0]) + 2.0 * c2w[:, 2]
    np.testing.assert_allclose(cam.project(fwd[None])[0], [32.0, 24.0, 2.0], atol=1e-9)
    right = np.array([1.0, 2.0, 3.0]) + 2.0 * c2w[:, 2] + 0.1 * c2w[:, 0]
    assert cam.project(right[None])[0, 0] > 32.0


def test_nerf_transforms_json_converts_opengl(tmp_path):
    # OpenGL camera at (0, 0, 4) looking down -z (identity rotation), world y up.
    c2w = np.eye(4)
    c2w[2, 3] = 4.0
    p = write(tmp_path / "transforms.json", {
        "camera_angle_x": 2 * math.atan(0.5), "w": 40, "h": 30,
        "frames": [{"file_path": "./train/r_7.png", "transform_matrix": c2w.tolist()}],
    })
    (cam,) = load_cameras(p)
    assert cam.name == "r_7"
    assert cam.fx == pytest.approx(40.0)  # tan(fov_x / 2) = 0.5 -> fx = 20 / 0.5
    assert cam.fy == pytest.approx(40.0)
    np.testing.assert_allclose(cam.center, [0.0, 0.0, 4.0], atol=1e-12)
    uvz = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(uvz[0], [20.0, 15.0, 4.0], atol=1e-9)  # in front, centred
    assert uvz[1, 1] < 15.0  # world +y (OpenGL up) appears above the centre (OpenCV y down)
    assert uvz[2, 0] > 20.0  # world +x to the right


def test_nerf_without_size_names_the_fix(tmp_path):
    p = write(tmp_path / "transforms.json", {"camera_angle_x": 0.7, "frames": [{"transform_matrix": np.eye(4).tolist()}]})
    with pytest.raises(CameraError, match="'w' and 'h'"):
        load_cameras(p)


def test_camera_json_roundtrip_and_position_rotation_form(tmp_path):
    w2c = look_at([3.0, -2.0, 1.0], [0.0, 0.0, 0.5], [0.0, 0.0, 1.0])
    cam = Camera(320, 180, 300.0, 310.0, 161.0, 89.5, w2c, name="view0", fps=24.0)
    path = tmp_path / "video" / "camera.json"
    save_camera_json(path, cam)
    assert sorted(os.listdir(path.parent)) == ["camera.json"]  # no temp file left behind
    (back,) = load_cameras(path)
    assert back.to_dict() == cam.to_dict()
    np.testing.assert_allclose(back.world_to_camera, w2c, atol=1e-12)
    assert back.fps == 24.0 and back.name == "view0"
    # Folder lookup finds camera.json.
    assert load_cameras(path.parent)[0].to_dict() == cam.to_dict()
    # position + rotation (camera-to-world) instead of world_to_camera.
    d = {"version": 1, "width": 320, "height": 180, "fx": 300.0, "position": cam.center.tolist(),
         "rotation": cam.camera_to_world[:3, :3].tolist()}
    (alt,) = load_cameras(write(tmp_path / "alt.json", d))
    np.testing.assert_allclose(alt.world_to_camera, w2c, atol=1e-12)
    assert (alt.fy, alt.cx, alt.cy, alt.fps) == (300.0, 160.0, 90.0, None)


def test_resized_keeps_field_of_view():
    cam = Camera(640, 360, 500.0, 500.0, 320.0, 180.0, look_at([0, -5, 1], [0, 0, 0], [0, 0, 1]))
    small = cam.resized(320, 180)
    pts = np.array([[0.3, 0.2, 0.1], [-1.0, 0.5, 0.7]])
    np.testing.assert_allclose(small.project(pts)[:, :2], cam.project(pts)[:, :2] / 2, atol=1e-9)
    assert math.atan(0.5 * small.width / small.fx) == pytest.approx(math.atan(0.5 * cam.width / cam.fx))
    np.testing.assert_allclose(small.K, np.diag([0.5, 0.5, 1.0]) @ cam.K)


def test_select_view():
    cams = [Camera(8, 8, 8, 8, 4, 4, np.eye(4), name=n) for n in ("a.png", "b", "c")]
    assert select_view(cams) is cams[0]
    assert select_view(cams, 2) is cams[2]
    assert select_view(cams, "b") is cams[1]
    assert select_view(cams, "a") is cams[0]  # file stem
    assert select_view(cams, "1") is cams[1]  # digits that name no camera: an index
    with pytest.raises(CameraError, match="no camera named 'zz'; choose one of: a.png, b, c"):
        select_view(cams, "zz")
    with pytest.raises(CameraError, match=r"view 3 out of range; the file has 3 cameras \(0..2\)"):
        select_view(cams, 3)


@pytest.mark.parametrize(
    "content,match",
    [
        ("{not json", "not valid JSON"),
        ('{"hello": 1}', "not a known camera file"),
        ('[{"id": 0, "width": 8, "height": 8, "fx": 8}]', "lacks 'position' and 'rotation'"),
        ('{"version": 1, "width": 8, "height": 8, "fx": 8}', "no extrinsics"),
        ('{"version": 2, "width": 8, "height": 8, "fx": 8, "world_to_camera": []}', "version 2"),
        ('{"version": 1, "width": 0, "height": 8, "fx": 8, "position": [0,0,0], "rotation": [[1,0,0],[0,1,0],[0,0,1]]}', "'width' must be a positive integer"),
        ('{"version": 1, "width": 8, "height": 8, "fx": "8", "position": [0,0,0], "rotation": [[1,0,0],[0,1,0],[0,0,1]]}', "'fx' must be a finite number"),
        ('{"version": 1, "width": 8, "height": 8, "fx": 8, "position": [0,0,0], "rotation": [[2,0,0],[0,1,0],[0,0,1]]}', "not a proper rotation"),
        ('{"version": 1, "width": 8, "height": 8, "fx": 8, "world_to_camera": [[1,0,0]]}', "finite 4x4 array"),
    ],
)
def test_malformed_files_raise_one_line(tmp_path, content, match):
    p = tmp_path / "camera.json"
    p.write_text(content)
    with pytest.raises(CameraError, match=match) as e:
        load_cameras(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(CameraError, match="camera file not found"):
        load_cameras(tmp_path / "nope.json")
    with pytest.raises(CameraError, match="folder holds no camera.json"):
        load_cameras(tmp_path)


@pytest.mark.parametrize("up_axis", ["z", "+z", "y", "-y"])
def test_auto_camera_frames_the_object(up_axis):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(2000, 3)) * [1.0, 0.5, 0.3] + [5.0, -2.0, 1.0]
    pts[:5] += 1000.0  # floaters must not shrink the object
    cam = auto_camera(pts, 160, 120, up_axis=up_axis)
    uvz = cam.project(pts[5:])
    assert (uvz[:, 2] > 0).all()
    inside = (uvz[:, 0] > 0) & (uvz[:, 0] < 160) & (uvz[:, 1] > 0) & (uvz[:, 1] < 120)
    assert inside.mean() > 0.95
    # Everything inside the 1-99th percentile box is in view, and it fills the frame.
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    box = uvz[np.all((pts[5:] >= lo) & (pts[5:] <= hi), axis=1)]
    assert (box[:, 0] > 0).all() and (box[:, 0] < 160).all() and (box[:, 1] > 0).all() and (box[:, 1] < 120).all()
    fill = max(np.ptp(box[:, 0]) / 160, np.ptp(box[:, 1]) / 120)
    assert 0.6 < fill < 1.0
    assert abs(np.median(uvz[:, 0]) - 80) < 16 and abs(np.median(uvz[:, 1]) - 60) < 12
    # The world up axis points up in the image (smaller v).
    up = {"z": [0, 0, 1], "+z": [0, 0, 1], "y": [0, 1, 0], "-y": [0, -1, 0]}[up_axis]
    c = np.median(pts, axis=0)
    a, b = cam.project(np.array([c, c + 0.1 * np.array(up)]))
    assert b[1] < a[1]
    with pytest.raises(CameraError, match="unknown up axis"):
        auto_camera(pts, 16, 16, up_axis="w")
