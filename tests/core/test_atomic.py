"""pd_tool.core.atomic.atomic_output: whole or absent, hidden temporaries, usual file modes,
folders replaced without a half-deleted moment (the SIGKILL tests are in
test_reliability_kill.py; what pdtool may replace is in test_reliability_outputs.py)."""
from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from pd_tool.core.atomic import MANIFEST, atomic_output


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def test_file_appears_whole_with_umask_mode(tmp_path: Path) -> None:
    umask = os.umask(0o022)
    try:
        with atomic_output(tmp_path / "a.json") as tmp:
            assert tmp.name.startswith(".a.json.") and tmp.parent == tmp_path  # hidden, same folder
            tmp.write_text("{}")
            assert not (tmp_path / "a.json").exists()  # nothing visible until the rename
    finally:
        os.umask(umask)
    assert (tmp_path / "a.json").read_text() == "{}"
    assert _mode(tmp_path / "a.json") == 0o644  # not mkstemp's 0600
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_error_keeps_the_old_file_and_removes_the_temporary(tmp_path: Path) -> None:
    (tmp_path / "a.txt").write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_output(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert (tmp_path / "a.txt").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def _pdtool_folder(path: Path, files: dict[str, str]) -> None:
    with atomic_output(path, directory=True) as tmp:
        for name, text in files.items():
            (tmp / name).write_text(text)


def _visible(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name != MANIFEST)


def test_folder_replaced_whole(tmp_path: Path) -> None:
    old = tmp_path / "frames"
    _pdtool_folder(old, {"f0.png": "old", "f1.png": "old"})
    with atomic_output(old, directory=True) as tmp:
        (tmp / "f0.png").write_text("new")
        # while the new folder is written, the old one is untouched
        assert _visible(old) == ["f0.png", "f1.png"]
    assert _visible(old) == ["f0.png"] and (old / "f0.png").read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["frames"]  # no hidden leftovers
    assert _mode(old) & 0o700 == 0o700


def test_folder_error_keeps_the_old_folder(tmp_path: Path) -> None:
    old = tmp_path / "frames"
    _pdtool_folder(old, {"f0.png": "old"})
    with pytest.raises(OSError):
        with atomic_output(old, directory=True) as tmp:
            (tmp / "f0.png").write_text("new")
            raise OSError("disk full")
    assert (old / "f0.png").read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["frames"]
