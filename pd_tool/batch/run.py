"""The scheduler: `run_batch` starts each job once the jobs it waits for have finished,
records the results (`JobResult`, `BatchResult` and its table, the JSON summary) and stops
the workers on Ctrl-C or SIGTERM.
"""
from __future__ import annotations

import contextlib
import json
import signal
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

from pd_tool.batch.files import (
    CommandLines,
    JobFiles,
    check_outputs,
    clash,
    fingerprint,
    is_up_to_date,
    job_files,
    outside,
    outside_message,
    record_path,
    remove_temporaries,
    write_record,
)
from pd_tool.batch.jobs import Job, JobsFileError, asks_for_help, help_error, one_line
from pd_tool.batch.workers import LocalBackend, RayBackend
from pd_tool.core.atomic import atomic_output
from pd_tool.core.errors import PdToolError

# Terminal states of a job. "up-to-date": skipped by --resume; "blocked": a job it waits
# for failed, so it never ran.
OK, FAILED, BLOCKED, UP_TO_DATE = "ok", "failed", "blocked", "up-to-date"


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM reached the driver while the jobs ran; `signum` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


@dataclass
class JobResult:
    """How one job ended. status: ok | failed | blocked | up-to-date; seconds: wall time in
    the worker (0 unless it ran); outputs: absolute paths; error: one line or None."""

    name: str
    command: str
    status: str
    seconds: float = 0.0
    outputs: list[str] = field(default_factory=list)
    error: str | None = None
    fingerprint: str | None = None
    log: list[str] = field(default_factory=list)
    worker: str | None = None  # "host:pid" of the process that ran it


@dataclass
class BatchResult:
    """All jobs' results in file order, plus the backend's description and wall time, s."""

    jobs: list[JobResult]
    backend: str
    seconds: float

    def counts(self) -> dict[str, int]:
        c = {OK: 0, FAILED: 0, BLOCKED: 0, UP_TO_DATE: 0}
        for r in self.jobs:
            c[r.status] += 1
        return c

    @property
    def ok(self) -> bool:
        """True when no job failed or was blocked."""
        c = self.counts()
        return c[FAILED] == 0 and c[BLOCKED] == 0

    def to_json(self) -> dict[str, Any]:
        return {"backend": self.backend, "seconds": round(self.seconds, 3), "counts": self.counts(),
                "jobs_per_minute": round(60 * self.counts()[OK] / self.seconds, 3) if self.seconds > 0 else None,
                "jobs": [asdict(r) for r in self.jobs]}

    def table(self) -> str:
        """The summary table, one line per job."""
        w = max([4, *(len(r.name) for r in self.jobs)])
        lines = [f"{'job':<{w}}  {'status':<10}  {'time':>7}  output / error"]
        for r in self.jobs:
            t = f"{r.seconds:6.1f}s" if r.seconds else "      -"
            what = r.error if r.error else (r.outputs[0] if r.outputs else "")
            lines.append(f"{r.name:<{w}}  {r.status:<10}  {t}  {what}")
        c = self.counts()
        lines.append(f"{len(self.jobs)} jobs: {c[OK]} ok, {c[FAILED]} failed, {c[BLOCKED]} blocked, "
                     f"{c[UP_TO_DATE]} up to date; {self.seconds:.1f} s on {self.backend}")
        return "\n".join(lines)


def write_summary(result: BatchResult, path: str | Path) -> Path:
    """Write `result.to_json()` to `path`, atomically. Raises OutputError (one line, no
    temporary left) when the destination cannot take it."""
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(result.to_json(), indent=2))
    return path


@contextlib.contextmanager
def _driver_signals():
    """SIGTERM, and Ctrl-C where Python's default handler has it, raise BatchInterrupted in
    the driver, so that both stop the batch the same way (only in the main thread, where
    Python runs signal handlers)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum: int, frame: Any) -> None:
        raise BatchInterrupted(signum)

    old = {signal.SIGTERM: signal.signal(signal.SIGTERM, on_signal)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        old[signal.SIGINT] = signal.signal(signal.SIGINT, on_signal)
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextlib.contextmanager
def _signals_held():
    """Ignore Ctrl-C and SIGTERM for the block: a second one must not cut the stop short
    (it lasts at most STOP_GRACE_S plus a few seconds)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.signal(s, signal.SIG_IGN) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def run_batch(jobs: list[Job], commands: CommandLines, *, workers: int | None = None, ray_address: str | None = None,
              resume: bool = False, echo: Callable[[str], None] | None = None,
              show_progress: bool = True, backend: Any = None, allow_outside: bool = False) -> BatchResult:
    """Run `jobs` respecting their `after` edges; return every job's result.

    workers: CPU worker processes (default: the CPU count). ray_address: run on Ray instead
    (see RayBackend). resume: skip jobs whose outputs exist with a matching fingerprint
    record. echo: where per-job status lines go (default: above the progress bar).
    allow_outside: let jobs write outside their jobs file's folder (refused otherwise, with
    a JobsFileError before anything runs).
    A failed job never stops the others; the jobs that wait for it end as 'blocked'.

    Ctrl-C or SIGTERM while the jobs run stops the running jobs, removes their temporaries
    and raises BatchInterrupted (a KeyboardInterrupt); finished jobs keep their outputs and
    records.
    """
    t0 = time.perf_counter()
    results: dict[str, JobResult] = {}
    # Everything that can refuse the batch comes before the backend and the bar, so that a
    # refusal is one line.
    check_outputs(jobs, commands, allow_outside)
    if backend is None:
        backend = RayBackend(ray_address) if ray_address else LocalBackend(workers)
    bar = None
    if show_progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(jobs), desc="batch", unit="job", dynamic_ncols=True, file=sys.stderr)
    say = echo or ((lambda s: bar.write(s, file=sys.stderr)) if bar is not None else print)

    def finish(r: JobResult) -> None:
        results[r.name] = r
        n = len(results)
        detail = r.error if r.error else (f"{r.seconds:.1f} s  {r.outputs[0]}" if r.outputs else f"{r.seconds:.1f} s")
        say(f"[{n}/{len(jobs)}] {r.status:<10} {r.name}  {detail}")
        if bar is not None:
            bar.update(1)

    def failed(job: Job, error: str) -> None:
        finish(JobResult(job.name, job.command, FAILED, error=one_line(error)))

    in_flight: dict[Any, tuple[Job, JobFiles, str | None]] = {}
    writers: dict[Path, str] = {}  # path -> the job that writes it
    folders: dict[Path, str] = {}  # output folder -> the job that writes it
    waiting = list(jobs)
    try:
        with _driver_signals():
            while waiting or in_flight:
                still = []
                for job in waiting:
                    deps = [results.get(d) for d in job.after]
                    if any(d is None for d in deps):
                        still.append(job)
                        continue
                    bad = [d.name for d in deps if d.status in (FAILED, BLOCKED)]
                    if bad:
                        finish(JobResult(job.name, job.command, BLOCKED,
                                         error=one_line(f"waits for {', '.join(bad)}, which did not finish")))
                        continue
                    arg = asks_for_help(job.args)
                    if arg is not None:
                        failed(job, help_error(job, arg))
                        continue
                    files = job_files(job, commands)  # inputs made by earlier jobs exist now
                    away = [] if allow_outside else outside(files, job.cwd)
                    if away:  # a symlink changed since the start
                        failed(job, outside_message(job, away[0]))
                        continue
                    c = clash(files, writers, folders)
                    if c is not None:  # two jobs renaming onto one file: the last one would silently win
                        failed(job, f"writes {c[0]}, which job {c[1]} also writes; give each job its own "
                                    "output (e.g. out/{name}.usd)")
                        continue
                    writers.update({p: job.name for p in files.written()})
                    folders.update({p: job.name for p in files.folders})
                    try:
                        for p in files.outputs:  # templated outputs often go to new folders
                            p.parent.mkdir(parents=True, exist_ok=True)
                    except OSError as e:
                        failed(job, f"cannot create the folder for {p} ({e.strerror or e}); choose a writable folder")
                        continue
                    fp = fingerprint(job, files) if files.parsed else None
                    if resume and fp is not None and is_up_to_date(files, fp):
                        finish(JobResult(job.name, job.command, UP_TO_DATE, outputs=[str(p) for p in files.outputs],
                                         fingerprint=fp))
                        continue
                    in_flight[backend.submit(job, commands.run)] = (job, files, fp)
                    say(f"start {job.name}")
                waiting = still
                if not in_flight:
                    if waiting:  # unreachable after the cycle check; guard against a silent hang
                        raise JobsFileError(f"jobs {', '.join(j.name for j in waiting)} can never start")
                    break
                for handle, res in backend.wait(in_flight):
                    job, files, fp = in_flight.pop(handle)
                    r = JobResult(job.name, job.command, OK if res["ok"] else FAILED, seconds=res["seconds"],
                                  outputs=[str(p) for p in files.outputs], error=res["error"], fingerprint=fp,
                                  log=res.get("log", []),
                                  worker=f"{res['host']}:{res['pid']}" if "pid" in res else None)
                    if r.status == OK and fp is not None:
                        try:
                            write_record(job, files, fp, r.seconds)
                        except (OSError, PdToolError) as e:
                            r.status = FAILED
                            r.error = one_line(f"wrote its outputs, but not its --resume record {record_path(files)} "
                                            f"({getattr(e, 'strerror', None) or e}); free some space or make the "
                                            "folder writable")
                    finish(r)
            backend.close()
    except BaseException:  # Ctrl-C, SIGTERM, or a bug here: stop the running jobs, then re-raise
        with _signals_held():
            backend.close(cancel=True, handles=list(in_flight))
            # The workers have stopped: what a killed one could not remove goes now.
            remove_temporaries(files for _, files, _ in in_flight.values())
            if bar is not None:
                bar.close()
        raise
    if bar is not None:
        bar.close()
    return BatchResult([results[j.name] for j in jobs if j.name in results], backend.name, time.perf_counter() - t0)
