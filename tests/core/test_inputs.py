"""Small files from elsewhere: only a regular file of bounded size is read."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from pd_tool.core.cameras import load_cameras
from pd_tool.core.errors import CameraError, MaterialFileError, PdToolError
from pd_tool.core.inputs import read_small_file


def test_regular_file_within_the_limit_is_read(tmp_path: Path) -> None:
    p = tmp_path / "a.json"
    p.write_bytes(b"x" * 10)
    assert read_small_file(p, limit=10, error=PdToolError, fix="fix") == b"x" * 10
    with pytest.raises(PdToolError, match=r"a.json: is larger than .* MiB.*; fix$"):
        read_small_file(p, limit=9, error=PdToolError, fix="fix")


def test_pipe_device_folder_and_missing_file_are_one_line(tmp_path: Path) -> None:
    fifo = tmp_path / "cameras.json"
    os.mkfifo(fifo)  # opening it would block until a writer comes
    with pytest.raises(CameraError, match="is not a regular file"):
        load_cameras(fifo)
    with pytest.raises(CameraError, match="is not a regular file"):
        load_cameras("/dev/zero")  # would never end
    with pytest.raises(MaterialFileError, match="no such file"):
        read_small_file(tmp_path / "gone.json", limit=10, error=MaterialFileError, fix="fix")


def test_cli_camera_from_a_device_is_one_line(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cli import main
    from pd_tool.io import save_ply
    from pd_tool.io.synthetic import make_plant

    scene = save_ply(make_plant(200, seed=0), tmp_path / "p.ply")
    res = CliRunner().invoke(main, ["render", str(scene), "--camera", "/dev/zero", "-o", str(tmp_path / "v.png")])
    assert res.exit_code == 2, res.output
    assert res.stderr.splitlines() == ["Error: /dev/zero: is not a regular file (a pipe or a device?); pass a "
                                       "cameras.json, transforms.json or camera.json file"]
    assert not (tmp_path / "v.png").exists()


def test_a_huge_preset_file_is_one_line(tmp_path: Path) -> None:
    from pd_tool.core.errors import PresetError
    from pd_tool.materials.presets import load_preset

    big = tmp_path / "q.toml"
    big.write_text("# " + "x" * (2 << 20) + "\ngrid_res = 16\n")
    with pytest.raises(PresetError, match="q.toml: is larger than 1 MiB"):
        load_preset("quality", big)


def test_a_device_as_the_reference_video_is_one_line() -> None:
    from pd_tool.core.errors import VideoError
    from pd_tool.video.folder import load_reference_video

    with pytest.raises(VideoError, match="/dev/zero: is not a regular file or a folder"):
        load_reference_video("/dev/zero")
