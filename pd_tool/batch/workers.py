"""The worker side: `run_job` (one job in-process, its output captured from the file
descriptors), the worker's stop signal, parent-death signal and watchdog, and the two
backends that start workers, `LocalBackend` (spawned processes) and `RayBackend` (Ray tasks).
"""
from __future__ import annotations

import atexit
import concurrent.futures as cf
import contextlib
import ctypes
import gc
import io
import multiprocessing as mp
import os
import platform
import signal
import socket
import sys
import tempfile
import threading
import time
from multiprocessing import resource_tracker
from multiprocessing.connection import wait as wait_for
from typing import Any, Callable, Iterable

from pd_tool.batch.jobs import Job, asks_for_help, one_line
from pd_tool.core.device import native_stderr_silenced
from pd_tool.core.errors import PdToolError

# Seconds a stopped worker gets to unwind its job (atomic outputs remove their temporaries)
# before it is killed.
STOP_GRACE_S = 10.0
# How often a worker's watchdog looks for its driver, s.
WATCHDOG_S = 0.5


class WorkerStopped(BaseException):
    """Raised in a worker's main thread when the driver stops it (SIGTERM) during a job, so
    that the job's `with` blocks (atomic outputs, the USD writer) remove their temporaries
    on the way out. A BaseException: the CLI's handlers must not turn it into a job error."""


# Per worker process: the driver's pid, whether a job runs, whether a stop was asked for.
_WORKER: dict[str, Any] = {"driver": None, "running": False, "stopping": False}


def _on_stop_signal(signum: int, frame: Any) -> None:
    if _WORKER["stopping"]:
        return  # already unwinding: a second signal must not cut the cleanup short
    _WORKER["stopping"] = True
    if _WORKER["running"]:
        raise WorkerStopped(signal.Signals(signum).name)
    os._exit(128 + signum)  # idle: nothing to clean up


def _set_parent_death_signal() -> bool:
    """Linux: have the kernel SIGKILL this process when its parent dies. Called in the
    worker itself; the kernel ties it to the driver thread that started the worker (the one
    that called submit), which lives as long as the batch. False where unavailable."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        PR_SET_PDEATHSIG = 1
        return libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def watchdog(driver: int) -> None:
    """Stop this worker once its parent is no longer `driver`: the portable backstop for
    the parent-death signal (a worker whose driver is gone is reparented, so its parent pid
    changes). Runs in a daemon thread of each local worker; never returns."""
    while os.getppid() == driver:
        time.sleep(WATCHDOG_S)
    os.kill(os.getpid(), signal.SIGTERM)  # unwind a running job as a stop would
    time.sleep(STOP_GRACE_S)
    os._exit(1)


def _init_worker(cuda_visible: str | None, driver: int | None = None) -> None:
    # Pin a GPU worker to its device before torch/warp see CUDA; CPU workers see none, so
    # that `--device auto` in a CPU worker means CPU.
    if cuda_visible is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = cuda_visible
    if driver is None:
        return
    _WORKER["driver"] = driver
    # Ctrl-C in a terminal reaches the whole process group; the driver alone decides how
    # the workers stop (SIGTERM, then a grace period), so a worker never starts a queued
    # job while the driver is shutting down.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_stop_signal)
    # tqdm's default lock is a multiprocessing one; made in a spawned worker it is registered
    # with the driver's resource tracker, which warns about it on stderr when a stopped or
    # killed worker could not unregister it. A worker's bars need only a thread lock.
    from tqdm import tqdm

    tqdm.set_lock(threading.RLock())
    _set_parent_death_signal()
    if os.getppid() != driver:  # the driver died before the signal was armed
        os._exit(1)
    threading.Thread(target=watchdog, args=(driver,), name="pdtool-batch-watchdog", daemon=True).start()


def run_job(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one job in this process through the frontend's `run`, output captured.

    spec: {'command', 'args', 'cwd', 'run' (CommandLines.run), 'threads'} and, from the local
    pool, 'driver' (the driver's pid: a job is not started once it is gone). Returns {'ok',
    'error', 'seconds', 'log', 'host', 'pid'}; `error` is one line (the frontend's own
    message for a user error). Module-level so that both process pools and Ray can pickle it.
    """

    t0 = time.perf_counter()

    def failed(error: str) -> dict[str, Any]:
        return {"ok": False, "seconds": 0.0, "log": [], "host": platform.node(), "pid": os.getpid(),
                "error": error}

    driver = spec.get("driver")
    if driver is not None and (_WORKER["stopping"] or os.getppid() != driver):
        return failed("not started: the batch was stopped")
    if not os.path.isdir(spec["cwd"]):  # a Ray node without the shared storage
        return failed(f"folder {spec['cwd']} does not exist on {platform.node()}; put the jobs file and "
                      "its inputs on storage every node mounts at the same path")
    arg = asks_for_help(spec["args"])
    if arg is not None:
        return failed(f"its args ask for {arg}, which prints help or version text instead of running the "
                      "command; remove it")
    os.chdir(spec["cwd"])
    threads = int(spec.get("threads") or 0)
    if threads > 0:
        import torch

        torch.set_num_threads(threads)

    buf = io.StringIO()
    error = None
    try:
        _WORKER["running"] = True
        with _capture_fds() as native, contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
            try:
                error = spec["run"](spec["command"], list(spec["args"]))
            except SystemExit as e:  # a library calling sys.exit must not end the worker
                if e.code not in (0, None):
                    error = f"exited with code {e.code}"
            except PdToolError as e:
                error = str(e)
            except Exception as e:  # a bug, not a user error: still one line, and the others go on
                error = f"{type(e).__name__}: {e}"
    except WorkerStopped:
        # The job's with-blocks removed their temporaries on the way here; a writer left to
        # its finalizer goes with the collection. Then this worker ends: the pool may hold
        # queued jobs, and none may start.
        gc.collect()
        with contextlib.suppress(BaseException):
            atexit._run_exitfuncs()  # what a normal exit runs: weakref finalizers, multiprocessing's
        os._exit(143)
    finally:
        _WORKER["running"] = False
    if _WORKER["stopping"]:  # the stop was swallowed somewhere inside the job: end anyway
        os._exit(143)
    log = native.read().splitlines() + buf.getvalue().splitlines()
    return {"ok": error is None, "error": None if error is None else one_line(error),
            "seconds": time.perf_counter() - t0, "log": [one_line(s) for s in log[-20:]],
            "host": platform.node(), "pid": os.getpid()}


_CAPTURE_TAIL = 64 << 10  # bytes of a job's own output kept for its log


@contextlib.contextmanager
def _capture_fds():
    """Send file descriptors 1 and 2 to a temporary file for the block (native libraries
    such as warp print there, past sys.stdout); yields a buffer that holds its last 64 kB
    afterwards."""

    out = io.StringIO()
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    with tempfile.TemporaryFile() as cap:
        os.dup2(cap.fileno(), 1)
        os.dup2(cap.fileno(), 2)
        try:
            yield out
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            size = cap.seek(0, os.SEEK_END)
            cap.seek(max(0, size - _CAPTURE_TAIL))
            out.write(cap.read().decode("utf-8", "replace"))
            out.seek(0)


# ------------------------------------------------------------------------------ backends


def count_gpus() -> int:
    """CUDA devices visible to this process (0 without torch's CUDA build)."""
    try:
        import torch

        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except Exception:
        return 0


def stop_processes(procs: list[Any], grace: float = STOP_GRACE_S) -> None:
    """SIGTERM each multiprocessing Process, give them `grace` seconds to unwind their jobs,
    then SIGKILL the rest; returns once all have ended (or 5 s after the kill)."""

    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    pending = {p.sentinel: p for p in procs}
    deadline = time.monotonic() + grace
    while pending and time.monotonic() < deadline:
        for s in wait_for(list(pending), timeout=max(0.0, deadline - time.monotonic())):
            pending.pop(s, None)
    for p in pending.values():
        with contextlib.suppress(Exception):
            p.kill()
    if pending:
        wait_for(list(pending), timeout=5.0)


def _start_resource_tracker_quietly() -> None:
    """Start multiprocessing's resource tracker (the process that unlinks the pool's
    semaphores once their owners are gone) with stderr on /dev/null. After a SIGKILL of the
    driver it cleans up as it should, but also warns about "leaked semaphore objects" on
    the terminal the user killed the batch from. Nothing to do when it already runs."""

    with native_stderr_silenced():
        resource_tracker.ensure_running()


class LocalBackend:
    """Spawned worker processes: `workers` for CPU jobs plus one per GPU for CUDA jobs.

    threads: torch threads per CPU job (default 1).

    A job goes to the GPU workers when it asks for `--device cuda`, or for `auto` while a GPU
    is visible; everything else to the CPU workers. Each worker keeps torch/warp (and warp's
    loaded kernels) between jobs. One torch thread per CPU job.

    Workers end with the driver: on Linux the kernel kills them when the thread that
    submitted their first job ends (a parent-death signal; use the backend from a thread
    that outlives it), and everywhere a watchdog thread in each worker ends it once its
    parent is gone. A worker ignores SIGINT; `close(cancel=True)` stops it with SIGTERM,
    which unwinds the running job (its temporaries are removed), then SIGKILL after
    STOP_GRACE_S.
    """

    def __init__(self, workers: int | None = None, gpus: int | None = None, threads: int | None = None) -> None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        self.workers = max(1, workers or cores)
        self.gpus = count_gpus() if gpus is None else gpus
        # One torch thread per job by default: a sweep is parallel across jobs, and OpenMP
        # threads of several jobs fighting for the same cores made tiny bakes ~7x slower
        # (docs/batch.md).
        self.threads = threads or 1
        ctx = mp.get_context("spawn")  # fork after torch/warp init is unsafe; spawn is the same everywhere
        _start_resource_tracker_quietly()  # before the pools make their queues' semaphores
        me = os.getpid()
        self.cpu = cf.ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker, initargs=("", me))
        self.gpu = [cf.ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker, initargs=(str(i), me))
                    for i in range(self.gpus)]
        self._rr = 0
        self.name = f"local ({self.workers} CPU worker{'s' * (self.workers != 1)}, {self.gpus} GPU)"

    def route(self, job: Job) -> int | None:
        """Index of the GPU worker a job goes to, or None for the CPU workers."""
        if self.gpus > 0 and job.device in ("cuda", "auto"):
            self._rr += 1
            return (self._rr - 1) % self.gpus
        return None

    def submit(self, job: Job, run: Callable[[str, list[str]], str | None]) -> cf.Future:
        gpu = self.route(job)
        spec = {"command": job.command, "args": list(job.args), "cwd": job.cwd, "run": run,
                "threads": self.threads, "driver": os.getpid()}
        return (self.cpu if gpu is None else self.gpu[gpu]).submit(run_job, spec)

    def wait(self, handles: Iterable[cf.Future]) -> list[tuple[cf.Future, dict[str, Any]]]:
        done, _ = cf.wait(list(handles), return_when=cf.FIRST_COMPLETED)
        out = []
        for f in done:
            try:
                out.append((f, f.result()))
            except Exception as e:  # the worker process died (killed, out of memory)
                out.append((f, {"ok": False, "error": one_line(f"worker died: {type(e).__name__}: {e}"),
                                "seconds": 0.0, "log": []}))
        return out

    def close(self, cancel: bool = False, handles: Iterable[Any] = ()) -> None:
        pools = [self.cpu, *self.gpu]
        if cancel:
            # Stop the running jobs now rather than wait for them; each unwinds and removes
            # its temporaries. Queued jobs never start: a stopped worker exits.
            stop_processes([proc for p in pools for proc in list((getattr(p, "_processes", None) or {}).values())])
        # shutdown() drops the pools' references to their manager threads and wake-up pipes,
        # so they are taken first
        managers = [(getattr(p, "_executor_manager_thread", None), getattr(p, "_executor_manager_thread_wakeup", None))
                    for p in pools]
        for p in pools:
            p.shutdown(wait=not cancel, cancel_futures=cancel)
        if cancel:
            # Let each pool's manager thread finish closing its wake-up pipe now: at exit,
            # Python 3.11's concurrent.futures wakes it without a lock and can hit the pipe
            # while the thread closes it ("OSError: Bad file descriptor" on stderr). On a
            # busy machine the thread can outlast the wait, so that late wake-up is also
            # told to ignore a pipe closed under it.
            for thread, wakeup in managers:
                _quiet_wakeup(wakeup)
                if thread is not None:
                    thread.join(timeout=STOP_GRACE_S)


def _quiet_wakeup(wakeup: Any) -> None:
    """Make a concurrent.futures wake-up pipe's wakeup() ignore the pipe being closed under
    it by its manager thread (the exit-time race above)."""
    if wakeup is None or not hasattr(wakeup, "wakeup"):
        return
    loud = wakeup.wakeup

    def wake() -> None:
        try:
            loud()
        except OSError:  # closed meanwhile: the thread it would wake has finished
            pass

    wakeup.wakeup = wake


def ray_resources(job: Job, cluster_gpus: int, cpus_per_job: float = 1.0) -> dict[str, float]:
    """Ray task resources for a job: one GPU when it asks for --device cuda, or for auto (the
    CLI default) on a cluster that has GPUs; none otherwise."""
    on_gpu = job.device == "cuda" or (job.device == "auto" and cluster_gpus > 0)
    return {"num_cpus": cpus_per_job, "num_gpus": 1 if on_gpu else 0}


def _probe(address: str | None) -> None:
    """For a HOST:PORT address, one TCP connection first: Ray itself retries an address
    that nobody listens on for minutes, logging to stderr all the while."""

    if address in (None, "auto", "local") or "://" in address or ":" not in address:
        return
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=10).close()
    except ValueError:
        raise PdToolError(f"--ray {address}: not an address; give HOST:PORT (e.g. head:6379), ray://HOST:10001, "
                          "auto or local") from None
    except OSError as e:
        raise PdToolError(f"--ray {address}: cannot connect ({e.strerror or e}); start a cluster there with "
                          "`ray start --head`, or pass its address") from None


class RayBackend:
    """One Ray task per job on a Ray cluster (`address`: 'auto', 'ray://host:10001', 'host:6379',
    or 'local' for a fresh single-node cluster). A CUDA job, or an `auto` one while the cluster
    has GPUs, asks for `num_gpus=1`; Ray then sets CUDA_VISIBLE_DEVICES for it. Uses an
    already-initialised Ray session as it is. Every node must have pdtool installed and see
    the job's files at the same paths (shared storage)."""

    def __init__(self, address: str | None = "auto", cpus_per_job: float = 1.0) -> None:
        try:
            import ray
        except ImportError:
            raise PdToolError("--ray needs Ray: pip install 'pdtool[ray]' (or pip install ray)") from None
        self.ray = ray
        self._owns = False
        if not ray.is_initialized():
            _probe(address)
            try:
                # Ray logs its connection attempts to stderr (a line a second while it retries);
                # a refusal must be one line, and a success needs none.
                with _capture_fds():
                    if address == "local":
                        ray.init(include_dashboard=False, log_to_driver=False)
                    else:
                        ray.init(address=address, log_to_driver=False)
            except (ConnectionError, RuntimeError, ValueError) as e:
                raise PdToolError(f"--ray {address}: cannot connect ({' '.join(str(e).split())[:200]}); "
                                  "start one with `ray start --head`, or pass its address") from None
            self._owns = True
        res = ray.cluster_resources()
        self.cluster_gpus = int(res.get("GPU", 0))
        self.cpus_per_job = cpus_per_job
        self._task = ray.remote(max_retries=0)(run_job)
        self.name = (f"ray ({int(res.get('CPU', 0))} CPU, {self.cluster_gpus} GPU, "
                     f"{len(ray.nodes())} node{'s' * (len(ray.nodes()) != 1)})")

    def submit(self, job: Job, run: Callable[[str, list[str]], str | None]):
        spec = {"command": job.command, "args": list(job.args), "cwd": job.cwd, "run": run,
                "threads": max(1, int(self.cpus_per_job))}
        return self._task.options(**ray_resources(job, self.cluster_gpus, self.cpus_per_job)).remote(spec)

    def wait(self, handles: Iterable[Any]) -> list[tuple[Any, dict[str, Any]]]:
        ray = self.ray
        done, _ = ray.wait(list(handles), num_returns=1)
        out = []
        for ref in done:
            try:
                out.append((ref, ray.get(ref)))
            except Exception as e:  # the task's worker died, or the node went away
                out.append((ref, {"ok": False, "error": one_line(f"ray: {type(e).__name__}: {e}", 300),
                                  "seconds": 0.0, "log": []}))
        return out

    def close(self, cancel: bool = False, handles: Iterable[Any] = ()) -> None:
        if cancel:
            # First a KeyboardInterrupt inside each task, so that its outputs unwind and remove
            # their temporaries; after STOP_GRACE_S the task's worker is killed.
            refs = list(handles)
            for ref in refs:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref, force=False)
            if refs:
                with contextlib.suppress(Exception):
                    self.ray.wait(refs, num_returns=len(refs), timeout=STOP_GRACE_S)
            for ref in refs:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref, force=True)
        if self._owns:
            self.ray.shutdown()
