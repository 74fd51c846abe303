"""One input per loader bug that tests/fuzz_cases.py found (see docs/reliability.md): each
crashed with a foreign exception, printed a warning, or loaded an insane object; each must
raise the loader's PdToolError subclass with a one-line message naming the file."""
from __future__ import annotations

import json
import random
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pd_tool.core.cameras import load_cameras
from pd_tool.core.errors import CameraError, MaterialFileError, PlyFormatError, PresetError
from pd_tool.io import load_splats
from pd_tool.materials.file import MaterialFile
from pd_tool.materials.presets import load_preset
import fuzz_cases as fuzz


def _one_line(e: pytest.ExceptionInfo, path: Path) -> None:
    msg = str(e.value)
    assert "\n" not in msg and str(path) in msg


# ----------------------------------------------------------------------------- cameras
def _pdtool_cam(**changes) -> dict:
    cam = {"version": 1, "width": 64, "height": 48, "fx": 50.0, "world_to_camera": np.eye(4).tolist()}
    cam.update(changes)
    return cam


def _nerf(**changes) -> dict:
    d = {"w": 64, "h": 48, "camera_angle_x": 0.7, "frames": [{"file_path": "r_0", "transform_matrix": np.eye(4).tolist()}]}
    d.update(changes)
    return d


CAMERA_CASES = {
    "deep nesting (RecursionError)": "[" * 100000 + "]" * 100000,
    "width inf (OverflowError)": json.dumps(_pdtool_cam(width=float("inf"))),
    "height NaN (ValueError)": json.dumps(_pdtool_cam(height=float("nan"))),
    "transforms width as a string (ValueError)": json.dumps(
        {k: v for k, v in _nerf(width="abc", height=48).items() if k not in ("w", "h")}),
    "integer beyond float range (OverflowError)": json.dumps(_pdtool_cam()).replace('"fx": 50.0', '"fx": 1' + "0" * 400),
    "matrix entry beyond float range (OverflowError)": json.dumps(_pdtool_cam()).replace("1.0", "1" + "0" * 400, 1),
    "non-object in cameras list (AttributeError)": json.dumps({"cameras": [[1, 2]]}),
    "zero focal length": json.dumps(_pdtool_cam(fx=0.0)),
    "negative focal length": json.dumps(_pdtool_cam(fy=-50.0)),
    "camera_angle_x = 0 (ZeroDivisionError)": json.dumps(_nerf(camera_angle_x=0.0)),
    "camera_angle_x = pi (negative focal)": json.dumps(_nerf(camera_angle_x=3.2)),
    "transform_matrix last row (non-rigid camera)": json.dumps(
        _nerf(frames=[{"transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 5, 1]]}])),
}


@pytest.mark.parametrize("name", sorted(CAMERA_CASES))
def test_camera_regressions(tmp_path: Path, name: str) -> None:
    path = tmp_path / ("transforms.json" if "transforms" in name or "camera_angle" in name else "camera.json")
    path.write_text(CAMERA_CASES[name])
    with pytest.raises(CameraError) as e:
        load_cameras(path)
    _one_line(e, path)


# ----------------------------------------------------------------------------- material file
def _material_members() -> dict[str, bytes]:
    arrays = fuzz._material_arrays(random.Random(0))
    return {f"{k}.npy": fuzz._npy(v) for k, v in arrays.items()}


def _meta_with(**changes) -> bytes:
    arrays = fuzz._material_arrays(random.Random(0))
    meta = json.loads(arrays["meta"].tobytes())
    for k, v in changes.items():
        if v is None:
            meta.pop(k)
        else:
            meta[k] = v
    return fuzz._npy(np.frombuffer(json.dumps(meta).encode(), np.uint8))


def _damaged_deflate() -> bytes:
    import io

    data = bytearray(fuzz._zip_of(_material_members(), compress=True))
    info = zipfile.ZipFile(io.BytesIO(bytes(data))).getinfo("driver_E.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)  # its compressed stream
    data[start] = 0x07  # a deflate block of the reserved type 3: zlib.error "invalid block type"
    return bytes(data)


def _unknown_compression() -> bytes:
    data = bytearray(fuzz._zip_of(_material_members(), compress=False))
    data[8] = 99  # the first local header's compression method
    i = data.index(b"PK\x01\x02")
    data[i + 10] = 99  # and the central directory's
    return bytes(data)


MATERIAL_CASES = {
    "a bare .npy (TypeError)": lambda: fuzz._npy(np.ones(3)),
    "damaged deflate data (zlib.error)": _damaged_deflate,
    "unknown compression method (NotImplementedError)": _unknown_compression,
    "huge declared .npy shape (MemoryError)": lambda: fuzz._zip_of(
        {**_material_members(), "driver_E.npy": fuzz._npy_with_shape(np.ones(2), f"({10 ** 12},)")}, False),
    "deeply nested header (RecursionError)": lambda: fuzz._zip_of(
        {**_material_members(), "meta.npy": fuzz._npy(np.frombuffer(("[" * 100000).encode(), np.uint8))}, False),
    "0-d driver_E (TypeError)": lambda: fuzz._zip_of({**_material_members(), "driver_E.npy": fuzz._npy(np.array(3.0))}, False),
    "string driver_E (TypeError)": lambda: fuzz._zip_of(
        {**_material_members(), "driver_E.npy": fuzz._npy(np.array(["1", "2"]))}, False),
    "complex field array": lambda: fuzz._zip_of(
        {**_material_members(), "field.material.weight.npy": fuzz._npy(np.ones(3, np.complex64))}, False),
    "NaN in a field array": lambda: fuzz._zip_of(
        {**_material_members(), "field.material.weight.npy": fuzz._npy(np.array([np.nan], np.float32))}, False),
    "nu out of range": lambda: fuzz._zip_of({**_material_members(), "meta.npy": _meta_with(nu=0.7)}, False),
    "density a string": lambda: fuzz._zip_of({**_material_members(), "meta.npy": _meta_with(density="1000")}, False),
    "prepare not a table": lambda: fuzz._zip_of({**_material_members(), "meta.npy": _meta_with(prepare=[1])}, False),
}


@pytest.mark.parametrize("name", sorted(MATERIAL_CASES))
def test_material_regressions(tmp_path: Path, name: str) -> None:
    path = tmp_path / "m.pdmat"
    path.write_bytes(MATERIAL_CASES[name]())
    with pytest.raises(MaterialFileError) as e:
        MaterialFile.load(path)
    _one_line(e, path)


def test_material_generator_base_is_valid(tmp_path: Path) -> None:
    """The unmutated generator output loads (so the cases above fail for their one edit)."""
    path = tmp_path / "m.pdmat"
    path.write_bytes(fuzz._zip_of(_material_members(), compress=True))
    m = MaterialFile.load(path)
    assert m.nu == 0.3 and m.density == 1000.0 and len(m.driver_E) == len(m.driver_v0)
    with zipfile.ZipFile(path) as z:
        assert z.testzip() is None


def test_material_missing_nu_is_a_clear_error(tmp_path: Path) -> None:
    """A header without nu loads (old test files have none) but a bake reading it gets a
    MaterialFileError, not KeyError."""
    path = tmp_path / "m.pdmat"
    path.write_bytes(fuzz._zip_of({**_material_members(), "meta.npy": _meta_with(nu=None)}, False))
    m = MaterialFile.load(path)
    with pytest.raises(MaterialFileError, match="no 'nu'"):
        m.nu


# ----------------------------------------------------------------------------- presets
PRESET_CASES = {
    "nan for an integer (ValueError)": "[q]\ngrid_res = nan\ncfl_safety = 0.5\ndriver_ratio = 0.1\nfit_velocity_iters = 1\nfit_material_iters = 1\n",
    "inf for an integer (OverflowError)": "grid_res = inf\ncfl_safety = 0.5\ndriver_ratio = 0.1\nfit_velocity_iters = 1\nfit_material_iters = 1\n",
    "nested arrays (RecursionError)": "grid_res = " + "[" * 100000 + "]" * 100000 + "\n",
}


@pytest.mark.parametrize("name", sorted(PRESET_CASES))
def test_preset_regressions(tmp_path: Path, name: str) -> None:
    path = tmp_path / "q.toml"
    path.write_text(PRESET_CASES[name])
    with pytest.raises(PresetError) as e:
        load_preset("quality", path)
    _one_line(e, path)


# ----------------------------------------------------------------------------- ply
def _ply(tmp_path: Path, dtype: str = "<f4", **values) -> Path:
    rec = fuzz._ply_records(random.Random(0), 3, 0, normals=False, extra=False, dtype=dtype)
    for name, v in values.items():
        rec[name][1] = v
    path = tmp_path / "s.ply"
    path.write_bytes(fuzz._ply_bytes(rec, "le"))
    return path


@pytest.mark.parametrize("values", [
    {"scale_0": 100.0},  # exp(100) is finite in float64, inf in float32
    {"x": 1e300},  # a double-precision file
    {"f_dc_0": -1e300},
    {"rot_0": 1e300, "rot_1": 1e300},  # the norm overflows: quats of zero length
], ids=["log-scale 100", "x 1e300", "f_dc 1e300", "rot 1e300"])
def test_ply_beyond_float32(tmp_path: Path, values: dict) -> None:
    path = _ply(tmp_path, "<f8", **values)
    with pytest.raises(PlyFormatError) as e:
        load_splats(path)
    _one_line(e, path)


def test_ply_very_negative_opacity_logit_is_quiet(tmp_path: Path) -> None:
    """A logit of -1000 is opacity 0, without numpy's overflow warning on stderr."""
    path = _ply(tmp_path, opacity=-1000.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_splats(path)
    assert float(scene.opacities[1]) == 0.0


@pytest.mark.parametrize("fmt", ["le", "ascii"])
def test_ply_list_property(tmp_path: Path, fmt: str) -> None:
    """A well-formed PLY whose f_dc_0 is a `property list uchar float` (numpy's ValueError
    before; an empty list in an ASCII body also printed numpy's loadtxt UserWarning)."""
    import io

    from plyfile import PlyData, PlyElement

    rec = fuzz._ply_records(random.Random(0), 2, 0, normals=False, extra=False)
    dtype = [(n, "O" if n == "f_dc_0" else rec.dtype[n]) for n in rec.dtype.names]
    lst = np.empty(2, dtype=dtype)
    for n in rec.dtype.names:
        lst[n] = rec[n]
    lst["f_dc_0"][0] = np.array([0.5], np.float32)
    lst["f_dc_0"][1] = np.array([], np.float32)
    buf = io.BytesIO()
    el = PlyElement.describe(lst, "vertex", val_types={"f_dc_0": "f4"}, len_types={"f_dc_0": "u1"})
    PlyData([el], text=fmt == "ascii").write(buf)
    path = tmp_path / "s.ply"
    path.write_bytes(buf.getvalue())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(PlyFormatError) as e:
            load_splats(path)
    _one_line(e, path)
    assert not caught, [str(w.message) for w in caught]


def test_ply_float_region_is_not_a_label(tmp_path: Path) -> None:
    """A float 'region' property holding NaN is kept as an extra property, not cast to int
    labels (numpy's 'invalid value in cast' warning before)."""
    rec = fuzz._ply_records(random.Random(0), 3, 0, normals=False, extra=False)
    from numpy.lib import recfunctions

    rec = recfunctions.append_fields(rec, "region", np.array([0.0, np.nan, 2.0], np.float32), usemask=False)
    path = tmp_path / "s.ply"
    path.write_bytes(fuzz._ply_bytes(rec, "le"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_splats(path)
    assert scene.labels is None and "region" in scene.extra


def test_ply_signalling_nan_is_quiet(tmp_path: Path) -> None:
    """A float32 signalling NaN (bytes 7fa00000) widened to float64 printed numpy's
    'invalid value encountered in cast' warning before the one-line error."""
    rec = fuzz._ply_records(random.Random(0), 2, 0, normals=False, extra=False)
    rec["x"].view(np.uint32)[1] = 0x7FA00000
    path = tmp_path / "s.ply"
    path.write_bytes(fuzz._ply_bytes(rec, "le"))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(PlyFormatError, match="NaN/inf position") as e:
            load_splats(path)
    _one_line(e, path)
    assert not caught, [str(w.message) for w in caught]


def test_camera_huge_rotation_entry_is_quiet(tmp_path: Path) -> None:
    """A rotation entry of 1e308 printed numpy's overflow warning (from the SVD) before the
    one-line error."""
    m = np.eye(4)
    m[0, 1] = 1e308
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(_pdtool_cam(world_to_camera=m.tolist())))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(CameraError, match="not a proper rotation") as e:
            load_cameras(path)
    _one_line(e, path)
    assert not caught, [str(w.message) for w in caught]


@pytest.mark.parametrize("size", [(10000, 10000), (100000, 100000)])
def test_video_frame_declaring_huge_size(tmp_path: Path, size: tuple[int, int]) -> None:
    """A PNG header claiming 10^8 pixels printed Pillow's DecompressionBombWarning before the
    error; both sizes now give one VideoError line."""
    from pd_tool.core.cameras import Camera, save_camera_json
    from pd_tool.core.errors import VideoError
    from pd_tool.video.folder import load_reference_video

    folder = tmp_path / "video"
    folder.mkdir()
    frame = fuzz._png_bytes(np.zeros((8, 8, 3), np.uint8))
    for i in range(3):
        (folder / f"frame_{i:04d}.png").write_bytes(frame)
    (folder / "frame_0001.png").write_bytes(fuzz._png_with_size(frame, *size))
    save_camera_json(folder / "camera.json", Camera(8, 8, 10.0, 10.0, 4.0, 4.0))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(VideoError, match="pixels") as e:
            load_reference_video(folder)
    _one_line(e, folder / "frame_0001.png")
    assert not [w for w in caught if not issubclass(w.category, ResourceWarning)]


def test_material_scene_path_and_prepare_accessors(tmp_path: Path) -> None:
    """A hand-made material without scene_path / prepare loads; the accessors a bake should
    use say so with None / a MaterialFileError instead of KeyError (cli.py indexes meta)."""
    path = tmp_path / "m.pdmat"
    path.write_bytes(fuzz._zip_of({**_material_members(), "meta.npy": _meta_with(scene_path=None, prepare=None)}, False))
    m = MaterialFile.load(path)
    assert m.scene_path is None
    with pytest.raises(MaterialFileError, match="no 'prepare'"):
        m.prepare
    path.write_bytes(fuzz._zip_of(_material_members(), False))
    m = MaterialFile.load(path)
    assert m.scene_path == Path("/tmp/scene.ply") and m.prepare["grid_res"] == 32
