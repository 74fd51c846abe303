"""A real `pdtool batch` process, stopped while a slow bake runs and two quick ones wait:

- SIGKILL: its worker processes are gone within seconds (parent-death signal, watchdog), and
  none of the queued jobs starts afterwards;
- SIGTERM to the driver, or SIGINT to its process group (Ctrl-C in a terminal): it exits
  with 128 + the signal and one `Error:` line, its workers are gone, and no temporary of
  the running bake stays beside the outputs.

Each run is one interpreter plus one worker (torch and warp imports), so the file takes
about a minute on two shared cores.
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

REPO = Path(__file__).resolve().parents[2]
TINY = ["--quality", "draft", "--frames", "3", "--format", "instancer", "--device", "cpu"]
# Long enough to be running whenever the signal comes (~50 ms a frame here: minutes in all);
# the force lasts the whole clip so that the object never comes to rest.
SLOW = ["--quality", "draft", "--frames", "2000", "--substeps", "500", "--duration", "60",
        "--format", "instancer", "--device", "cpu"]
POKE = ["--scene", "../plant.ply", "--preset", "flower", "--force", "0,0,1"]

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")


def _jobs() -> str:
    jobs = [("slow", [*POKE, *SLOW, "out/slow.usd"]), ("queued_1", [*POKE, *TINY, "out/queued_1.usd"]),
            ("queued_2", [*POKE, *TINY, "out/queued_2.usd"])]
    return "".join(f'[[job]]\nname = "{n}"\ncommand = "bake"\nargs = {json.dumps(a)}\n' for n, a in jobs)


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) of a process, or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text[text.rindex(")") + 2:].split()
    return fields[0], int(fields[1])


def _descendants(pid: int) -> set[int]:
    found: set[int] = set()
    todo = [pid]
    while todo:
        parent = todo.pop()
        for d in os.listdir("/proc"):
            if d.isdigit() and int(d) not in found:
                st = _stat(int(d))
                if st is not None and st[1] == parent:
                    found.add(int(d))
                    todo.append(int(d))
    return found


def _alive(pid: int) -> bool:
    st = _stat(pid)
    return st is not None and st[0] != "Z"  # a zombie has ended; only its parent's wait is missing


def _interactive_sigint() -> None:
    # A shell starts background commands with SIGINT ignored, and a Python started so keeps
    # ignoring it (as `nohup pdtool batch &` should); a terminal's Ctrl-C is what is tested.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def running_batch(tmp_path: Path):
    """Start `pdtool batch --workers 1` in its own session and wait until the slow bake is
    writing its USD; yields (process, its worker pids, out folder, stderr file)."""
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    save_splats(make_plant(600, seed=0), tmp_path / "plant.ply")
    project = tmp_path / "project"
    project.mkdir()
    (project / "jobs.toml").write_text(_jobs())
    out = project / "out"
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    err = tmp_path / "stderr.txt"
    with open(err, "wb") as e:
        proc = subprocess.Popen([sys.executable, "-m", "cli", "batch", "jobs.toml", "--workers", "1"], cwd=project,
                                env=env, stdout=subprocess.DEVNULL, stderr=e, start_new_session=True,
                                preexec_fn=_interactive_sigint)
    workers: set[int] = set()
    try:
        deadline = time.monotonic() + 600  # a slow, shared CI machine: spawn + imports + preparation
        while not (out.is_dir() and any(p.name.startswith(".slow.usd.tmp-") for p in out.iterdir())):
            assert proc.poll() is None, err.read_text()
            assert time.monotonic() < deadline, "the slow bake did not start within 600 s"
            time.sleep(0.05)
        workers = _descendants(proc.pid)
        assert workers, "no worker process found"
        yield proc, workers, out, err
    finally:
        for pid in workers:  # a failed run must not leave them behind
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _wait_gone(pids: set[int], seconds: float = 15.0) -> set[int]:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        left = {p for p in pids if _alive(p)}
        if not left:
            return left
        time.sleep(0.05)
    return {p for p in pids if _alive(p)}


def test_sigkill_of_the_driver_takes_its_workers_and_its_queue(running_batch) -> None:
    proc, workers, out, err = running_batch
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert _wait_gone(workers) == set(), "workers outlived the killed driver"
    # Nothing ran after the driver: the queued bakes left neither an output nor a temporary.
    assert not [p.name for p in out.iterdir() if "queued" in p.name]
    assert not (out / "slow.usd").exists()
    assert "Warning" not in err.read_text()  # nor does anything of it complain afterwards


@pytest.mark.parametrize("how", ["SIGTERM to the driver", "SIGINT to the driver", "SIGINT to the group"])
def test_sigterm_and_ctrl_c_stop_the_jobs_and_remove_their_temporaries(running_batch, how: str) -> None:
    proc, workers, out, err = running_batch
    sig = signal.SIGTERM if "SIGTERM" in how else signal.SIGINT
    if "group" in how:
        os.killpg(proc.pid, sig)  # what Ctrl-C in a terminal does
    else:
        os.kill(proc.pid, sig)
    rc = proc.wait(timeout=120)
    assert rc == 128 + sig, (rc, err.read_text()[-2000:])
    assert _wait_gone(workers) == set()
    assert sorted(p.name for p in out.iterdir()) == [], "temporaries or outputs left beside the outputs"
    text = err.read_text()
    lines = [line for line in text.replace("\r", "\n").splitlines() if line.startswith("Error")]
    assert len(lines) == 1 and signal.Signals(sig).name in lines[0] and "--resume" in lines[0], lines
    assert "Traceback" not in text and "Warning" not in text, text[-2000:]  # no noise from the workers


def _parent_death_signal() -> int:
    """What a worker's prctl(PR_GET_PDEATHSIG) says (runs in the worker)."""
    import ctypes

    value = ctypes.c_int(-1)
    ctypes.CDLL(None, use_errno=True).prctl(2, ctypes.byref(value), 0, 0, 0)  # PR_GET_PDEATHSIG
    return value.value


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
def test_a_worker_has_the_parent_death_signal() -> None:
    from pd_tool.batch import LocalBackend

    backend = LocalBackend(workers=1, gpus=0)
    try:
        assert backend.cpu.submit(_parent_death_signal).result(timeout=300) == signal.SIGKILL
    finally:
        backend.close()


def test_the_watchdog_ends_a_worker_whose_driver_died() -> None:
    # A process in the role of the driver starts one running only the watchdog (no
    # parent-death signal), then is killed: the watchdog notices the new parent.
    worker = ("import sys; from pd_tool.batch.workers import watchdog; print('watching', flush=True); "
              "watchdog(int(sys.argv[1]))")
    driver = ("import os, subprocess, sys, time\n"
              f"w = subprocess.Popen([sys.executable, '-c', {worker!r}, str(os.getpid())])\n"
              "print(w.pid, flush=True)\n"
              "while w.poll() is None:\n"  # until this process is killed, or the watcher fails
              "    time.sleep(0.1)\n")
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-c", driver], stdout=subprocess.PIPE, env=env, start_new_session=True)
    pid = int(proc.stdout.readline())
    try:
        assert proc.stdout.readline().strip() == b"watching"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        assert _wait_gone({pid}) == set(), "the watchdog did not end the orphaned worker"
    finally:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)
        proc.stdout.close()


def test_a_cancelled_pool_wakes_quietly_at_exit() -> None:
    """At exit Python 3.11's concurrent.futures wakes each pool's manager thread through a
    pipe that the thread may be closing at that moment. After close(cancel=True) that late
    wake-up ignores a pipe closed under it, instead of printing a traceback."""
    from pd_tool.batch.workers import LocalBackend

    backend = LocalBackend(workers=1, gpus=0)
    assert backend.cpu.submit(os.getpid).result(timeout=300) != os.getpid()
    wakeup = backend.cpu._executor_manager_thread_wakeup
    backend.close(cancel=True)
    # the race: the manager thread has closed the pipe, and the exit hook has already seen
    # it open
    wakeup._writer.close()
    wakeup._closed = False
    wakeup.wakeup()  # what the exit hook calls
