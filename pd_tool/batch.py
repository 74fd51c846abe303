"""`pdtool batch`: many bake/fit jobs from one TOML file, on a local process pool or a Ray cluster.

A job is a pdtool command line. The worker runs the very same click command in-process
(`cli.main.main([command, *args], standalone_mode=False)`), so a batch job and a typed
command take one code path: same option checks, same defaults, same atomic outputs, same
one-line errors. The scheduler here only decides *when* and *where* a job runs:

- jobs file: `[[job]]` tables, sweeps expanded into a cartesian product, `after` edges;
- fingerprints: sha256 over the job's command line and the bytes of every input file it
  names, kept in a small `<output>.batch.json` record beside the job's main output so that
  `--resume` skips the jobs that are already done with the same inputs;
- backends: `LocalBackend` (spawned processes, one per CPU worker plus one per visible GPU)
  and `RayBackend` (one Ray task per job, `num_gpus=1` when the job runs on CUDA).

See docs/batch.md for the file format, the Ray set-up and measured throughput.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import hashlib
import io
import itertools
import json
import multiprocessing as mp
import os
import re
import string
import sys
import time
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from pd_tool.atomic import atomic_output
from pd_tool.errors import PdToolError

COMMANDS = ("bake", "fit")
JOB_KEYS = {"name", "command", "args", "after", "sweep"}
RECORD_SUFFIX = ".batch.json"
# Terminal states of a job. "up-to-date": skipped by --resume; "blocked": a job it waits
# for failed, so it never ran.
OK, FAILED, BLOCKED, UP_TO_DATE = "ok", "failed", "blocked", "up-to-date"


class JobsFileError(PdToolError):
    """The jobs file is unreadable or inconsistent (unknown key, bad sweep, cycle...)."""


# ----------------------------------------------------------------------------- jobs file


@dataclass(frozen=True)
class Job:
    """One command line to run.

    name: unique, file-safe. command: 'bake' | 'fit'. args: the arguments after the
    command, exactly as typed. after: names of jobs that must finish first. cwd: the
    folder relative paths in args are read from (the jobs file's folder). table: the
    `name` of the [[job]] table it was expanded from (a sweep's base name).
    """

    name: str
    command: str
    args: tuple[str, ...]
    after: tuple[str, ...] = ()
    cwd: str = "."
    table: str = ""

    @property
    def device(self) -> str:
        """The --device the command line asks for: 'auto' (the CLI default), 'cpu' or 'cuda'."""
        dev = "auto"
        for i, a in enumerate(self.args):
            if a == "--device" and i + 1 < len(self.args):
                dev = self.args[i + 1]
            elif a.startswith("--device="):
                dev = a.split("=", 1)[1]
        return dev


def slug(value: Any) -> str:
    """A file-name-safe form of a sweep value: '0,0,1' -> '0_0_1', 'my preset.toml' -> 'my_preset.toml'."""
    return re.sub(r"[^A-Za-z0-9.+-]+", "_", str(value)).strip("_") or "_"


class _Formatter(string.Formatter):
    """str.format with one extra spec, `{key:slug}`, for sweep values inside file names."""

    def format_field(self, value: Any, format_spec: str) -> str:
        if format_spec == "slug":
            return slug(value)
        return super().format_field(value, format_spec)


_FMT = _Formatter()


def _fill(template: str, values: dict[str, Any], where: str) -> str:
    try:
        return _FMT.vformat(template, (), values)
    except KeyError as e:
        known = ", ".join(sorted(values)) or "none"
        raise JobsFileError(f"{where}: unknown placeholder {{{e.args[0]}}} (known: {known}); "
                            "write {{ and }} for literal braces") from None
    except (ValueError, IndexError) as e:
        raise JobsFileError(f"{where}: bad placeholder in {template!r} ({e}); write {{{{ and }}}} for "
                            "literal braces") from None


def _scalar(v: Any) -> bool:
    return isinstance(v, (str, int, float, bool)) and not isinstance(v, dict)


def parse_jobs(data: dict[str, Any], cwd: str | Path = ".", source: str = "jobs file") -> list[Job]:
    """Expand the `[[job]]` tables of a parsed jobs file into Jobs, in file order.

    Sweeps: `[job.sweep]` maps a key to a list of values; the table expands into one job per
    combination (cartesian product, keys in file order, the last key varying fastest). In
    `name`, `{key}` is the value's slug; if the name has no placeholder the slugs are
    appended (`poke` -> `poke_flower_0_0_1`). In `args` and `after`, `{key}` is the raw value,
    `{key:slug}` its slug and `{name}` the expanded job name. Raises JobsFileError.
    """
    extra = set(data) - {"job"}
    if extra:
        raise JobsFileError(f"{source}: unknown top-level key(s) {', '.join(sorted(extra))}; "
                            "only [[job]] tables are read")
    tables = data.get("job")
    if not isinstance(tables, list) or not tables:
        raise JobsFileError(f"{source}: no [[job]] tables; see `pdtool batch --help` for the format")
    cwd = str(Path(cwd).resolve())
    jobs: list[Job] = []
    for i, t in enumerate(tables):
        where = f"{source}: job #{i + 1}"
        if not isinstance(t, dict):
            raise JobsFileError(f"{where}: must be a [[job]] table")
        unknown = set(t) - JOB_KEYS
        if unknown:
            raise JobsFileError(f"{where}: unknown key(s) {', '.join(sorted(unknown))} "
                                f"(allowed: {', '.join(sorted(JOB_KEYS))})")
        name = t.get("name")
        if not isinstance(name, str) or not name.strip():
            raise JobsFileError(f"{where}: needs name = \"...\"")
        where = f"{source}: job {name!r}"
        command = t.get("command")
        if command not in COMMANDS:
            raise JobsFileError(f"{where}: command must be one of {', '.join(COMMANDS)}, got {command!r}")
        args = t.get("args", [])
        if not isinstance(args, list) or not all(_scalar(a) for a in args):
            raise JobsFileError(f"{where}: args must be a list of strings, as on the command line")
        after = t.get("after", [])
        if isinstance(after, str):
            after = [after]
        if not isinstance(after, list) or not all(isinstance(a, str) for a in after):
            raise JobsFileError(f"{where}: after must be a list of job names")
        sweep = t.get("sweep", {})
        if not isinstance(sweep, dict):
            raise JobsFileError(f"{where}: sweep must be a table of key = [values]")
        for k, vals in sweep.items():
            if k == "name" or not k.isidentifier():
                raise JobsFileError(f"{where}: sweep key {k!r} must be an identifier other than 'name'")
            if not isinstance(vals, list) or not vals or not all(_scalar(v) for v in vals):
                raise JobsFileError(f"{where}: sweep.{k} must be a non-empty list of values")
        keys = list(sweep)
        for combo in itertools.product(*(sweep[k] for k in keys)):
            raw = {k: str(v) if not isinstance(v, bool) else str(v).lower() for k, v in zip(keys, combo)}
            slugs = {k: slug(v) for k, v in raw.items()}
            if keys and "{" not in name:
                job_name = "_".join([name, *slugs.values()])
            else:
                job_name = _fill(name, slugs, f"{where} name")
            values = {**raw, "name": job_name}
            jobs.append(Job(
                name=job_name, command=command,
                args=tuple(_fill(str(a).lower() if isinstance(a, bool) else str(a), values, f"{where} args")
                           for a in args),
                after=tuple(_fill(a, {**slugs, "name": job_name}, f"{where} after") for a in after),
                cwd=cwd, table=name,
            ))
    return _resolve_after(jobs, source)


def _resolve_after(jobs: list[Job], source: str) -> list[Job]:
    """Check names are unique, map `after` entries (a job name or a sweep's base name) to
    job names, and reject cycles."""
    names: dict[str, Job] = {}
    for j in jobs:
        if j.name in names:
            raise JobsFileError(f"{source}: two jobs are named {j.name!r}; give sweeps placeholders in name")
        names[j.name] = j
    by_table: dict[str, list[str]] = {}
    for j in jobs:
        by_table.setdefault(j.table, []).append(j.name)
    out = []
    for j in jobs:
        deps: list[str] = []
        for a in j.after:
            hit = [a] if a in names else by_table.get(a, [])
            if not hit:
                raise JobsFileError(f"{source}: job {j.name!r} waits for {a!r}, which is no job name")
            deps += [h for h in hit if h not in deps]
        if j.name in deps:
            raise JobsFileError(f"{source}: job {j.name!r} waits for itself")
        out.append(Job(**{**asdict(j), "after": tuple(deps)}))
    # Cycle check (Kahn): every job must become ready at some point.
    remaining = {j.name: set(j.after) for j in out}
    while remaining:
        ready = [n for n, d in remaining.items() if not d]
        if not ready:
            raise JobsFileError(f"{source}: the after= edges form a cycle among "
                                f"{', '.join(sorted(remaining))}")
        for n in ready:
            del remaining[n]
        for d in remaining.values():
            d.difference_update(ready)
    return out


def load_jobs(path: str | Path) -> list[Job]:
    """Read a TOML jobs file; relative paths in its jobs are relative to its folder."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise JobsFileError(f"{path}: no such jobs file") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise JobsFileError(f"{path}: not valid TOML ({e}); fix the file") from None
    except OSError as e:
        raise JobsFileError(f"{path}: unreadable ({e.strerror})") from None
    return parse_jobs(data, cwd=path.resolve().parent, source=str(path))


# ----------------------------------------------------------------------- inputs, outputs


@dataclass
class JobFiles:
    """What a job reads and writes, as absolute paths. `outputs[0]` is its main output
    (the record sits beside it). `parsed` is False when the command line does not parse;
    the job then runs (and fails with the CLI's own message) but cannot be resumed."""

    inputs: list[Path] = field(default_factory=list)
    outputs: list[Path] = field(default_factory=list)
    parsed: bool = True


# Options whose value is a preset name or a file: only a file is an input.
_NAME_OR_FILE = {"preset", "interaction", "quality"}
_OUTPUTS = {"bake": ("out", "preview", "frames_out"), "fit": ("out",)}


def job_files(job: Job) -> JobFiles:
    """Split a job's paths into inputs and outputs by parsing its args with the CLI's own
    click command (no option table is duplicated here)."""
    import click

    import cli

    cwd = Path(job.cwd)
    cmd = cli.main.commands[job.command]
    try:
        # click checks exists=True paths against the process's folder: parse from the job's.
        with contextlib.chdir(cwd), contextlib.redirect_stderr(io.StringIO()):
            ctx = cmd.make_context(job.command, list(job.args), resilient_parsing=True)
        params = dict(ctx.params)
    except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort):
        return JobFiles(parsed=False)

    def absolute(p: Any) -> Path:
        p = Path(p)
        return p if p.is_absolute() else cwd / p

    outs: list[Path] = []
    for key in _OUTPUTS[job.command]:
        if params.get(key) is not None:
            outs.append(absolute(params[key]))
    if job.command == "fit" and params.get("out") is None and params.get("scene") is not None:
        outs.insert(0, absolute(params["scene"]).with_suffix(".pdmat"))  # the CLI's default
    ins: list[Path] = []
    for key, value in params.items():
        if key in _OUTPUTS[job.command] or value is None:
            continue
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(v, Path) or key in _NAME_OR_FILE:
                p = absolute(v)
                if p.exists():
                    ins.append(p)
    if job.command == "bake" and params.get("material") is None and params.get("preset") is None:
        from pd_tool.material_file import RECORD_PATH

        ins.append(cwd / RECORD_PATH)  # a bare `bake` uses the folder's last fit
    return JobFiles(inputs=ins, outputs=outs, parsed=bool(outs))


_DIGESTS: dict[tuple[str, int, int], bytes] = {}


def file_digest(p: Path) -> bytes:
    """sha256 of one file's bytes, cached by (path, size, mtime): a sweep of 100 bakes of one
    large scene reads it once, and a file rewritten in between is read again."""
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(p, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
        _DIGESTS[key] = h.digest()
    return _DIGESTS[key]


def _hash_path(h: "hashlib._Hash", p: Path) -> None:
    if p.is_dir():
        for f in sorted(q for q in p.rglob("*") if q.is_file()):
            _hash_path(h, f)
        return
    h.update(str(p).encode() + b"\0")
    h.update(file_digest(p) if p.is_file() else b"<missing>")


def fingerprint(job: Job, files: JobFiles) -> str:
    """sha256 (hex) of the command, its args and the bytes of every input file (folders:
    every file inside, sorted)."""
    h = hashlib.sha256()
    h.update(json.dumps([job.command, list(job.args)]).encode())
    for p in sorted(set(files.inputs)):
        _hash_path(h, p)
    return h.hexdigest()


def record_path(files: JobFiles) -> Path:
    """`<main output>.batch.json`: the small record --resume reads."""
    main = files.outputs[0]
    return main.with_name(main.name + RECORD_SUFFIX)


def is_up_to_date(files: JobFiles, fp: str) -> bool:
    """All outputs exist and the record beside them holds this fingerprint."""
    if not files.parsed or not all(p.exists() for p in files.outputs):
        return False
    try:
        return json.loads(record_path(files).read_text()).get("fingerprint") == fp
    except (OSError, ValueError, AttributeError):
        return False


def write_record(job: Job, files: JobFiles, fp: str, seconds: float) -> Path:
    """Write the --resume record beside the job's main output, atomically."""
    path = record_path(files)
    rec = {"job": job.name, "command": job.command, "args": list(job.args), "fingerprint": fp,
           "inputs": [str(p) for p in files.inputs], "outputs": [str(p) for p in files.outputs],
           "seconds": round(seconds, 3), "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(rec, indent=2))
    return path


# ------------------------------------------------------------------------------- worker


def run_job(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one job in this process: the click command itself, output captured.

    spec: {'command', 'args', 'cwd', 'threads'}. Returns {'ok', 'error', 'seconds', 'log',
    'host', 'pid'}; `error` is one line (the CLI's own message for a user error).
    Module-level so that both process pools and Ray can pickle it.
    """
    import platform

    import click

    t0 = time.perf_counter()
    if not os.path.isdir(spec["cwd"]):  # a Ray node without the shared storage
        return {"ok": False, "seconds": 0.0, "log": [], "host": platform.node(), "pid": os.getpid(),
                "error": f"folder {spec['cwd']} does not exist on {platform.node()}; put the jobs file and "
                         "its inputs on storage every node mounts at the same path"}
    os.chdir(spec["cwd"])
    threads = int(spec.get("threads") or 0)
    if threads > 0:
        import torch

        torch.set_num_threads(threads)
    import cli

    buf = io.StringIO()
    error = None
    with _capture_fds() as native, contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf):
        try:
            rc = cli.main.main([spec["command"], *spec["args"]], prog_name="pdtool", standalone_mode=False)
            if isinstance(rc, int) and rc != 0:
                error = f"exited with code {rc}"
        except click.UsageError as e:
            error = " ".join(f"usage: {e.format_message()}".split())
        except click.ClickException as e:
            error = " ".join(e.format_message().split())
        except click.exceptions.Abort:
            error = "aborted"
        except SystemExit as e:  # a library calling sys.exit must not end the worker
            if e.code not in (0, None):
                error = f"exited with code {e.code}"
        except PdToolError as e:
            error = " ".join(str(e).split())
        except Exception as e:  # a bug, not a user error: still one line, and the others go on
            error = " ".join(f"{type(e).__name__}: {e}".split())
    log = native.read().splitlines() + buf.getvalue().splitlines()
    return {"ok": error is None, "error": error, "seconds": time.perf_counter() - t0,
            "log": log[-20:], "host": platform.node(), "pid": os.getpid()}


@contextlib.contextmanager
def _capture_fds():
    """Send file descriptors 1 and 2 to a temporary file for the block (native libraries
    such as warp print there, past sys.stdout); yields a buffer that holds it afterwards."""
    import tempfile

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
            cap.seek(0)
            out.write(cap.read().decode("utf-8", "replace"))
            out.seek(0)


def _init_worker(cuda_visible: str | None) -> None:
    # Pin a GPU worker to its device before torch/warp see CUDA; CPU workers see none, so
    # that `--device auto` in a CPU worker means CPU.
    if cuda_visible is not None:
        os.environ["CUDA_VISIBLE_DEVICES"] = cuda_visible


# ------------------------------------------------------------------------------ backends


def count_gpus() -> int:
    """CUDA devices visible to this process (0 without torch's CUDA build)."""
    try:
        import torch

        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except Exception:
        return 0


class LocalBackend:
    """Spawned worker processes: `workers` for CPU jobs plus one per GPU for CUDA jobs.

    threads: torch threads per CPU job (default 1).

    A job goes to the GPU workers when it asks for `--device cuda`, or for `auto` while a GPU
    is visible; everything else to the CPU workers. Each worker keeps torch/warp (and warp's
    loaded kernels) between jobs. One torch thread per CPU job.
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
        self.cpu = cf.ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker, initargs=("",))
        self.gpu = [cf.ProcessPoolExecutor(1, mp_context=ctx, initializer=_init_worker, initargs=(str(i),))
                    for i in range(self.gpus)]
        self._rr = 0
        self.name = f"local ({self.workers} CPU worker{'s' * (self.workers != 1)}, {self.gpus} GPU)"

    def route(self, job: Job) -> int | None:
        """Index of the GPU worker a job goes to, or None for the CPU workers."""
        if self.gpus > 0 and job.device in ("cuda", "auto"):
            self._rr += 1
            return (self._rr - 1) % self.gpus
        return None

    def submit(self, job: Job) -> cf.Future:
        gpu = self.route(job)
        spec = {"command": job.command, "args": list(job.args), "cwd": job.cwd,
                "threads": self.threads}
        return (self.cpu if gpu is None else self.gpu[gpu]).submit(run_job, spec)

    def wait(self, handles: Iterable[cf.Future]) -> list[tuple[cf.Future, dict[str, Any]]]:
        done, _ = cf.wait(list(handles), return_when=cf.FIRST_COMPLETED)
        out = []
        for f in done:
            try:
                out.append((f, f.result()))
            except Exception as e:  # the worker process died (killed, out of memory)
                out.append((f, {"ok": False, "error": " ".join(f"worker died: {type(e).__name__}: {e}".split()),
                                "seconds": 0.0, "log": []}))
        return out

    def close(self, cancel: bool = False, handles: Iterable[Any] = ()) -> None:
        for p in [self.cpu, *self.gpu]:
            if cancel:
                # Ctrl-C: stop running jobs now rather than wait for them (their outputs are
                # atomic, so nothing half-written stays behind).
                for proc in list(getattr(p, "_processes", {}).values()):
                    proc.terminate()
            p.shutdown(wait=not cancel, cancel_futures=cancel)


def ray_resources(job: Job, cluster_gpus: int, cpus_per_job: float = 1.0) -> dict[str, float]:
    """Ray task resources for a job: one GPU when it asks for --device cuda, or for auto (the
    CLI default) on a cluster that has GPUs; none otherwise."""
    on_gpu = job.device == "cuda" or (job.device == "auto" and cluster_gpus > 0)
    return {"num_cpus": cpus_per_job, "num_gpus": 1 if on_gpu else 0}


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
            try:
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

    def submit(self, job: Job):
        spec = {"command": job.command, "args": list(job.args), "cwd": job.cwd,
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
                out.append((ref, {"ok": False, "error": " ".join(f"ray: {type(e).__name__}: {e}".split())[:300],
                                  "seconds": 0.0, "log": []}))
        return out

    def close(self, cancel: bool = False, handles: Iterable[Any] = ()) -> None:
        if cancel:
            for ref in handles:
                with contextlib.suppress(Exception):
                    self.ray.cancel(ref, force=True)
        if self._owns:
            self.ray.shutdown()


# ----------------------------------------------------------------------------- scheduler


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
    """Write `result.to_json()` to `path`, atomically."""
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(result.to_json(), indent=2))
    return path


def run_batch(jobs: list[Job], *, workers: int | None = None, ray_address: str | None = None,
              resume: bool = False, echo: Callable[[str], None] | None = None,
              show_progress: bool = True, backend: Any = None) -> BatchResult:
    """Run `jobs` respecting their `after` edges; return every job's result.

    workers: CPU worker processes (default: the CPU count). ray_address: run on Ray instead
    (see RayBackend). resume: skip jobs whose outputs exist with a matching fingerprint
    record. echo: where per-job status lines go (default: above the progress bar).
    A failed job never stops the others; the jobs that wait for it end as 'blocked'.
    """
    t0 = time.perf_counter()
    results: dict[str, JobResult] = {}
    bar = None
    if show_progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(jobs), desc="batch", unit="job", dynamic_ncols=True, file=sys.stderr)
    say = echo or (bar.write if bar is not None else print)

    def finish(r: JobResult) -> None:
        results[r.name] = r
        n = len(results)
        detail = r.error if r.error else (f"{r.seconds:.1f} s  {r.outputs[0]}" if r.outputs else f"{r.seconds:.1f} s")
        say(f"[{n}/{len(jobs)}] {r.status:<10} {r.name}  {detail}")
        if bar is not None:
            bar.update(1)

    if backend is None:
        backend = RayBackend(ray_address) if ray_address else LocalBackend(workers)
    in_flight: dict[Any, tuple[Job, JobFiles, str | None]] = {}
    writers: dict[Path, str] = {}  # output path -> the job that writes it
    waiting = list(jobs)
    try:
        while waiting or in_flight:
            still = []
            for job in waiting:
                deps = [results.get(d) for d in job.after]
                if any(d is None for d in deps):
                    still.append(job)
                    continue
                bad = [d.name for d in deps if d.status in (FAILED, BLOCKED)]
                if bad:
                    finish(JobResult(job.name, job.command, BLOCKED, error=f"waits for {', '.join(bad)}, which did not finish"))
                    continue
                files = job_files(job)  # inputs made by earlier jobs exist now
                clash = [(p, writers[p]) for p in files.outputs if p in writers]
                if clash:  # two jobs renaming onto one file: the last one would silently win
                    p, other = clash[0]
                    finish(JobResult(job.name, job.command, FAILED, error=f"writes {p}, which job {other} also "
                                     "writes; give each job its own output (e.g. out/{name}.usd)"))
                    continue
                writers.update({p: job.name for p in files.outputs})
                for p in files.outputs:  # templated outputs often go to new folders
                    p.parent.mkdir(parents=True, exist_ok=True)
                fp = fingerprint(job, files) if files.parsed else None
                if resume and fp is not None and is_up_to_date(files, fp):
                    finish(JobResult(job.name, job.command, UP_TO_DATE, outputs=[str(p) for p in files.outputs],
                                     fingerprint=fp))
                    continue
                in_flight[backend.submit(job)] = (job, files, fp)
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
                    write_record(job, files, fp, r.seconds)
                finish(r)
    except BaseException:  # Ctrl-C, or a bug here: stop the running jobs, then re-raise
        backend.close(cancel=True, handles=list(in_flight))
        if bar is not None:
            bar.close()
        raise
    backend.close()
    if bar is not None:
        bar.close()
    return BatchResult([results[j.name] for j in jobs if j.name in results], backend.name, time.perf_counter() - t0)
