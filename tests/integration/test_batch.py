"""`pdtool batch`: jobs-file expansion, then real tiny bakes of the synthetic plant on the local
process pool (killed, then --resume) and on a single-node Ray cluster on loopback.

The run tests share one module fixture: a batch is killed with SIGKILL after its first job,
resumed, and its outputs are then compared byte for byte with a Ray run of the same jobs.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from cli import batch_parse, batch_run
from pd_tool.batch import (BLOCKED, FAILED, OK, UP_TO_DATE, CommandLines, JobsFileError, LocalBackend, RayBackend,
                           job_files, load_jobs, parse_jobs, ray_resources, run_batch, run_job)

COMMANDS = CommandLines(parse=batch_parse, run=batch_run)
REPO = Path(__file__).resolve().parents[2]
TINY = ["--quality", "draft", "--frames", "3", "--format", "instancer", "--device", "cpu"]


def _toml_list(items: list[str]) -> str:
    return "[" + ", ".join(json.dumps(a) for a in items) + "]"


# 'bad' comes first so that a one-worker run fails it before the first bake finishes. Then a
# reference bake whose rendered frames a tiny fit reads, and two bakes of the fitted material
# (the studio chain: fit waits for its video, bakes wait for the fit), and a 2x2 preset/force
# sweep of bakes.
JOBS = f"""
[[job]]
name = "bad"
command = "bake"
args = ["--scene", "../missing.ply", "--preset", "flower", "--force", "0,0,1", "out/bad.usd"]

[[job]]
name = "after_bad"
command = "bake"
after = ["bad"]
args = {_toml_list(["--scene", "../plant.ply", "--preset", "flower", "--force", "0,0,1", *TINY, "out/{name}.usd"])}

[[job]]
name = "reference"
command = "bake"
args = {_toml_list(["--scene", "../plant.ply", "--preset", "flower", "--force", "0,0,1", *TINY,
                    "--frames-out", "ref", "out/{name}.usd"])}

[[job]]
name = "fit"
command = "fit"
after = ["reference"]
args = ["../plant.ply", "ref", "--quality", "draft", "--velocity-iters", "1", "--material-iters", "1",
        "--working-size", "32", "--no-preview", "--device", "cpu", "-o", "fits/plant.pdmat"]

[[job]]
name = "fitted"
command = "bake"
after = ["fit"]
args = {_toml_list(["--scene", "../plant.ply", "--material", "fits/plant.pdmat", "--force", "{force}", *TINY,
                    "out/{name}.usd"])}
[job.sweep]
force = ["0,0,1", "-1,0,0"]

[[job]]
name = "poke_{{preset}}_{{force}}"
command = "bake"
args = {_toml_list(["--scene", "../plant.ply", "--preset", "{preset}", "--force", "{force}", *TINY, "out/{name}.usd"])}
[job.sweep]
preset = ["flower", "jelly"]
force = ["0,0,1", "1,0,0"]
"""
POKES = ["poke_flower_0_0_1", "poke_flower_1_0_0", "poke_jelly_0_0_1", "poke_jelly_1_0_0"]
BAKES = ["reference", "fitted_0_0_1", "fitted_-1_0_0", *POKES]  # every job that writes a .usd
RUNNABLE = [*BAKES, "fit"]


def test_sweep_expands_names_args_and_after(tmp_path: Path) -> None:
    data = {"job": [
        {"name": "fit_{obj}", "command": "fit", "args": ["{obj}.ply", "video_{obj}/", "-o", "{name}.pdmat"],
         "sweep": {"obj": ["udon", "donut"]}},
        {"name": "poke", "command": "bake", "after": ["fit_{obj}"],
         "args": ["--material", "fit_{obj}.pdmat", "--force", "{force}", "out/{obj}_{force:slug}.usd"],
         "sweep": {"obj": ["udon", "donut"], "force": ["0,0,1", "-1,0,0"]}},
        {"name": "report", "command": "bake", "after": ["poke"], "args": ["x.usd"]},
    ]}
    jobs = parse_jobs(data, cwd=tmp_path)
    names = [j.name for j in jobs]
    assert names == ["fit_udon", "fit_donut", "poke_udon_0_0_1", "poke_udon_-1_0_0", "poke_donut_0_0_1",
                     "poke_donut_-1_0_0", "report"]
    by = {j.name: j for j in jobs}
    assert by["fit_donut"].args == ("donut.ply", "video_donut/", "-o", "fit_donut.pdmat")
    assert by["poke_udon_-1_0_0"].args == ("--material", "fit_udon.pdmat", "--force", "-1,0,0",
                                          "out/udon_-1_0_0.usd")
    assert by["poke_donut_0_0_1"].after == ("fit_donut",)
    # A sweep's base name stands for all of its jobs.
    assert set(by["report"].after) == {n for n in names if n.startswith("poke_")}
    assert all(j.cwd == str(tmp_path.resolve()) for j in jobs)


@pytest.mark.parametrize("jobs, words", [
    ([{"name": "a", "command": "bake", "after": ["b"]}], "no job name"),
    ([{"name": "a", "command": "bake", "after": ["b"]}, {"name": "b", "command": "bake", "after": ["a"]}], "cycle"),
    ([{"name": "a", "command": "bake"}, {"name": "a", "command": "fit"}], "two jobs"),
    ([{"name": "a", "command": "bake", "sweep": {"x": [1, 2]}, "args": ["{y}"]}], "unknown placeholder {y}"),
    ([{"name": "a", "command": "render"}], "command must be one of"),
    ([{"name": "a", "command": "bake", "sweep": {"x": []}}], "non-empty list"),
    ([{"name": "a", "command": "bake", "argz": []}], "unknown key(s) argz"),
    ([{"name": "same", "command": "bake", "sweep": {"x": [1, 2]}}, {"name": "same_1", "command": "bake"}],
     "two jobs"),
])
def test_jobs_file_errors_are_one_line(jobs, words: str) -> None:
    with pytest.raises(JobsFileError) as e:
        parse_jobs({"job": jobs})
    assert words in str(e.value) and "\n" not in str(e.value)


def test_not_toml(tmp_path: Path) -> None:
    bad = tmp_path / "jobs.toml"
    bad.write_text("[[job]\nname=")
    with pytest.raises(JobsFileError, match="not valid TOML"):
        load_jobs(bad)


def test_job_files_use_the_cli_parser(tmp_path: Path) -> None:
    (tmp_path / "s.ply").write_bytes(b"x")
    (tmp_path / "v").mkdir()
    (tmp_path / "q.toml").write_text("grid = 16\n")
    fit, bake = parse_jobs({"job": [
        {"name": "f", "command": "fit", "args": ["s.ply", "v", "--quality", "q.toml"]},
        {"name": "b", "command": "bake", "args": ["--scene", "s.ply", "--preset", "flower", "--force", "0,0,1",
                                                  "--preview", "p.mp4", "o/b.usd"]},
    ]}, cwd=tmp_path)
    f = job_files(fit, COMMANDS)
    assert f.outputs == [tmp_path.resolve() / "s.pdmat"]  # the CLI's default --out
    assert set(f.inputs) == {tmp_path.resolve() / p for p in ("s.ply", "v", "q.toml")}
    b = job_files(bake, COMMANDS)
    assert b.outputs == [tmp_path.resolve() / "o/b.usd", tmp_path.resolve() / "p.mp4"]
    assert b.inputs == [tmp_path.resolve() / "s.ply"]  # 'flower' is a built-in preset, not a file
    # a clip without a camera is registered: the camera and its picture are the fit's too
    assert {tmp_path.resolve() / n for n in ("s.camera.json", "s.camera.register.png")} <= set(f.side)
    (tmp_path / "w").mkdir()
    (two,) = parse_jobs({"job": [{"name": "g", "command": "fit", "args": ["s.ply", "v", "w", "-o", "g.pdmat"]}]},
                        cwd=tmp_path)
    side = set(job_files(two, COMMANDS).side)
    assert {tmp_path.resolve() / n for n in ("g.camera-0.json", "g.camera-1.register.png")} <= side


def test_run_job_reports_one_line_errors(tmp_path: Path) -> None:
    # What a worker runs, in this process: the click command's own usage error, one line.
    r = run_job({"command": "bake", "args": ["--force", "0,0,1", "x.txt"], "cwd": str(tmp_path), "threads": 0,
                 "run": batch_run})
    assert not r["ok"] and r["error"].startswith("usage: ") and "must end in .usd" in r["error"]
    r = run_job({"command": "bake", "args": ["x.usd"], "cwd": str(tmp_path / "gone"), "threads": 0,
                 "run": batch_run})
    assert not r["ok"] and "does not exist on" in r["error"] and "same path" in r["error"]


class InProcess:
    """A backend that runs each job right here, in order (the same run_job a worker runs)."""

    name = "in-process"

    def __init__(self) -> None:
        self.done: list[tuple[int, dict]] = []

    def submit(self, job, run):
        self.done.append((len(self.done), run_job({"command": job.command, "args": list(job.args),
                                                   "cwd": job.cwd, "threads": 0, "run": run})))
        return self.done[-1][0]

    def wait(self, handles):
        return [(h, r) for h, r in self.done if h in set(handles)]

    def close(self, cancel=False, handles=()):
        pass


def test_two_jobs_one_output_is_refused(tmp_path: Path) -> None:
    args = ["--preset", "flower", "--force", "0,0,1", "out/x.usd"]  # no --scene: the CLI's own error
    jobs = parse_jobs({"job": [{"name": "a", "command": "bake", "args": args},
                               {"name": "b", "command": "bake", "args": args}]}, cwd=tmp_path)
    res = run_batch(jobs, COMMANDS, backend=InProcess(), show_progress=False, echo=lambda s: None)
    a, b = res.jobs
    assert a.status == FAILED and "no scene" in a.error
    assert b.status == FAILED and "which job a also writes" in b.error
    assert not (tmp_path / "out" / "x.usd").exists()


def test_gpu_placement() -> None:
    jobs = parse_jobs({"job": [
        {"name": "c", "command": "bake", "args": ["--device", "cuda", "a.usd"]},
        {"name": "p", "command": "bake", "args": ["--device=cpu", "a.usd"]},
        {"name": "a", "command": "bake", "args": ["a.usd"]},
    ]})
    c, p, a = jobs
    assert (c.device, p.device, a.device) == ("cuda", "cpu", "auto")
    assert ray_resources(c, 0)["num_gpus"] == 1 and ray_resources(p, 8)["num_gpus"] == 0
    assert ray_resources(a, 0)["num_gpus"] == 0 and ray_resources(a, 2)["num_gpus"] == 1
    # Local pool: two (pretend) GPUs get the cuda/auto jobs in turn; no process starts here.
    backend = LocalBackend(workers=1, gpus=2)
    try:
        assert [backend.route(j) for j in (c, p, a, c)] == [0, None, 1, 0]
        assert LocalBackend(workers=1, gpus=0).route(c) is None  # fails there with the CLI's message
    finally:
        backend.close()


# ------------------------------------------------------------------------- real runs


def _records_so_far(folder: Path) -> list[Path]:
    # the batch creates and renames hidden temporary folders while we look
    try:
        return list(folder.rglob("*.batch.json"))
    except FileNotFoundError:
        return []


@pytest.fixture(scope="module")
def killed_then_resumed(tmp_path_factory):
    """Start `pdtool batch --workers 1` in its own process group, SIGKILL the group as soon as
    the first job's record appears, then run `--resume` in-process on two workers."""
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    root = tmp_path_factory.mktemp("batch")
    save_splats(make_plant(600, seed=0), root / "plant.ply")
    for sub in ("local", "ray"):
        (root / sub).mkdir()
        (root / sub / "jobs.toml").write_text(JOBS)
    local = root / "local"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "cli", "batch", "jobs.toml", "--workers", "1"], cwd=local,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 600  # a slow, shared CI machine: spawn + imports + first bake
    try:
        while not _records_so_far(local):
            assert proc.poll() is None, "the batch ended before it could be killed"
            assert time.monotonic() < deadline, "no job finished within 600 s"
            time.sleep(0.02)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    records = {json.loads(p.read_text())["job"]: json.loads(p.read_text()) for p in local.rglob("*.batch.json")}
    done_at_kill = set(records)
    mtimes = {n: Path(r["outputs"][0]).stat().st_mtime_ns for n, r in records.items()}
    # The resume goes through the CLI command, with its summary table and --json file.
    from click.testing import CliRunner

    from cli import main

    old = os.getcwd()
    os.chdir(root)  # relative paths in the jobs file follow the file, not the caller's folder
    try:
        r = CliRunner().invoke(main, ["batch", "local/jobs.toml", "--workers", "2", "--resume",
                                      "--json", "summary.json"])
    finally:
        os.chdir(old)
    assert r.exit_code == 1, r.output  # one job failed
    summary = json.loads((root / "summary.json").read_text())
    return root, done_at_kill, mtimes, summary, r.output


def test_resume_after_kill_runs_only_the_missing_jobs(killed_then_resumed) -> None:
    root, done_at_kill, mtimes, summary, _ = killed_then_resumed
    status = {r["name"]: r["status"] for r in summary["jobs"]}
    assert done_at_kill and done_at_kill < set(RUNNABLE), done_at_kill
    assert {n for n in RUNNABLE if status[n] == UP_TO_DATE} == done_at_kill
    assert {n for n in RUNNABLE if status[n] == OK} == set(RUNNABLE) - done_at_kill
    by = {r["name"]: r for r in summary["jobs"]}
    for n in done_at_kill:  # skipped, not rewritten
        assert Path(by[n]["outputs"][0]).stat().st_mtime_ns == mtimes[n]
    for n in RUNNABLE:
        out = Path(by[n]["outputs"][0])
        rec = json.loads(out.with_name(out.name + ".batch.json").read_text())
        assert rec["job"] == n and rec["fingerprint"] == by[n]["fingerprint"] and len(rec["fingerprint"]) == 64
    # The fit read the reference bake's frames: its fingerprint covers them.
    assert any("/ref" in p for p in json.loads((root / "local" / "fits" / "plant.pdmat.batch.json").read_text())["inputs"])


def test_a_fits_side_outputs_are_known_to_the_batch(killed_then_resumed) -> None:
    # Clash checks and the clean-up after Ctrl-C cover what a fit writes beside its material:
    # every file the real fit left in fits/ (but the batch's own record) is in its list.
    root = killed_then_resumed[0]
    (fit,) = [j for j in load_jobs(root / "local" / "jobs.toml") if j.name == "fit"]
    written = set(job_files(fit, COMMANDS).written())
    left = {p for p in (root / "local" / "fits").iterdir() if not p.name.endswith(".batch.json")}
    assert left and left <= written, left - written


def test_bad_input_fails_alone(killed_then_resumed) -> None:
    _, _, _, summary, table = killed_then_resumed
    by = {r["name"]: r for r in summary["jobs"]}
    assert by["bad"]["status"] == FAILED
    assert "missing.ply" in by["bad"]["error"] and "\n" not in by["bad"]["error"]
    assert by["after_bad"]["status"] == BLOCKED and "bad" in by["after_bad"]["error"]
    assert all(by[n]["status"] in (OK, UP_TO_DATE) for n in RUNNABLE)
    assert summary["counts"][FAILED] == 1 and summary["counts"][BLOCKED] == 1
    # The summary table names every job with its status.
    for n, r in by.items():
        assert any(line.startswith(n + " ") and r["status"] in line for line in table.splitlines())


def test_ray_gives_the_same_usd_bytes_as_the_local_pool(killed_then_resumed) -> None:
    ray = pytest.importorskip("ray", reason="the ray extra is not installed (pip install -e '.[ray]'); .ci/run installs it")
    root = killed_then_resumed[0]
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
             _node_ip_address="127.0.0.1")
    try:
        result = run_batch(load_jobs(root / "ray" / "jobs.toml"), COMMANDS, backend=RayBackend(None),
                           show_progress=False, echo=lambda s: None)
    finally:
        ray.shutdown()
    status = {r.name: r.status for r in result.jobs}
    assert status["bad"] == FAILED and status["after_bad"] == BLOCKED
    assert all(status[n] == OK for n in RUNNABLE)
    # The fitted material too (material files are byte-identical for the same fit).
    assert (root / "local" / "fits" / "plant.pdmat").read_bytes() == (root / "ray" / "fits" / "plant.pdmat").read_bytes()
    for n in BAKES:
        a = (root / "local" / "out" / f"{n}.usd").read_bytes()
        b = (root / "ray" / "out" / f"{n}.usd").read_bytes()
        assert a == b, n


def test_cli_jobs_file_error_exits_2(tmp_path: Path) -> None:
    from click.testing import CliRunner

    from cli import main

    jobs = tmp_path / "jobs.toml"
    jobs.write_text('[[job]]\nname = "a"\ncommand = "bake"\nafter = ["nope"]\n')
    r = CliRunner().invoke(main, ["batch", str(jobs)])
    assert r.exit_code == 2 and "waits for 'nope', which is no job name" in r.output


def test_job_files_know_the_splat_outputs_of_format(tmp_path: Path) -> None:
    (tmp_path / "s.ply").write_bytes(b"x")
    common = ["--scene", "s.ply", "--preset", "flower", "--force", "0,0,1", "--format"]
    bake, seq = parse_jobs({"job": [
        {"name": "b", "command": "bake", "args": [*common, "both,ply-seq,gltf", "o.usd"]},
        {"name": "q", "command": "bake", "args": [*common, "spz-seq", "frames"]},
    ]}, cwd=tmp_path)
    root = tmp_path.resolve()
    f = job_files(bake, COMMANDS)
    assert f.outputs == [root / "o.usd", root / "o_ply", root / "o.glb"] and f.folders == [root / "o_ply"]
    f = job_files(seq, COMMANDS)
    assert f.outputs == [root / "frames"] and f.folders == [root / "frames"]
