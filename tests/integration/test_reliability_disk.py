"""Every writer on a full, nearly full or read-only destination: one `Error:` line naming
the user's path (never a temporary), exit code 2, no traceback, nothing left behind.

The destinations are real tmpfs mounts when the tests run as root and mounting works:
"full" has no block left, "tight" has 8 KiB (the write fails part way), "read-only" is
mounted ro. Otherwise an injected OSError stands in: pd_tool.core.atomic.destination_problem
reports the errno for paths in the folder, so the writers refuse up front; the write-time
conversion is then covered by the injected errors of the library tests at the end."""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from _cli import invoke, refusal_line

from pd_tool.core.atomic import atomic_output
from pd_tool.core.errors import OutputError

POT_TOP = "0.2"
BAKE = ["--preset", "flower", "--force", "0,0,1", "--frames", "4", "--quality", "draft", "--device", "cpu"]
REASON = {"full": "No space left on device", "tight": "No space left on device", "read-only": "Read-only file system"}
FIX = "free some space or choose a writable folder"


def _mountable() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("mount") is not None


@contextlib.contextmanager
def _tmpfs(where: Path, options: str):
    """Mount a tmpfs at `where` (True) or say it could not (False); always unmounted."""
    where.mkdir(parents=True, exist_ok=True)
    if not _mountable():
        yield False
        return
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True)
    if r.returncode != 0:
        yield False
        return
    try:
        yield True
    finally:
        subprocess.run(["umount", str(where)], capture_output=True)
        if os.path.ismount(where):
            subprocess.run(["umount", "-l", str(where)], capture_output=True)


def _fill(folder: Path, leave: int) -> None:
    """Fill a tmpfs until `leave` bytes of blocks are free."""
    with open(folder / "filler", "wb") as fh:
        while True:
            st = os.statvfs(folder)
            free = st.f_bavail * st.f_frsize
            if free <= leave:
                break
            try:
                fh.write(b"\0" * min(4096, free - leave))
                fh.flush()
            except OSError:
                break


@pytest.fixture(params=["full", "tight", "read-only"])
def dest(request, tmp_path: Path, monkeypatch):
    """(kind, folder): a destination where writes fail."""
    kind = request.param
    where = tmp_path / "dest"
    options = {"full": "size=64k", "tight": "size=64k", "read-only": "ro,size=64k"}[kind]
    with _tmpfs(where, options) as mounted:
        if mounted:
            if kind != "read-only":
                _fill(where, 0 if kind == "full" else 8192)
        else:
            from pd_tool.core import atomic

            code = errno.EROFS if kind == "read-only" else errno.ENOSPC
            real = atomic.destination_problem

            def injected(path):
                p = Path(os.path.abspath(path))
                return code if where == p or where in p.parents else real(path)

            monkeypatch.setattr(atomic, "destination_problem", injected)
        yield kind, where


def _check(res, kind: str, folder: Path, named: str, bar: bool = False) -> None:
    line = refusal_line(res, bar=bar)
    if named.endswith("*"):  # the fit's checkpoint or its material file, whichever comes first
        assert line.startswith(f"Error: cannot write {named[:-1]}"), line
        assert line.endswith(f": {REASON[kind]}; {FIX}"), line
    else:
        assert line == f"Error: cannot write {named}: {REASON[kind]}; {FIX}", line
    left = sorted(p.name for p in folder.rglob("*") if p.name != "filler")
    assert left == [], left  # no temporaries (.*.part*, .*.tmp-*, .*.old) and no partial output


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    return save_splats(make_plant(300, seed=0), tmp_path_factory.mktemp("plant") / "plant.ply")


def test_render_png(plant, dest, tmp_path):
    kind, d = dest
    _check(invoke(["render", plant, "-o", "dest/x.png"], tmp_path), kind, d, "dest/x.png")


@pytest.mark.parametrize("dest", ["full", "read-only"], indirect=True)  # camera.json fits in 8 KiB
def test_render_write_camera(plant, dest, tmp_path):
    kind, d = dest
    res = invoke(["render", plant, "-o", "x.png", "--width", "32", "--height", "32", "--write-camera", "dest"],
               tmp_path)
    # refused before rendering: the PNG is not written either
    assert res.stdout == "" and not (tmp_path / "x.png").exists()
    _check(res, kind, d, "dest/camera.json")


def test_select_ply(plant, dest, tmp_path):
    kind, d = dest
    _check(invoke(["select", plant, "-o", "dest/s.ply"], tmp_path), kind, d, "dest/s.ply")


def test_select_png(plant, dest, tmp_path):
    kind, d = dest
    _check(invoke(["select", plant, "-o", "s.ply", "--png", "dest/s.png"], tmp_path), kind, d, "dest/s.png")
    if kind != "tight":  # both destinations are checked before either is written (a tight disk fills later)
        assert not (tmp_path / "s.ply").exists()


def test_blender_addon_zip(dest, tmp_path):
    kind, d = dest
    _check(invoke(["blender-addon", "--zip", "dest/a.zip"], tmp_path), kind, d, "dest/a.zip")


def test_blender_addon_install(dest, tmp_path):
    kind, d = dest
    _check(invoke(["blender-addon", "--install-to", "dest/addons"], tmp_path), kind, d, "dest/addons/pdtool_blender")


def test_bake_usd(plant, dest, tmp_path):
    kind, d = dest
    _check(invoke(["bake", "--scene", plant, *BAKE, "dest/o.usd"], tmp_path), kind, d, "dest/o.usd", bar=True)


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_bake_preview(plant, dest, tmp_path, suffix):
    kind, d = dest
    frames = ["--frames", "24"] if suffix == ".mp4" else []  # 4 frames of H.264 fit in 8 KiB, 24 do not
    res = invoke(["bake", "--scene", plant, *BAKE, *frames, "o.usd", "--preview", f"dest/p{suffix}"], tmp_path)
    _check(res, kind, d, f"dest/p{suffix}", bar=True)


def test_bake_frames_out(plant, dest, tmp_path):
    kind, d = dest
    res = invoke(["bake", "--scene", plant, *BAKE, "o.usd", "--frames-out", "dest/frames"], tmp_path)
    _check(res, kind, d, "dest/frames", bar=True)


FIT = ["--quality", "draft", "--velocity-iters", "1", "--material-iters", "1", "--working-size", "24",
       "--static-below", POT_TOP, "--device", "cpu", "--no-preview"]


def test_fit_material(fit_dir, dest, tmp_path):
    kind, d = dest
    res = invoke(["fit", fit_dir / "plant.ply", fit_dir / "video", "-o", "dest/f.pdmat", *FIT], tmp_path)
    _check(res, kind, d, "dest/f.pdmat*", bar=True)


@pytest.mark.parametrize("dest", ["full", "read-only"], indirect=True)  # the record fits in 8 KiB
def test_fit_record(fit_dir, dest, tmp_path):
    """The working folder (where .pdtool/last-fit.json goes) is the bad one."""
    kind, d = dest
    res = invoke(["fit", fit_dir / "plant.ply", fit_dir / "video", "-o", tmp_path / "f.pdmat", *FIT], d)
    _check(res, kind, d, ".pdtool/last-fit.json", bar=True)


# ----------------------------------------------------------------------------- library, injected errors


@pytest.mark.parametrize("code", [errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EDQUOT, errno.EFBIG, errno.EPERM,
                                  errno.ENAMETOOLONG, errno.ENOTDIR, errno.ENOENT])
def test_atomic_output_turns_write_errors_into_one_line(tmp_path: Path, code: int) -> None:
    target = tmp_path / "out.png"
    target.write_text("old")
    with pytest.raises(OutputError) as e:
        with atomic_output(target) as tmp:
            tmp.write_text("half")
            raise OSError(code, os.strerror(code), str(tmp))
    fix = {errno.ENAMETOOLONG: "choose a shorter name",
           errno.ENOTDIR: "check that the output folder exists and is a folder, not a file",
           errno.ENOENT: "check that the output folder exists and is a folder, not a file"}.get(code, FIX)
    assert str(e.value) == f"cannot write {target}: {os.strerror(code)}; {fix}"
    assert isinstance(e.value, OSError)  # still an OSError for code that handles those
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out.png"]


def test_atomic_output_errors_outside_the_body(tmp_path: Path, monkeypatch) -> None:
    import tempfile

    def ro(*a, **k):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS))

    monkeypatch.setattr(tempfile, "mkstemp", ro)
    with pytest.raises(OutputError, match=r"cannot write .*x\.json: Read-only file system"):
        with atomic_output(tmp_path / "x.json") as tmp:
            tmp.write_text("{}")
    monkeypatch.undo()
    real = os.replace

    def full(src, dst):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OutputError, match="No space left on device"):
        with atomic_output(tmp_path / "frames", directory=True) as tmp:
            (tmp / "f.png").write_text("x")
    monkeypatch.setattr(os, "replace", real)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="file is a file, not a folder; choose a folder$"):
        with atomic_output(tmp_path / "file" / "x.json") as tmp:
            pass


def test_errors_that_are_not_write_errors_pass_through(tmp_path: Path) -> None:
    from pd_tool.core.errors import PdToolError

    with pytest.raises(ValueError):
        with atomic_output(tmp_path / "x.json"):
            raise ValueError("a bug, not the disk")
    with pytest.raises(PdToolError, match="bad frames"):
        with atomic_output(tmp_path / "x.json"):
            raise PdToolError("bad frames")
    assert list(tmp_path.iterdir()) == []


def test_a_failing_encoder_is_one_line_and_quiet(tmp_path: Path, monkeypatch, capfd) -> None:
    """ffmpeg's own error output goes to pdtool, not to the terminal; its exit status is read."""
    from pd_tool.render.preview import PreviewError, write_preview

    frames = [np.zeros((16, 16, 3), np.uint8)] * 3
    script = tmp_path / "fake-ffmpeg"
    for message, expected in (("No space left on device", OutputError), ("Unknown encoder 'libx264'", PreviewError)):
        script.write_text(f"#!/bin/sh\ncat > /dev/null\necho \"[out] {message}\" >&2\nexit 1\n")
        script.chmod(0o755)
        monkeypatch.setattr("pd_tool.render.preview.ffmpeg_exe", lambda: str(script))
        with pytest.raises(expected) as e:
            write_preview(frames, tmp_path / "out" / "p.mp4", 10)
        assert "\n" not in str(e.value) and "out/p.mp4" in str(e.value)
        if expected is PreviewError:
            assert message in str(e.value)
    assert not (tmp_path / "out").exists()  # nothing left, not even the folder made for it
    assert capfd.readouterr().err == ""

