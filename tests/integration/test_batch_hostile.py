"""`pdtool batch` with a jobs file from elsewhere: confined outputs, normalised clashes, plain
templates, size/depth/count limits, help-asking jobs, the hidden temporaries it may remove and
a --json destination that cannot be written. All in-process, no worker starts: the jobs that
pass the checks go to a backend that records them instead of running them."""
from __future__ import annotations

import contextlib
import errno
import json
import os
import subprocess
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main
from pd_tool import batch as B
from cli import batch_parse, batch_run
from pd_tool.batch import CommandLines, FAILED, OK, JobsFileError, load_jobs, parse_jobs, run_batch, run_job

BAKE = ["--scene", "plant.ply", "--preset", "flower", "--force", "0,0,1"]


COMMANDS = CommandLines(parse=batch_parse, run=batch_run)


class Recorder:
    """A backend that records what it is given and reports every job ok without running it."""

    name = "recorder"

    def __init__(self) -> None:
        self.submitted: list[str] = []

    def submit(self, job, run):
        self.submitted.append(job.name)
        return job.name

    def wait(self, handles):
        return [(h, {"ok": True, "error": None, "seconds": 0.0, "log": []}) for h in list(handles)]

    def close(self, cancel=False, handles=()):
        pass


def _toml(jobs: list[dict]) -> str:
    out = []
    for j in jobs:
        out.append("[[job]]")
        for k, v in j.items():
            if k != "sweep":
                out.append(f"{k} = {json.dumps(v)}")
        if "sweep" in j:
            out.append("[job.sweep]")
            out += [f"{k} = {json.dumps(v)}" for k, v in j["sweep"].items()]
    return "\n".join(out) + "\n"


def _cli(args: list[str]):
    r = CliRunner().invoke(main, args)
    return r, [line for line in r.stderr.splitlines() if line.strip()]


def _one_error_line(r, lines: list[str], *words: str) -> str:
    assert r.exit_code == 2, r.output
    assert len(lines) == 1 and lines[0].startswith("Error: "), lines
    assert "Traceback" not in r.output
    for w in words:
        assert w in lines[0], (w, lines[0])
    return lines[0]


def _run(jobs: list[dict], folder: Path, **kw):
    rec = Recorder()
    res = run_batch(parse_jobs({"job": jobs}, cwd=folder), COMMANDS, backend=rec, show_progress=False,
                    echo=lambda s: None, **kw)
    return res, rec


# ------------------------------------------------------------------ confinement


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """tmp/project/jobs.toml's folder; tmp/elsewhere is outside it."""
    (tmp_path / "project").mkdir()
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "plant.ply").write_bytes(b"not read")
    return tmp_path / "project"


OUTSIDE = {
    "dotdot": ("bake", [*BAKE, "../x.usd"]),
    "absolute": ("bake", [*BAKE, "{elsewhere}/x.usd"]),
    "preview": ("bake", [*BAKE, "--preview", "../p.mp4", "out/x.usd"]),
    "frames_out": ("bake", [*BAKE, "--frames-out", "../frames", "out/x.usd"]),
    "frames_out_is_the_folder": ("bake", [*BAKE, "--frames-out", ".", "out/x.usd"]),
    "symlinked_folder": ("bake", [*BAKE, "link/x.usd"]),
    "fit_out": ("fit", ["../plant.ply", "video", "-o", "../fitted.pdmat"]),
    "fit_default_out": ("fit", ["../plant.ply", "video"]),  # ../plant.pdmat, as the CLI would write
}


@pytest.mark.parametrize("case", sorted(OUTSIDE))
def test_outputs_outside_the_jobs_folder_are_refused(project: Path, case: str) -> None:
    elsewhere = project.parent / "elsewhere"
    (project / "link").symlink_to(elsewhere)
    command, args = OUTSIDE[case]
    args = [a.replace("{elsewhere}", str(elsewhere)) for a in args]
    (project / "jobs.toml").write_text(_toml([{"name": "sneaky", "command": command, "args": args}]))
    before = sorted(p.name for p in project.parent.rglob("*"))
    r, lines = _cli(["batch", str(project / "jobs.toml"), "--workers", "1"])
    _one_error_line(r, lines, "job 'sneaky'", "outside the jobs file's folder", "--allow-outside")
    assert sorted(p.name for p in project.parent.rglob("*")) == before  # not even a folder made


def test_allow_outside_lets_them_run_and_inputs_outside_need_no_flag(project: Path) -> None:
    # Without the flag: ../plant.ply is read from outside, and outputs inside run, also
    # through a symlink that stays inside.
    (project / "real").mkdir()
    (project / "alias").symlink_to(project / "real")
    res, rec = _run([{"name": "a", "command": "bake", "args": [*BAKE, "--preview", "out/a.mp4", "out/a.usd"]},
                     {"name": "b", "command": "bake", "args": [*BAKE, "alias/b.usd"]}], project)
    assert rec.submitted == ["a", "b"]
    # Outputs outside: refused without the flag, run with it.
    jobs = [{"name": "a", "command": "bake", "args": [*BAKE, "../elsewhere/new/x.usd"]},
            {"name": "b", "command": "bake", "args": [*BAKE, str(project.parent / "elsewhere" / "y.usd")]}]
    with pytest.raises(JobsFileError, match="--allow-outside"):
        _run(jobs, project)
    res, rec = _run(jobs, project, allow_outside=True)
    assert rec.submitted == ["a", "b"] and [j.status for j in res.jobs] == [OK, OK]
    assert (project.parent / "elsewhere" / "new").is_dir()  # the batch made the output's folder there


@pytest.mark.parametrize("second", ["out/../out/same.usd", "out/sub/../same.usd", "alias/same.usd"])
def test_normalised_paths_clash(project: Path, second: str) -> None:
    (project / "out").mkdir()
    (project / "alias").symlink_to(project / "out")
    res, rec = _run([{"name": "a", "command": "bake", "args": [*BAKE, "out/same.usd"]},
                     {"name": "b", "command": "bake", "args": [*BAKE, second]}], project)
    a, b = res.jobs
    assert a.status == OK and b.status == FAILED and rec.submitted == ["a"]
    assert "which job a also writes" in b.error and str(project / "out" / "same.usd") in b.error


def test_a_frames_folder_clashes_with_outputs_inside_it(project: Path) -> None:
    res, rec = _run([{"name": "a", "command": "bake", "args": [*BAKE, "--frames-out", "out", "a.usd"]},
                     {"name": "b", "command": "bake", "args": [*BAKE, "out/b.usd"]},
                     {"name": "c", "command": "fit", "args": ["../plant.ply", "v", "-o", "fits/c.pdmat"]},
                     {"name": "d", "command": "bake", "args": [*BAKE, "--preview", "fits/c.preview.mp4", "d.usd"]}],
                    project)
    status = {j.name: (j.status, j.error) for j in res.jobs}
    assert rec.submitted == ["a", "c"]
    assert status["b"][0] == FAILED and "which job a also writes" in status["b"][1]
    # a fit writes its preview beside its material: a bake may not write the same file
    assert status["d"][0] == FAILED and "which job c also writes" in status["d"][1]


# -------------------------------------------------------------------- templates


# Python's format language reaches into objects and pads without bound; the rest are malformed.
BAD_TEMPLATES = ["{x.__class__.__name__}", "{x:>100000000}", "{x!r}", "{x[0]}", "{name.__init__}", "{x:slug!r}",
                 "{0}", "{}", "{x:slug:y}", "{ x}", "{x:upper}", "a}b", "{x"]


def test_templates_take_plain_names_only() -> None:
    for template in BAD_TEMPLATES:
        cases = [("args", {"args": [template]}), ("after", {"after": [template]})]
        if "{" in template:  # a name without a placeholder is not a template: the slugs are appended
            cases.append(("name", {"name": "a" + template}))
        for where, table in cases:
            job = {"name": "a", "command": "bake", "sweep": {"x": ["1"]}, **table}
            with pytest.raises(JobsFileError) as e:
                parse_jobs({"job": [job]})
            msg = str(e.value)
            assert "\n" not in msg and "job 'a" in msg and where in msg and len(msg) < 400, (template, msg)
    # What is allowed: {key}, {key:slug}, {name}, and {{ }} for literal braces.
    (j,) = parse_jobs({"job": [{"name": "n_{x}", "command": "bake", "sweep": {"x": ["0,0,1"]},
                                "args": ["{x}", "{x:slug}", "{{x}}", "}}{{", "out/{name}.usd"]}]})
    assert j.name == "n_0_0_1" and j.args == ("0,0,1", "0_0_1", "{x}", "}{", "out/n_0_0_1.usd")


def test_argument_and_name_lengths_are_bounded() -> None:
    long = "v" * 2000
    with pytest.raises(JobsFileError, match="expands to more than 4,096 characters"):
        parse_jobs({"job": [{"name": "a_{i}", "command": "bake", "sweep": {"i": [1], "x": [long]},
                             "args": ["{x}{x}{x}"]}]})
    with pytest.raises(JobsFileError, match="200 characters"):
        parse_jobs({"job": [{"name": "a_{x}", "command": "bake", "sweep": {"x": ["y" * 300]}}]})
    with pytest.raises(JobsFileError, match="printable"):
        parse_jobs({"job": [{"name": "a\nb", "command": "bake"}]})
    with pytest.raises(JobsFileError, match="more than the limit of 512"):
        parse_jobs({"job": [{"name": "a", "command": "bake", "args": ["x"] * 513}]})
    with pytest.raises(JobsFileError, match="NUL"):
        parse_jobs({"job": [{"name": "a", "command": "bake", "args": ["out\0.usd"]}]})
    # 200 jobs x 500 args x 200 characters = 20 M characters of arguments in all
    with pytest.raises(JobsFileError, match="add up to more than"):
        parse_jobs({"job": [{"name": "a", "command": "bake", "sweep": {"i": list(range(200))},
                             "args": ["z" * 200] * 500}]})


# ---------------------------------------------------------------- size, depth, count


def test_sweep_explosion_is_refused_before_expanding() -> None:
    with pytest.raises(JobsFileError, match="more than 10,000 jobs"):  # 11^4 = 14,641
        parse_jobs({"job": [{"name": "a", "command": "bake", "sweep": {f"k{i}": list(range(11)) for i in range(4)}}]})
    sweep = {f"k{i}": list(range(10)) for i in range(10)}  # 10^10 jobs
    with pytest.raises(JobsFileError, match="more than 10,000 jobs") as e:
        parse_jobs({"job": [{"name": "a", "command": "bake", "args": ["x.usd"], "sweep": sweep}]})
    assert "10 x 10 x 10" in str(e.value)
    # two tables of 6,000 each pass one at a time, not together
    with pytest.raises(JobsFileError, match="more than 10,000 jobs"):
        parse_jobs({"job": [{"name": f"t{t}", "command": "bake", "sweep": {"i": list(range(6000))}}
                            for t in range(2)]})


DEEP = [  # a parser that recurses per level ends in a RecursionError on the first two
    "x = " + "[" * 100_000 + "]" * 100_000,
    "x = " + "{a = " * 100_000 + "1" + "}" * 100_000,
    "x = " + "[" * 17 + "]" * 17,
    "[" + ".".join(["a"] * 100_000) + "]",
    ".".join(["a"] * 100_000) + " = 1",  # quadratic in tomllib: minutes without the check
]


def test_deep_files_get_one_line(tmp_path: Path) -> None:
    f = tmp_path / "jobs.toml"
    for body in DEEP:
        f.write_text(body + "\n")
        r, lines = _cli(["batch", str(f)])
        _one_error_line(r, lines, "jobs.toml", "nested more than 16 levels deep")
    # Brackets, braces and dots inside strings and comments do not count.
    brackets = "[[[[[[[[[[[[[[[[[[[[{{{{{{{{{{{{{{{{{{{{"
    f.write_text(_toml([{"name": "a", "command": "bake", "args": [brackets, "x.usd"],
                         "sweep": {"x": ["1.5.6.7.8.9.1.2.3.4.5.6.7.8.9.0.1.2"]}}])
                 + "# " + brackets + "\n" + f"[[job]]\nname = 'b'\ncommand = 'bake'\nargs = ['''{brackets}''']\n")
    jobs = load_jobs(f)
    assert [j.args[0] for j in jobs] == ["[" * 20 + "{" * 10] * 2  # {{ is a literal brace


def test_large_file_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "jobs.toml"
    f.write_text(_toml([{"name": "a", "command": "bake", "args": ["x.usd"]}]) + "# " + "x" * (1 << 20) + "\n")
    r, lines = _cli(["batch", str(f)])
    _one_error_line(r, lines, "jobs.toml", "larger than 1,048,576 bytes")


def test_a_pipe_as_the_jobs_file_is_refused_without_blocking(tmp_path: Path) -> None:
    fifo = tmp_path / "jobs.toml"
    os.mkfifo(fifo)
    with pytest.raises(B.JobsFileError, match="not a regular file"):
        B.load_jobs(fifo)


def test_not_utf8_is_one_line(tmp_path: Path) -> None:
    f = tmp_path / "jobs.toml"
    f.write_bytes(b'[[job]]\nname = "\xff"\n')
    r, lines = _cli(["batch", str(f)])
    _one_error_line(r, lines, "jobs.toml", "UTF-8")


def test_help_states_the_limits() -> None:
    r = CliRunner().invoke(main, ["batch", "--help"])
    text = " ".join(r.output.split())
    for n in (f"{B.MAX_JOBS:,}", f"{B.MAX_ARGS}", f"{B.MAX_ARG_CHARS:,}", f"{B.MAX_DEPTH}", "1 MiB",
              f"{B.MAX_NAME_CHARS}", "--allow-outside"):
        assert n in text, n
    assert B.MAX_FILE_BYTES == 1 << 20


# -------------------------------------------------------------------- help jobs


@pytest.mark.parametrize("arg", ["--help", "-h", "--version"])
def test_a_job_that_asks_for_help_fails(project: Path, arg: str) -> None:
    res, rec = _run([{"name": "helpme", "command": "bake", "args": [*BAKE, arg, "out/x.usd"]},
                     {"name": "next", "command": "bake", "after": ["helpme"], "args": [*BAKE, "out/y.usd"]},
                     {"name": "other", "command": "fit", "args": ["../plant.ply", "v", "-o", "f.pdmat"]}], project)
    by = {j.name: j for j in res.jobs}
    assert by["helpme"].status == FAILED and arg in by["helpme"].error and "\n" not in by["helpme"].error
    assert by["next"].status == "blocked" and by["other"].status == OK and rec.submitted == ["other"]
    assert not (project / "out").exists()


def test_the_worker_refuses_help_too(tmp_path: Path) -> None:
    # What a worker runs, as a second line of defence (the API lets anyone call it).
    for args in (["--help"], ["--force", "0,0,1", "-h", "x.usd"]):
        r = run_job({"command": "bake", "args": args, "cwd": str(tmp_path), "threads": 0, "run": batch_run})
        assert not r["ok"] and "help" in r["error"]


# ------------------------------------------------------------------- temporaries


def test_remove_temporaries_takes_only_the_writers_temporaries(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    long = "é" * 60 + ".usd"  # 124 bytes: a writer keeps the first 96 in its temporaries' names
    mine = [".x.usd.ab_cd123.part.usd", ".x.usd.tmp-4242-0a1b2c3d.usdc", ".x.usd.tmp-4242-0a1b2c3d.usda",
            ".p.mp4.zzzzzzzz.part.mp4", f".{'é' * 48}.abcdefgh.part.usd", f".{long}.abcdefgh.part.usd"]
    folders = [".frames.q1w2e3r4.part", ".frames.a1b2c3d4.old"]
    others = ["x.usd", ".x.usd.notes", ".x.usd.ab_cd123.part.usda", ".x.usd.ab_cd12.part.usd",
              "x.usd.ab_cd123.part.usd",
              ".y.usd.ab_cd123.part.usd", ".x.usd.tmp-4242-0a1b2c3d.usdz", ".frames.a1b2c3d4.older", "keep.txt"]
    for n in mine + others:
        (out / n).write_text("x")
    for n in folders:
        (out / n).mkdir()
        (out / n / "frame_0000.png").write_text("x")
    # the folder replace was cut between its renames: the previous frames wait in .old/,
    # under the name pd_tool.core.atomic parks them with
    from pd_tool.core.atomic import PARKED

    (out / ".frames.a1b2c3d4.old" / PARKED).mkdir()
    (out / ".frames.a1b2c3d4.old" / PARKED / "camera.json").write_text("{}")
    files = B.JobFiles(outputs=[out / "x.usd", out / "p.mp4", out / "frames", out / long], folders=[out / "frames"])
    removed = B.remove_temporaries([files])
    assert sorted(p.name for p in removed) == sorted(mine + folders)
    assert sorted(p.name for p in out.iterdir()) == sorted(others + ["frames"])
    assert (out / "frames" / "camera.json").read_text() == "{}"  # put back, not deleted


# ------------------------------------------------------------------ --json writes


@contextlib.contextmanager
def _tmpfs(folder: Path, options: str):
    """Mount a tmpfs on `folder` (root only); yields False when mounting is not possible."""
    folder.mkdir(exist_ok=True)
    ok = os.geteuid() == 0 and subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)],
                                             capture_output=True).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", "-l", str(folder)], check=False)


def _help_job_file(folder: Path) -> Path:
    # Its one job fails in the driver (it asks for help), so the run needs no worker process.
    f = folder / "jobs.toml"
    f.write_text(_toml([{"name": "a", "command": "bake", "args": ["--help"]}]))
    return f


def test_json_to_a_read_only_folder_is_refused_before_the_jobs(tmp_path: Path, monkeypatch) -> None:
    jobs = _help_job_file(tmp_path)
    ro = tmp_path / "ro"
    with _tmpfs(ro, "ro") as mounted:
        if not mounted:  # what statvfs would say of a read-only mount
            from pd_tool.core import atomic

            real = atomic.destination_problem
            monkeypatch.setattr(atomic, "destination_problem",
                                lambda p: errno.EROFS if Path(p).parent == ro else real(p))
        r, lines = _cli(["batch", str(jobs), "--json", str(ro / "summary.json")])
        _one_error_line(r, lines, str(ro / "summary.json"), "writable")
        assert "1 jobs" not in r.output  # refused before running anything
        assert os.listdir(ro) == []


def test_json_to_a_full_disk_is_one_line_and_leaves_no_temporary(tmp_path: Path, monkeypatch) -> None:
    jobs = _help_job_file(tmp_path)
    full = tmp_path / "full"
    with _tmpfs(full, "size=64k") as mounted:
        if mounted:  # a disk already full is refused before the jobs run
            with contextlib.suppress(OSError), open(full / "filler", "wb") as f:
                f.write(b"\0" * (1 << 20))
            r, lines = _cli(["batch", str(jobs), "--json", str(full / "summary.json")])
            _one_error_line(r, lines, str(full / "summary.json"), "No space left on device")
            assert "1 jobs" not in r.output
            assert sorted(os.listdir(full)) == ["filler"]
            (full / "filler").unlink()
        # a disk that fills up while the jobs run: the summary's failure is the last line
        real = Path.write_text

        def write_text(self, *a, **kw):
            if self.parent == full:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            return real(self, *a, **kw)

        monkeypatch.setattr(Path, "write_text", write_text)
        r, lines = _cli(["batch", str(jobs), "--json", str(full / "summary.json")])
        assert [line for line in lines if line.startswith("Error")] == lines[-1:]
        _one_error_line(r, lines[-1:], str(full / "summary.json"), "No space left on device")
        assert "1 jobs: 0 ok, 1 failed" in r.stdout  # the jobs ran; only the summary file failed
        assert os.listdir(full) == []  # no temporary


def test_a_ray_refusal_is_one_line_with_no_progress_bar_before_it(tmp_path: Path) -> None:
    # Nobody listens on port 1: one line (Ray's own retries would log for minutes), and the
    # progress bar has not started. Without Ray installed the one line says how to get it.
    r, lines = _cli(["batch", str(_help_job_file(tmp_path)), "--ray", "127.0.0.1:1"])
    _one_error_line(r, lines, "--ray")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs /proc")
def test_fingerprints_read_inputs_only_up_to_their_size(tmp_path: Path) -> None:
    # A jobs file may name any existing path as an input; files of /proc say 0 bytes and
    # some would stream gigabytes (pagemap), and a FIFO would block the driver.
    import hashlib

    assert B.file_digest(Path("/proc/self/status")) == hashlib.sha256(b"").digest()
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "plant.ply").write_bytes(b"x")
    (job,) = parse_jobs({"job": [{"name": "a", "command": "bake",
                                  "args": [*BAKE, "--camera", "fifo", "out.usd"]}]}, cwd=tmp_path)
    files = B.job_files(job, COMMANDS)
    assert tmp_path / "fifo" in files.inputs and len(B.fingerprint(job, files)) == 64
