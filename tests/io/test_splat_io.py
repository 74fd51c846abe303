"""Splat I/O: real captures, lossless round trips, .splat quantisation, clear errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pd_tool.core.errors import PlyFormatError, SplatFormatError
from pd_tool.io import load_splats, save_splats
from pd_tool.io.ply import load_ply, save_ply
from pd_tool.io.synthetic import make_plant

ACTIVATED = ("positions", "quats", "scales", "opacities", "sh")


def assert_same_scene(a, b) -> None:
    for name in ACTIVATED:
        ta, tb = getattr(a, name), getattr(b, name)
        assert ta.shape == tb.shape, name
        assert torch.equal(ta, tb), f"{name} differs after round trip"


@pytest.mark.parametrize("name,count,degree", [("udon.ply", 2153, 3), ("donut_fused.ply", 45624, 0)])
def test_real_captures_load(shared_data: Path, name: str, count: int, degree: int) -> None:
    scene = load_splats(shared_data / name)
    assert scene.count == count
    assert scene.sh_degree == degree
    assert scene.sh.shape == (count, (degree + 1) ** 2, 3)
    norms = scene.quats.norm(dim=1)
    assert torch.allclose(norms, torch.ones_like(norms), atol=1e-5)
    assert (scene.opacities > 0).all() and (scene.opacities < 1.0 + 1e-6).all()
    assert (scene.scales > 0).all()


@pytest.mark.parametrize("name", ["udon.ply", "donut_fused.ply"])
def test_real_round_trip_is_bit_identical(shared_data: Path, tmp_path: Path, name: str) -> None:
    src = load_splats(shared_data / name)
    out = save_splats(src, tmp_path / name)
    back = load_splats(out)
    assert back.raw.dtype == src.raw.dtype
    assert back.raw.tobytes() == src.raw.tobytes()
    assert_same_scene(src, back)


def test_udon_f_rest_grouped_by_channel(shared_data: Path) -> None:
    # INRIA stores all R coefficients, then G, then B: coefficient 1 of G is f_rest_16 for degree 3
    scene = load_splats(shared_data / "udon.ply")
    raw = scene.raw
    assert np.float32(scene.sh[5, 1, 1].item()) == raw["f_rest_15"][5]
    assert np.float32(scene.sh[5, 2, 2].item()) == raw["f_rest_31"][5]
    assert np.float32(scene.sh[5, 0, 0].item()) == raw["f_dc_0"][5]


@pytest.mark.parametrize("text,byte_order", [(True, "<"), (False, ">")])
def test_ascii_and_big_endian_round_trip(shared_data: Path, tmp_path: Path, text: bool, byte_order: str) -> None:
    src = load_splats(shared_data / "udon.ply")
    path = save_ply(src, tmp_path / "u.ply", text=text, byte_order=byte_order)
    back = load_ply(path)
    assert back.source_format == ("ply-ascii" if text else "ply-binary-be")
    for name in src.raw.dtype.names:
        np.testing.assert_array_equal(back.raw[name], src.raw[name], err_msg=name)
    assert_same_scene(src, back)


def test_synthetic_plant_round_trip(tmp_path: Path) -> None:
    plant = make_plant(1500, seed=3, sh_degree=1)
    first = load_splats(save_splats(plant, tmp_path / "plant.ply"))
    # a scene built in memory is written from activated values: equal up to float32 log/exp
    for name in ACTIVATED:
        torch.testing.assert_close(getattr(first, name), getattr(plant, name), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(first.labels, plant.labels)
    assert first.label_names == plant.label_names == ("pot", "stem", "leaf", "flower")
    # from then on the raw records make it exact
    second = load_splats(save_splats(first, tmp_path / "plant2.ply"))
    assert second.raw.tobytes() == first.raw.tobytes()
    assert_same_scene(first, second)
    assert second.label_names == plant.label_names


@pytest.mark.parametrize("comment, expect", [
    ("pdtool region_names pot,stem,leaf,flower", ("pot", "stem", "leaf", "flower")),
    ("pdtool region_names pot,stem", ()),  # fewer names than the labels use
    ("pdtool region_names pot,st em,leaf,flower", ()),  # not a plain name
    ("pdtool region_names " + ",".join(["x" * 65] * 4), ()),  # too long
    ("something else", ()),
])
def test_region_names_come_from_a_checked_header_comment(tmp_path: Path, comment: str, expect: tuple) -> None:
    from plyfile import PlyData

    path = save_splats(make_plant(300, seed=0), tmp_path / "p.ply")
    ply = PlyData.read(str(path))
    ply.comments = [c for c in ply.comments if not c.startswith("pdtool region_names")] + [comment]
    ply.write(str(tmp_path / "q.ply"))
    assert load_ply(tmp_path / "q.ply").label_names == expect


def test_extra_properties_kept(tmp_path: Path) -> None:
    from plyfile import PlyData, PlyElement

    plant = make_plant(200, seed=0)
    path = save_splats(plant, tmp_path / "p.ply")
    data = PlyData.read(str(path))["vertex"].data
    dtype = data.dtype.descr + [("segment_id", "<u2")]
    rec = np.zeros(len(data), dtype=dtype)
    for n in data.dtype.names:
        rec[n] = data[n]
    rec["segment_id"] = np.arange(len(data)) % 7
    PlyData([PlyElement.describe(rec, "vertex")]).write(str(tmp_path / "x.ply"))
    scene = load_splats(tmp_path / "x.ply")
    assert "segment_id" in scene.extra
    back = load_splats(save_splats(scene, tmp_path / "y.ply"))
    np.testing.assert_array_equal(back.raw["segment_id"], rec["segment_id"])


def test_splat_round_trip_within_quantisation(tmp_path: Path) -> None:
    plant = make_plant(800, seed=1)
    back = load_splats(save_splats(plant, tmp_path / "p.splat"))
    assert back.count == plant.count and back.source_format == "splat"
    torch.testing.assert_close(back.positions, plant.positions, rtol=0, atol=0)
    torch.testing.assert_close(back.scales, plant.scales, rtol=0, atol=0)
    # colour and opacity: uint8, half a step of 1/255
    assert (back.colors - plant.colors).abs().max() <= 0.5 / 255 + 1e-6
    assert (back.opacities - plant.opacities).abs().max() <= 0.5 / 255 + 1e-6
    # rotation: each component within half a step of 1/128, then renormalised; compare up to sign
    dots = (back.quats * plant.quats).sum(1).abs()
    assert dots.min() > 1 - 2e-4


# ----------------------------------------------------------------------------- errors
def _write_bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def test_truncated_file(shared_data: Path, tmp_path: Path) -> None:
    data = (shared_data / "udon.ply").read_bytes()
    path = _write_bytes(tmp_path / "t.ply", data[: len(data) // 3])
    with pytest.raises(PlyFormatError, match="truncated"):
        load_splats(path)


def test_text_file_renamed_ply(tmp_path: Path) -> None:
    with pytest.raises(PlyFormatError, match="not a PLY file"):
        load_splats(_write_bytes(tmp_path / "notes.ply", b"shopping list\nmilk\n"))


def test_empty_file(tmp_path: Path) -> None:
    with pytest.raises(PlyFormatError, match="empty"):
        load_splats(_write_bytes(tmp_path / "e.ply", b""))
    with pytest.raises(SplatFormatError, match="empty"):
        load_splats(_write_bytes(tmp_path / "e.splat", b""))


def test_unknown_extension(tmp_path: Path) -> None:
    with pytest.raises(SplatFormatError, match="unknown extension"):
        load_splats(_write_bytes(tmp_path / "scene.obj", b"v 0 0 0\n"))


def _plant_records(n: int = 50):
    from pd_tool.io.ply import scene_to_records

    return scene_to_records(make_plant(max(n, 100), seed=0))[:n].copy()


def _write_records(path: Path, rec) -> Path:
    from plyfile import PlyData, PlyElement

    PlyData([PlyElement.describe(rec, "vertex")]).write(str(path))
    return path


@pytest.mark.parametrize(
    "field,value,match",
    [("scale_1", np.nan, "NaN/inf scale"), ("x", np.inf, "NaN/inf position"), ("opacity", np.nan, "NaN/inf opacity"),
     ("opacity", np.inf, "NaN/inf opacity"), ("opacity", -np.inf, "NaN/inf opacity"),
     ("scale_0", np.inf, "NaN/inf scale"), ("scale_2", -np.inf, "NaN/inf scale")],
)
def test_nan_values(tmp_path: Path, field: str, value: float, match: str) -> None:
    rec = _plant_records()
    rec[field][7] = value
    with pytest.raises(PlyFormatError, match=match):
        load_splats(_write_records(tmp_path / "nan.ply", rec))


def test_zero_quaternion(tmp_path: Path) -> None:
    rec = _plant_records()
    for i in range(4):
        rec[f"rot_{i}"][3] = 0.0
    with pytest.raises(PlyFormatError, match="zero-length rotation"):
        load_splats(_write_records(tmp_path / "q.ply", rec))


def test_missing_property(tmp_path: Path) -> None:
    import numpy.lib.recfunctions as rfn

    rec = rfn.drop_fields(_plant_records(), "scale_2", usemask=False)
    with pytest.raises(PlyFormatError, match="scale_2"):
        load_splats(_write_records(tmp_path / "m.ply", rec))


def test_wrong_sh_count(tmp_path: Path) -> None:
    import numpy.lib.recfunctions as rfn

    rec = rfn.append_fields(_plant_records(), ["f_rest_0", "f_rest_1"], [np.zeros(50), np.zeros(50)],
                            dtypes=["<f4", "<f4"], usemask=False)
    with pytest.raises(PlyFormatError, match="f_rest"):
        load_splats(_write_records(tmp_path / "sh.ply", rec))


def test_zero_gaussians(tmp_path: Path) -> None:
    with pytest.raises(PlyFormatError, match="0 Gaussians"):
        load_splats(_write_records(tmp_path / "z.ply", _plant_records()[:0]))


def test_splat_wrong_size(tmp_path: Path) -> None:
    with pytest.raises(SplatFormatError, match="multiple of 32"):
        load_splats(_write_bytes(tmp_path / "x.splat", b"\0" * 33))


def _undercount(data: bytes, n: int) -> bytes:
    head, body = data.split(b"end_header", 1)
    return head.replace(f"element vertex {n}".encode(), f"element vertex {n - 1}".encode()) + b"end_header" + body


@pytest.mark.parametrize("text,byte_order", [(False, "<"), (False, ">"), (True, "<")])
def test_header_that_undercounts_the_body_is_refused(tmp_path: Path, text: bool, byte_order: str) -> None:
    # plyfile reads the counted records only: the last Gaussian would vanish without a word
    path = save_ply(make_plant(100, seed=0), tmp_path / "ok.ply", text=text, byte_order=byte_order)
    assert load_ply(path).count == 100
    bad = _write_bytes(tmp_path / "under.ply", _undercount(path.read_bytes(), 100))
    with pytest.raises(PlyFormatError, match="99 vertex records"):
        load_ply(bad)


@pytest.mark.parametrize("text", [False, True])
def test_trailing_bytes_are_refused(tmp_path: Path, text: bool) -> None:
    path = save_ply(make_plant(100, seed=0), tmp_path / "ok.ply", text=text)
    tail = b"1 2 3\n" if text else b"\x00" * 5
    bad = _write_bytes(tmp_path / "tail.ply", path.read_bytes() + tail)
    with pytest.raises(PlyFormatError, match="export the splat again"):
        load_ply(bad)
    # blank lines after an ASCII body are layout, not data
    if text:
        assert load_ply(_write_bytes(tmp_path / "blank.ply", path.read_bytes() + b"\n\n")).count == 100


def test_pipe_named_like_a_scene_is_refused(tmp_path: Path) -> None:
    # opening a FIFO for reading blocks until a writer comes: the load must not hang
    import os

    fifo = tmp_path / "scene.ply"
    os.mkfifo(fifo)
    with pytest.raises(SplatFormatError, match="not a regular file"):
        load_splats(fifo)
