"""`pdtool info` through click and through the real console script."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli import main


@pytest.mark.parametrize("name,count,degree", [("udon.ply", 2153, 3), ("donut_fused.ply", 45624, 0)])
def test_info_json(shared_data: Path, name: str, count: int, degree: int) -> None:
    res = CliRunner().invoke(main, ["info", str(shared_data / name), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["count"] == count and data["sh_degree"] == degree and data["format"] == "ply-binary-le"
    assert np.all(np.array(data["bbox_min"]) <= np.array(data["robust_bbox_min"]))
    assert np.all(np.array(data["robust_bbox_max"]) <= np.array(data["bbox_max"]))


def test_info_text(shared_data: Path) -> None:
    res = CliRunner().invoke(main, ["info", str(shared_data / "udon.ply")])
    assert res.exit_code == 0
    assert "2,153" in res.stdout and "SH degree     3" in res.stdout


def _bad_files(shared_data: Path, tmp: Path) -> dict[str, Path]:
    data = (shared_data / "udon.ply").read_bytes()
    truncated = tmp / "truncated.ply"
    truncated.write_bytes(data[: len(data) // 2])
    text = tmp / "readme.ply"
    text.write_text("this is not a splat\n")
    # a NaN: patch the first x of the binary body
    body = data.index(b"end_header\n") + len(b"end_header\n")
    nan = bytearray(data)
    nan[body: body + 4] = np.array([np.nan], "<f4").tobytes()
    nanp = tmp / "nan.ply"
    nanp.write_bytes(bytes(nan))
    return {"truncated": truncated, "text": text, "nan": nanp}


def test_bad_files_exit_2_with_one_line(shared_data: Path, tmp_path: Path) -> None:
    # the installed console script, as a user runs it: stderr must be one line, no traceback
    exe = Path(sys.executable).with_name("pdtool")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "cli"]
    for kind, path in _bad_files(shared_data, tmp_path).items():
        proc = subprocess.run([*cmd, "info", str(path)], capture_output=True, text=True, env=dict(os.environ))
        assert proc.returncode == 2, (kind, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1, (kind, proc.stderr)
        assert lines[0].startswith("Error: ") and "Traceback" not in proc.stderr
        assert str(path) in lines[0]
