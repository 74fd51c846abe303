"""Every option is checked where it enters, and every refusal is one stderr line.

Most cases fail in click's parsing, before any heavy import, so CliRunner runs them in
milliseconds: the scene and video arguments exist but are never read. A few run a tiny
bake (no progress bar before an error, no warnings), one a subprocess (SIGTERM).
"""
from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main

import cli as _cli_module

ROOT = Path(_cli_module.__file__).resolve().parent  # the checkout whose cli.py is under test

NON_FINITE = ["nan", "inf", "-inf"]
BOX_BAD = ["nan,0,0,1,1,1", "0,0,0,inf,1,1", "0,0,0,1,1,0", "0,0,0,-1,1,1", "1,2,3", "0,0,0,1,1,1,1"]
VEC_BAD = ["nan,0,0", "0,inf,0", "0,0,-inf", "1,2", "a,b,c", "1e10,0,0"]
COLOUR_BAD = ["nan,1,1", "1,inf,1", "2,2,2", "-0.1,0,0", "1,1"]
FPS_BAD = NON_FINITE + ["0", "0.5", "1e6", "-30"]
SEED_BAD = ["-1", "4294967296", "18446744073709551616", "nan", "1.5"]
MINUTES_BAD = NON_FINITE + ["0", "-1"]

# the options every command that prepares a scene shares (fit, bake, select)
PREPARE = [
    ("--foreground-box", BOX_BAD),
    ("--static-box", BOX_BAD),
    ("--min-opacity", NON_FINITE + ["-0.1", "1.1"]),
    ("--static-below", NON_FINITE + ["1e10", "-1e10"]),
    ("--meters-per-unit", NON_FINITE + ["0", "-1", "1e-30", "1e300", "1e7"]),
]

# command -> (arguments that reach option parsing, [(option, bad values)])
CASES = {
    "render": (["{scene}", "-o", "{tmp}/r.png"], [
        ("--width", ["7", "8193", "nan", "1e3"]),
        ("--height", ["0", "9000"]),
        ("--background", COLOUR_BAD),
        ("--fps", FPS_BAD),
    ]),
    "generate": (["{scene}", "--model", "{tmp}", "-o", "{tmp}/gen"], [
        ("--width", ["7", "8193"]),
        ("--height", ["7", "8193"]),
        ("--frames", ["2", "1025"]),
        ("--motion-bucket", ["-1", "256"]),
        ("--seed", SEED_BAD),
        ("--count", ["0", "65"]),
        ("--steps", ["0", "1001"]),
        ("--fps", FPS_BAD),
        ("--max-camera-motion", NON_FINITE + ["-1", "101"]),
        ("--static-below", NON_FINITE),
        ("--static-box", BOX_BAD),
        ("--background", COLOUR_BAD),
    ]),
    "fit": (["{scene}", "{tmp}"], [
        ("--fps", FPS_BAD),
        ("--velocity-iters", ["-1", "10001"]),
        ("--material-iters", ["-1", "10001"]),
        ("--rounds", ["0", "21"]),
        ("--horizon", ["-1", "1025"]),
        ("--polish", ["-1", "10001"]),
        ("--keep-best", ["-1", "10001"]),
        ("--diffusion", NON_FINITE + ["-0.1", "11"]),
        ("--working-size", ["15", "4097"]),
        ("--init-e", NON_FINITE + ["0", "999", "1e9"]),
        ("--nu", NON_FINITE + ["-0.1", "0.5"]),
        ("--density", NON_FINITE + ["0", "1e6"]),
        ("--background", COLOUR_BAD),
        ("--seed", SEED_BAD),
        ("--max-minutes", MINUTES_BAD),
        *PREPARE,
    ]),
    "bake": (["{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1"], [
        ("--force", VEC_BAD),
        ("--at", VEC_BAD),
        ("--radius", NON_FINITE + ["0", "-1"]),
        ("--box", BOX_BAD),
        ("--start", NON_FINITE + ["-1", "601"]),
        ("--duration", NON_FINITE + ["0", "-1", "601"]),
        ("--seconds", NON_FINITE + ["0", "-1", "601", "1e9"]),
        ("--frames", ["0", "600002", "100000000", "nan"]),
        ("--fps", FPS_BAD),
        ("--substeps", ["0", "5001", "100000"]),
        ("--seed", SEED_BAD),
        ("--max-minutes", MINUTES_BAD),
        *PREPARE,
    ]),
    "select": (["{scene}", "-o", "{tmp}/s.ply"], [
        ("--grid-res", ["9", "257", "512"]),
        *PREPARE,
    ]),
}


def _expand():
    for command, (base, options) in CASES.items():
        for option, values in options:
            for value in values:
                yield pytest.param(command, base, option, value, id=f"{command} {option} {value}")


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    # exists (click checks that) but is never read: every case fails before loading
    p = tmp_path / "scene.ply"
    p.write_bytes(b"not read")
    return p


def _run(args: list[str], env: dict | None = None):
    return CliRunner().invoke(main, args, env=env)


def _one_error_line(res) -> str:
    """The single stderr line of a refusal (exit 2, nothing on stdout, no traceback)."""
    assert res.exit_code == 2, (res.exit_code, res.stdout, res.stderr)
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), res.stderr
    assert "Traceback" not in res.stderr and res.stdout == "", (res.stdout, res.stderr)
    return lines[0]


@pytest.mark.parametrize("command,base,option,value", list(_expand()))
def test_bad_option_value_is_one_line_naming_the_option(command, base, option, value, scene, tmp_path) -> None:
    args = [a.format(scene=scene, tmp=tmp_path) for a in base]
    line = _one_error_line(_run([command, *args, f"{option}={value}"]))
    assert option in line, line
    assert not (tmp_path / "o.usd").exists() and not (tmp_path / "r.png").exists()


@pytest.mark.parametrize("args,needle", [
    (["render", "{scene}", "-o", "{tmp}/x.jpg"], "--out"),
    (["select", "{scene}", "-o", "{tmp}/s.ply", "--png", "{tmp}/x.jpg"], "--png"),
    (["select", "{scene}", "-o", "{tmp}/s.png"], "--out"),
    (["bake", "{tmp}/x.abc", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1"], "OUT"),
    (["bake", "{tmp}/x.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1",
      "--preview", "{tmp}/p.avi"], "--preview"),
    (["fit", "{scene}", "{tmp}", "-o", "{tmp}/m.json"], "--out"),
    (["blender-addon", "--zip", "{tmp}/a.tar"], "--zip"),
    (["render", "{scene}", "-o", "{tmp}/a\nb.png"], "--out"),
    (["render", "{scene}", "-o", "{tmp}/a\tb.png"], "--out"),
    (["bake", "{tmp}/" + "x" * 300 + ".usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1"], "OUT"),
    (["render", "{scene}", "-o", "{tmp}/" + "é" * 126 + ".png"], "--out"),  # 256 bytes
    (["demo", "--out", "{tmp}/new\nline"], "--out"),
    (["render", "{scene}", "-o", "{tmp}/r.png", "--write-camera", "{tmp}/c\r"], "--write-camera"),
])
def test_output_names_are_checked(args, needle, scene, tmp_path) -> None:
    line = _one_error_line(_run([a.format(scene=scene, tmp=tmp_path) for a in args]))
    assert needle in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.ply"], "something was written"


def test_name_check_allows_the_longest_name_that_fits(tmp_path) -> None:
    from pd_tool.core.atomic import atomic_output
    from pd_tool.cli_types import check_name

    ok = tmp_path / ("x" * 251 + ".usd")  # 255 bytes: the writers shorten it inside their temporaries
    assert check_name(ok) is None
    with atomic_output(ok) as tmp:
        tmp.write_bytes(b"usd")
    assert ok.read_bytes() == b"usd"
    assert check_name(tmp_path / ("x" * 252 + ".usd")) is not None
    assert check_name(tmp_path / ("d" * 255), directory=True) is None
    assert check_name(tmp_path / ("d" * 256), directory=True) is not None


@pytest.mark.parametrize("args,needle", [
    (["bake", "{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower"], "--force"),  # missing option
    (["bake", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1"], "OUT"),  # missing argument
    (["bake", "{tmp}/o.usd", "--bogus"], "--bogus"),  # unknown option
    (["render", "{scene}", "-o", "{tmp}/r.png", "--up", "sideways"], "--up"),  # bad choice
    (["render", "{tmp}/missing.ply", "-o", "{tmp}/r.png"], "missing.ply"),  # no such file
    (["bogus-command"], "bogus-command"),
    (["bake", "{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--material", "{scene}",
      "--force", "0,0,1"], "--material"),  # exclusive options
    (["bake", "{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1",
      "--seconds", "1", "--frames", "5"], "--frames"),
    (["bake", "{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1",
      "--frames", "600001", "--fps", "1"], "--frames"),  # in range alone, ten days of animation at 1 fps
    (["bake", "{tmp}/o.usd", "--scene", "{scene}", "--preset", "flower", "--force", "0,0,1",
      "--seconds", "1", "--start", "1"], "--start"),  # a force after the end pushes nothing
    (["generate", "{scene}", "--model", "{tmp}", "-o", "{tmp}/g", "--seed", "4294967295", "--count", "2"], "--seed"),
    (["blender-addon"], "--zip"),
])
def test_usage_errors_are_one_line(args, needle, scene, tmp_path) -> None:
    line = _one_error_line(_run([a.format(scene=scene, tmp=tmp_path) for a in args]))
    assert needle in line, line


def test_help_shows_the_ranges() -> None:
    res = _run(["bake", "--help"])
    assert res.exit_code == 0
    text = " ".join(res.stdout.split())
    for rng in ("1<=x<=1000", "0<x<=600", "1<=x<=5000", "0<=x<=4294967295", "1e-06<=x<=1e+06"):
        assert rng in text, rng
    bare = _run([])
    assert bare.exit_code == 0 and "Usage: pdtool" in bare.stdout and bare.stderr == ""


# ----------------------------------------------------------------------------- runs that start
@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    return save_splats(make_plant(600, seed=0), tmp_path_factory.mktemp("plant") / "plant.ply")


def test_render_fps_nan_writes_no_invalid_json(plant, tmp_path) -> None:
    """A real scene: the refusal comes before the render and the camera.json with "fps": NaN."""
    _one_error_line(_run(["render", str(plant), "-o", str(tmp_path / "r.png"), "--fps", "nan", "--width", "16",
                          "--height", "16", "--device", "cpu", "--write-camera", str(tmp_path / "cam")]))
    assert not (tmp_path / "cam").exists() and not (tmp_path / "r.png").exists()


def _bake_args(plant: Path, out: Path, *extra: str) -> list[str]:
    return ["bake", str(out), "--scene", str(plant), "--preset", "flower", "--quality", "draft",
            "--device", "cpu", *extra]


def test_no_bar_before_an_error_found_before_the_first_frame(plant, tmp_path) -> None:
    """A force aimed at nothing is found after preparation: no bar line comes first."""
    out = tmp_path / "x.usd"
    line = _one_error_line(_run(_bake_args(plant, out, "--force", "1,0,0", "--at", "5,5,5", "--radius", "0.1",
                                           "--frames", "3")))
    assert "holds no free particle" in line
    assert not out.exists()


def test_no_bar_before_an_error_found_during_the_simulation(plant, tmp_path) -> None:
    """The per-frame guard stops the run after frames were written: still one line."""
    out = tmp_path / "x.usd"
    line = _one_error_line(_run(["bake", str(out), "--scene", str(plant), "--preset", "jelly", "--quality", "draft",
                                 "--device", "cpu", "--force", "0,0,40", "--seconds", "1"]))
    assert "unstable" in line and "frame" in line, line
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_lazy_bar_appears_on_first_update_and_is_erased_after_an_error(monkeypatch, capsys) -> None:
    import cli

    monkeypatch.setenv("PDTOOL_PROGRESS", "1")
    bar = cli.LazyBar("bake", "frame")
    assert capsys.readouterr().err == ""  # nothing until the first update
    bar.update_to(1, 4)
    assert "bake" in capsys.readouterr().err  # tqdm draws the bar when it starts
    bar.update_to(2, 4)
    bar.close(ok=False)
    tail = capsys.readouterr().err
    # erased: spaces over the bar, the cursor back at the line's start, no newline left
    assert "\n" not in tail and tail.split("\r")[-1].strip() == "" and tail.strip() == ""
    monkeypatch.setenv("PDTOOL_PROGRESS", "0")
    quiet = cli.LazyBar("bake", "frame")
    quiet.update_to(1, 4)
    quiet.close()
    assert capsys.readouterr().err == ""


def test_normal_bake_prints_nothing_on_stderr_and_no_warning(plant, tmp_path) -> None:
    out = tmp_path / "ok.usd"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = _run(_bake_args(plant, out, "--force", "0,0,1", "--frames", "4", "--static-below", "0.2"))
    assert res.exit_code == 0, (res.stdout, res.stderr, res.exception)
    assert res.stderr == "", res.stderr
    assert out.is_file() and "work estimate up to" in res.stdout


def test_zero_size_gaussian_names_the_scene_file(plant, tmp_path) -> None:
    from plyfile import PlyData, PlyElement

    v = PlyData.read(str(plant))["vertex"].data.copy()
    v["scale_0"][7] = -200.0  # exp underflows to 0 in float32
    bad = tmp_path / "flat.ply"
    PlyData([PlyElement.describe(v, "vertex")]).write(str(bad))
    line = _one_error_line(_run(_bake_args(bad, tmp_path / "x.usd", "--force", "0,0,1", "--frames", "3")))
    assert "flat.ply" in line and "index 7" in line and "exp(log_scales)" not in line, line


# ----------------------------------------------------------------------------- OS errors, signals
def test_temporary_names_become_the_users_file() -> None:
    import cli

    assert cli.untemp("/a/b/.out.usd.tmp-1234-deadbeef.usdc: not a readable USD file") == "/a/b/out.usd: not a " \
                                                                                           "readable USD file"
    assert cli.untemp("write .x.png.k2j3h4g5.part.png failed") == "write x.png failed"
    assert cli.user_file("/d/.frames.ab12cd34.part") == "/d/frames"
    assert cli.untemp("a .hidden file stays") == "a .hidden file stays"


def _read_only_folder(tmp_path: Path):
    """A read-only tmpfs at tmp_path/ro when this test may mount (root), else None."""
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() != 0:
        return None
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(ro)], capture_output=True)
    return ro if r.returncode == 0 else None


def test_os_error_on_write_is_one_line_naming_the_users_file(plant, tmp_path, monkeypatch) -> None:
    out = tmp_path / "ro" / "view.png"
    ro = _read_only_folder(tmp_path)
    try:
        if ro is None:  # cannot mount here: the same error, injected where the PNG is written
            import pd_tool.render.preview

            def full(path, image):
                raise OSError(errno.EROFS, "Read-only file system", str(Path(path).parent / ".view.png.abcd1234.part.png"))

            monkeypatch.setattr(pd_tool.render.preview, "save_png", full)
        line = _one_error_line(_run(["render", str(plant), "-o", str(out), "--width", "16", "--height", "16",
                                     "--device", "cpu"]))
    finally:
        if ro is not None:
            subprocess.run(["umount", str(ro)], check=True)
    assert str(out) in line and "read-only" in line.lower() and ".part" not in line, line


def test_user_errors_maps_full_disk_to_one_line() -> None:
    import cli

    with pytest.raises(cli.InputError) as e:
        with cli.user_errors():
            raise OSError(errno.ENOSPC, "No space left on device", "/data/.out.usd.tmp-77-0badc0de.usdc")
    assert e.value.format_message() == "/data/out.usd: the disk is full; free some space or write to another disk"
    with pytest.raises(KeyError):  # anything else is a bug: it keeps its traceback
        with cli.user_errors():
            raise KeyError("x")


def test_sigterm_ends_a_bake_with_one_line_and_no_temporaries(plant, tmp_path) -> None:
    """SIGTERM (what `kill`, batch schedulers and the Blender add-on's cancel send) runs the
    same cleanup as Ctrl-C: exit 143, one line, no output and no hidden temporary left."""
    out = tmp_path / "long.usd"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PDTOOL_PROGRESS": "0", "OMP_NUM_THREADS": "1",
           "PDTOOL_SKIP_WORK_CHECK": "1"}  # a long bake on purpose: it is stopped in its frame loop
    proc = subprocess.Popen([sys.executable, "-c", "from cli import main; main()", *_bake_args(
        plant, out, "--force", "0,0,1", "--fps", "100", "--seconds", "60", "--substeps", "2000")],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while time.time() < deadline and not any(p.name.startswith(".long.usd") for p in tmp_path.iterdir()):
        if proc.poll() is not None:
            break
        time.sleep(0.1)
    assert proc.poll() is None, proc.communicate()
    time.sleep(0.5)  # into the frame loop
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, (proc.returncode, stderr)
    lines = stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: stopped by SIGTERM"), stderr
    assert not out.exists()
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
