"""`pdtool batch`: many bake/fit jobs from one TOML file, on a local process pool or a Ray cluster.

A job is a pdtool command line. The frontend that offers batch hands in `CommandLines`: how
to parse a command line and how to run one in-process. `pdtool batch` hands in its own click
commands, so a batch job and a typed command take one code path (same option checks, same
defaults, same atomic outputs, same one-line errors) while this scheduler imports no
frontend. It only decides *when* and *where* a job runs:

- jobs file: `[[job]]` tables, sweeps expanded into a cartesian product, `after` edges;
- fingerprints: sha256 over the job's command line and the bytes of every input file it
  names, kept in a small `<output>.batch.json` record beside the job's main output so that
  `--resume` skips the jobs that are already done with the same inputs;
- backends: `LocalBackend` (spawned processes, one per CPU worker plus one per visible GPU)
  and `RayBackend` (one Ray task per job, `num_gpus=1` when the job runs on CUDA).

A jobs file is data from anywhere: it is size- and depth-limited before it is parsed, its
templates are plain `{name}` substitutions, its outputs stay inside its own folder unless
the caller allows otherwise, and workers stop with the driver (see docs/batch.md).
"""
from __future__ import annotations

import atexit
import concurrent.futures as cf
import contextlib
import ctypes
import gc
import hashlib
import io
import itertools
import json
import multiprocessing as mp
import os
import platform
import re
import shutil
import signal
import socket
import stat
import sys
import tempfile
import threading
import time
import tomllib
from dataclasses import asdict, dataclass, field
from multiprocessing import resource_tracker
from multiprocessing.connection import wait as wait_for
from pathlib import Path
from typing import Any, Callable, Iterable

from pd_tool.core.atomic import PARKED, TEMP_SUFFIX_CHARS, atomic_output, temp_stem
from pd_tool.core.device import native_stderr_silenced
from pd_tool.core.errors import PdToolError
from pd_tool.core.inputs import regular_file_problem
from pd_tool.materials.file import RECORD_PATH

COMMANDS = ("bake", "fit")
JOB_KEYS = {"name", "command", "args", "after", "sweep"}
RECORD_SUFFIX = ".batch.json"
# Terminal states of a job. "up-to-date": skipped by --resume; "blocked": a job it waits
# for failed, so it never ran.
OK, FAILED, BLOCKED, UP_TO_DATE = "ok", "failed", "blocked", "up-to-date"

# Limits on a jobs file. A hand-written sweep is a few kB with a depth of 5 (file, job
# list, job table, sweep table, value list); these leave room for generated files while
# keeping a hostile one from exhausting memory, the parser's recursion or the summary.
MAX_FILE_BYTES = 1 << 20          # the jobs file itself
MAX_DEPTH = 16                    # nested arrays/tables, checked before and after parsing
MAX_JOBS = 10_000                 # jobs after sweep expansion
MAX_ARGS = 512                    # arguments per job
MAX_ARG_CHARS = 4096              # characters per argument after templating (PATH_MAX)
MAX_NAME_CHARS = 200              # characters of an expanded job name (it often becomes a file name)
MAX_TOTAL_ARG_CHARS = 16 << 20    # characters of all jobs' arguments together
MAX_EDGES = 1_000_000             # `after` edges after sweep names are expanded
# Arguments that make a command print something and exit instead of running.
HELP_ARGS = ("--help", "-h", "--version")
# Seconds a stopped worker gets to unwind its job (atomic outputs remove their temporaries)
# before it is killed.
STOP_GRACE_S = 10.0
# How often a worker's watchdog looks for its driver, s.
WATCHDOG_S = 0.5
# Files of one input folder hashed for a fingerprint; a larger folder makes the job run every time.
MAX_INPUT_FILES = 100_000
# Characters kept of one log line or error in the summary.
MAX_LINE_CHARS = 1000


class JobsFileError(PdToolError):
    """The jobs file is unreadable or inconsistent (unknown key, bad sweep, cycle...)."""


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM reached the driver while the jobs ran; `signum` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _line(text: str, limit: int = MAX_LINE_CHARS) -> str:
    """One line of at most `limit` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


# ----------------------------------------------------------------------------- jobs file


@dataclass(frozen=True)
class Job:
    """One command line to run.

    name: unique, file-safe. command: 'bake' | 'fit'. args: the arguments after the
    command, exactly as typed. after: names of jobs that must finish first. cwd: the
    folder relative paths in args are read from (the jobs file's folder, resolved). table:
    the `name` of the [[job]] table it was expanded from (a sweep's base name).
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


_FIELD = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)(:slug)?")


def _fill(template: str, values: dict[str, str], where: str, limit: int = MAX_ARG_CHARS) -> str:
    """Substitute `{key}` and `{key:slug}` in `template`; `{{` and `}}` are literal braces.

    Nothing else is a field: Python's format mini-language (attributes, indexing,
    conversions, widths) is refused, so a jobs file cannot reach into objects or ask for a
    100 MB padding. The result is at most `limit` characters.
    """
    out: list[str] = []
    size = 0
    i, n = 0, len(template)
    while i < n:
        c = template[i]
        if c == "{" and template.startswith("{{", i):
            piece, i = "{", i + 2
        elif c == "}" and template.startswith("}}", i):
            piece, i = "}", i + 2
        elif c == "{":
            end = template.find("}", i + 1)
            if end < 0:
                raise JobsFileError(f"{where}: unclosed {{ in {_line(template, 80)!r}; write {{{{ for a literal brace")
            inner = template[i + 1:end]
            m = _FIELD.fullmatch(inner)
            if m is None:
                raise JobsFileError(f"{where}: placeholder {{{_line(inner, 80)}}} is not allowed; write {{key}} or "
                                    "{key:slug} with a sweep key or name (no attributes, indexing or format "
                                    "specs), and {{ }} for literal braces")
            key = m.group(1)
            if key not in values:
                known = ", ".join(sorted(values)) or "none"
                raise JobsFileError(f"{where}: unknown placeholder {{{key}}} (known: {known}); "
                                    "write {{ and }} for literal braces")
            piece = slug(values[key]) if m.group(2) else values[key]
            i = end + 1
        elif c == "}":
            raise JobsFileError(f"{where}: single }} in {_line(template, 80)!r}; write }}}} for a literal brace")
        else:
            nxt = min((p for p in (template.find("{", i), template.find("}", i)) if p >= 0), default=n)
            piece, i = template[i:nxt], nxt
        size += len(piece)
        if size > limit:
            raise JobsFileError(f"{where}: {_line(template, 80)!r} expands to more than {limit:,} characters; "
                                "shorten it or its sweep values")
        out.append(piece)
    return "".join(out)


def _scalar(v: Any) -> bool:
    return isinstance(v, (str, int, float, bool)) and not isinstance(v, dict)


def _text(v: Any) -> str:
    return str(v).lower() if isinstance(v, bool) else str(v)


def parse_jobs(data: dict[str, Any], cwd: str | Path = ".", source: str = "jobs file") -> list[Job]:
    """Expand the `[[job]]` tables of a parsed jobs file into Jobs, in file order.

    Sweeps: `[job.sweep]` maps a key to a list of values; the table expands into one job per
    combination (cartesian product, keys in file order, the last key varying fastest). In
    `name`, `{key}` is the value's slug; if the name has no placeholder the slugs are
    appended (`poke` -> `poke_flower_0_0_1`). In `args` and `after`, `{key}` is the raw value,
    `{key:slug}` its slug and `{name}` the expanded job name. Raises JobsFileError, also
    when a limit (MAX_JOBS, MAX_ARGS, MAX_ARG_CHARS, ...) is passed.
    """
    if not isinstance(data, dict):
        raise JobsFileError(f"{source}: must be a TOML document of [[job]] tables")
    extra = set(data) - {"job"}
    if extra:
        raise JobsFileError(f"{source}: unknown top-level key(s) {_line(', '.join(sorted(map(str, extra))), 200)}; "
                            "only [[job]] tables are read")
    tables = data.get("job")
    if not isinstance(tables, list) or not tables:
        raise JobsFileError(f"{source}: no [[job]] tables; see `pdtool batch --help` for the format")
    if len(tables) > MAX_JOBS:
        raise JobsFileError(f"{source}: {len(tables):,} [[job]] tables, more than the limit of {MAX_JOBS:,} jobs; "
                            "split it into several jobs files")
    cwd = str(Path(cwd).resolve())
    jobs: list[Job] = []
    total_chars = 0
    for i, t in enumerate(tables):
        where = f"{source}: job #{i + 1}"
        if not isinstance(t, dict):
            raise JobsFileError(f"{where}: must be a [[job]] table")
        unknown = set(t) - JOB_KEYS
        if unknown:
            raise JobsFileError(f"{where}: unknown key(s) {_line(', '.join(sorted(map(str, unknown))), 200)} "
                                f"(allowed: {', '.join(sorted(JOB_KEYS))})")
        name = t.get("name")
        if not isinstance(name, str) or not name.strip():
            raise JobsFileError(f"{where}: needs name = \"...\"")
        if not name.isprintable() or len(name) > MAX_NAME_CHARS:
            raise JobsFileError(f"{where}: name must be printable text of at most {MAX_NAME_CHARS} characters, "
                                f"got {_line(repr(name), 80)}")
        where = f"{source}: job {name!r}"
        command = t.get("command")
        if command not in COMMANDS:
            raise JobsFileError(f"{where}: command must be one of {', '.join(COMMANDS)}, "
                                f"got {_line(repr(command), 80)}")
        args = t.get("args", [])
        if not isinstance(args, list) or not all(_scalar(a) for a in args):
            raise JobsFileError(f"{where}: args must be a list of strings, as on the command line")
        if len(args) > MAX_ARGS:
            raise JobsFileError(f"{where}: {len(args):,} args, more than the limit of {MAX_ARGS}")
        after = t.get("after", [])
        if isinstance(after, str):
            after = [after]
        if not isinstance(after, list) or not all(isinstance(a, str) for a in after):
            raise JobsFileError(f"{where}: after must be a list of job names")
        sweep = t.get("sweep", {})
        if not isinstance(sweep, dict):
            raise JobsFileError(f"{where}: sweep must be a table of key = [values]")
        combos = 1
        for k, vals in sweep.items():
            if k == "name" or not _FIELD.fullmatch(k) or ":" in k:
                raise JobsFileError(f"{where}: sweep key {_line(repr(k), 80)} must be a name of letters, digits "
                                    "and _ (not starting with a digit) other than 'name'")
            if not isinstance(vals, list) or not vals or not all(_scalar(v) for v in vals):
                raise JobsFileError(f"{where}: sweep.{k} must be a non-empty list of values")
            combos *= len(vals)
            # Checked as the product grows: a few keys of long lists is astronomically many jobs.
            if len(jobs) + combos > MAX_JOBS:
                sizes = " x ".join(str(len(v)) if isinstance(v, list) else "?" for v in sweep.values())
                raise JobsFileError(f"{where}: the sweep ({sizes}) makes the file expand to more than "
                                    f"{MAX_JOBS:,} jobs; split it into several jobs files")
        keys = list(sweep)
        for combo in itertools.product(*(sweep[k] for k in keys)):
            raw = {k: _text(v) for k, v in zip(keys, combo)}
            slugs = {k: slug(v) for k, v in raw.items()}
            if keys and "{" not in name:
                job_name = "_".join([name, *slugs.values()])
            else:
                job_name = _fill(name, slugs, f"{where} name", MAX_NAME_CHARS)
            if len(job_name) > MAX_NAME_CHARS:
                raise JobsFileError(f"{where}: expanded name {job_name[:60]!r}... is longer than "
                                    f"{MAX_NAME_CHARS} characters; shorten the name or the sweep values")
            values = {**raw, "name": job_name}
            job_args = tuple(_fill(_text(a), values, f"{where} args") for a in args)
            if any("\0" in a for a in job_args):
                raise JobsFileError(f"{where}: an argument holds a NUL character, which no command line can; "
                                    "remove it")
            total_chars += sum(len(a) for a in job_args)
            if total_chars > MAX_TOTAL_ARG_CHARS:
                raise JobsFileError(f"{source}: the jobs' arguments add up to more than {MAX_TOTAL_ARG_CHARS:,} "
                                    "characters; split it into several jobs files")
            jobs.append(Job(
                name=job_name, command=command, args=job_args,
                after=tuple(_fill(a, {**slugs, "name": job_name}, f"{where} after", MAX_NAME_CHARS) for a in after),
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
    edges = 0
    for j in jobs:
        deps: dict[str, None] = {}  # ordered set
        for a in j.after:
            hit = [a] if a in names else by_table.get(a, [])
            if not hit:
                raise JobsFileError(f"{source}: job {j.name!r} waits for {a!r}, which is no job name")
            deps.update(dict.fromkeys(hit))
        if j.name in deps:
            raise JobsFileError(f"{source}: job {j.name!r} waits for itself")
        edges += len(deps)
        if edges > MAX_EDGES:
            raise JobsFileError(f"{source}: the after= lists expand to more than {MAX_EDGES:,} dependencies; "
                                "wait for fewer or larger groups of jobs")
        out.append(Job(**{**asdict(j), "after": tuple(deps)}))
    # Cycle check (Kahn, linear in jobs + edges): every job must become ready at some point.
    indegree = {j.name: len(j.after) for j in out}
    waiters: dict[str, list[str]] = {}
    for j in out:
        for d in j.after:
            waiters.setdefault(d, []).append(j.name)
    ready = [n for n, k in indegree.items() if k == 0]
    done = 0
    while ready:
        n = ready.pop()
        done += 1
        for w in waiters.get(n, ()):
            indegree[w] -= 1
            if indegree[w] == 0:
                ready.append(w)
    if done < len(out):
        stuck = sorted(n for n, k in indegree.items() if k > 0)
        shown = ", ".join(stuck[:10]) + (f" and {len(stuck) - 10} more" if len(stuck) > 10 else "")
        raise JobsFileError(f"{source}: the after= edges form a cycle among {shown}")
    return out


_PLAIN = re.compile(r"[^\[\]{}=,\n.#\"']+")


def _nesting(text: str) -> int:
    """Deepest nesting of a TOML text, counted without parsing it: [ and { outside strings
    and comments, plus the dots of a dotted key (`a.b.c = 1` nests three tables).

    Run before the parser, which recurses once per bracket (a file nested 100,000 deep
    ends in a RecursionError) and slows down quadratically on long dotted keys; the parsed
    document's depth is checked again after. Stops counting past MAX_DEPTH.
    """
    depth = deepest = dots = 0
    i, n = 0, len(text)
    while i < n:
        m = _PLAIN.match(text, i)
        if m:
            i = m.end()
            continue
        c = text[i]
        if c in "[{":
            depth += 1
            dots = 0
        elif c in "]}":
            depth = max(0, depth - 1)
            dots = 0
        elif c in "=,\n":
            dots = 0
        elif c == ".":
            dots += 1  # a key's separator, or at most a float's or time's point in a value
        elif c == "#":
            nl = text.find("\n", i)
            i = n if nl < 0 else nl
            continue
        elif c in "\"'":
            q = c
            if text.startswith(q * 3, i):  # multi-line string; closes at the last of a run of 3-5 quotes
                j = i + 3
                while True:
                    k = text.find(q * 3, j)
                    if k < 0:
                        return deepest  # unterminated: the parser says so
                    if q == '"':
                        bs = 0
                        while k - 1 - bs >= j and text[k - 1 - bs] == "\\":
                            bs += 1
                        if bs % 2:
                            j = k + 1
                            continue
                    end = k + 3
                    while end < n and text[end] == q and end - k < 5:
                        end += 1
                    i = end
                    break
                continue
            j = i + 1
            while j < n and text[j] != q and text[j] != "\n":
                if q == '"' and text[j] == "\\":
                    j += 1
                j += 1
            i = j + 1
            continue
        deepest = max(deepest, depth + dots)
        if deepest > MAX_DEPTH:
            return deepest
        i += 1
    return deepest


def _data_depth(data: Any) -> int:
    """Nesting depth of parsed TOML (dicts and lists), without recursion."""
    deepest = 0
    stack = [(data, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        if d > MAX_DEPTH:
            return d
        children = node.values() if isinstance(node, dict) else node
        stack.extend((c, d + 1) for c in children if isinstance(c, (dict, list)))
    return deepest


def load_jobs(path: str | Path) -> list[Job]:
    """Read a TOML jobs file; relative paths in its jobs are relative to its folder.

    Raises JobsFileError (one line) for a missing, unreadable, too large, too deeply
    nested or malformed file.
    """

    path = Path(path)
    problem = regular_file_problem(path)  # a pipe or a device would block the read
    if problem is not None:
        raise JobsFileError(f"{path}: {problem}; give the jobs file (TOML) itself")
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_FILE_BYTES + 1)
    except OSError as e:
        raise JobsFileError(f"{path}: unreadable ({e.strerror})") from None
    if len(raw) > MAX_FILE_BYTES:
        raise JobsFileError(f"{path}: larger than {MAX_FILE_BYTES:,} bytes, the limit for a jobs file; "
                            "use sweeps, or split it into several jobs files")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise JobsFileError(f"{path}: not UTF-8 text (byte {e.start}); save it as UTF-8 TOML") from None
    too_deep = (f"{path}: nested more than {MAX_DEPTH} levels deep (arrays, tables or dotted keys inside "
                "each other); a jobs file needs 5: write [[job]] tables with flat args lists")
    if _nesting(text) > MAX_DEPTH:
        raise JobsFileError(too_deep)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise JobsFileError(f"{path}: not valid TOML ({_line(e, 200)}); fix the file") from None
    except RecursionError:
        raise JobsFileError(too_deep) from None
    if _data_depth(data) > MAX_DEPTH:
        raise JobsFileError(too_deep)
    return parse_jobs(data, cwd=path.resolve().parent, source=str(path))


# ----------------------------------------------------------------------- inputs, outputs


@dataclass(frozen=True)
class CommandLines:
    """How batch reads and runs a job's command line; the frontend supplies both.

    parse(command, args): the command's parameters by option name (None for an option left
    unset), or None when the args do not parse. Called in the job's folder.
    run(command, args): runs the command in this process; returns None when it ran, else
    its error as one line. Must be a module-level function: process pools and Ray send it
    to their workers by reference.
    """

    parse: Callable[[str, list[str]], dict[str, Any] | None]
    run: Callable[[str, list[str]], str | None]


@dataclass
class JobFiles:
    """What a job reads and writes, as absolute paths. `outputs[0]` is its main output
    (the record sits beside it); `side` are files the command writes beside an output
    without being asked (a fit's report, plots, checkpoint). Output paths are canonical:
    the folder resolved (no `..`, no symlinks), the name as written. `parsed` is False when
    the command line does not parse; the job then runs (and fails with the CLI's own
    message) but cannot be resumed."""

    inputs: list[Path] = field(default_factory=list)
    outputs: list[Path] = field(default_factory=list)
    parsed: bool = True
    side: list[Path] = field(default_factory=list)
    folders: list[Path] = field(default_factory=list)  # outputs that are folders (--frames-out)
    shared: list[Path] = field(default_factory=list)  # written by every such job (a fit's folder record)

    def written(self) -> list[Path]:
        """Every path the job writes: its outputs and their side files."""
        return [*self.outputs, *self.side]


# Options whose value is a preset name or a file: only a file is an input.
_NAME_OR_FILE = {"preset", "interaction", "quality"}
_OUTPUTS = {"bake": ("out", "preview", "frames_out"), "fit": ("out",)}
_FOLDER_OUTPUTS = {"frames_out"}
# What `pdtool fit -o STEM.pdmat` writes beside the material (pd_tool/fit/outputs.py
# write_fit_outputs, the checkpoint in pd_tool/fit/resume.py); the preview falls back to
# .gif without an mp4 encoder.
_FIT_SIDE = (".loss.png", ".E.ply", ".E.png", ".preview.mp4", ".preview.gif", ".report.json")


def canonical(p: str | Path, cwd: str | Path) -> Path:
    """Where a path a job names really is: relative to `cwd`, its folder resolved (`..` and
    symlinks), its last part kept as written (a rename replaces a symlink there, it does
    not write through it)."""
    p = Path(p)
    p = p if p.is_absolute() else Path(cwd) / p
    if p.name in ("", ".", ".."):
        return _real(p)
    return _real(p.parent) / p.name


def _real(p: Path) -> Path:
    # os.path.realpath, not Path.resolve: a symlink loop stays unresolved instead of raising
    # (writing through it then fails in the command, with its own message).
    return Path(os.path.realpath(p))


def _exists(p: Path) -> bool:
    try:
        return p.exists()
    except (OSError, ValueError):  # a name too long for the file system, a NUL byte
        return False


def job_files(job: Job, commands: CommandLines) -> JobFiles:
    """Split a job's paths into inputs and outputs by parsing its args with the frontend's
    own parser (no option table is duplicated here)."""
    cwd = Path(job.cwd)
    # A parser checks exists=True paths against the process's folder: parse from the job's.
    with contextlib.chdir(cwd), contextlib.redirect_stderr(io.StringIO()):
        params = commands.parse(job.command, list(job.args))
    if params is None:
        return JobFiles(parsed=False)

    def absolute(p: Any) -> Path:
        p = Path(p)
        return p if p.is_absolute() else cwd / p

    outs: list[Path] = []
    folders: list[Path] = []
    for key in _OUTPUTS[job.command]:
        if params.get(key) is not None:
            outs.append(canonical(params[key], cwd))
            if key in _FOLDER_OUTPUTS:
                folders.append(outs[-1])
    if job.command == "fit" and params.get("out") is None and params.get("scene") is not None:
        outs.insert(0, canonical(Path(params["scene"]).with_suffix(".pdmat"), cwd))  # the CLI's default
    side: list[Path] = []
    if job.command == "fit" and outs:
        main = outs[0]
        stem = main.name[: -len(main.suffix)] if main.suffix else main.name
        side = [main.with_name(main.name + ".ckpt"), *(main.with_name(stem + s) for s in _FIT_SIDE)]
    ins: list[Path] = []
    for key, value in params.items():
        if key in _OUTPUTS[job.command] or value is None:
            continue
        for v in value if isinstance(value, (tuple, list)) else (value,):
            if isinstance(v, Path) or key in _NAME_OR_FILE:
                p = absolute(v)
                if _exists(p):
                    ins.append(p)

    if job.command == "bake" and params.get("material") is None and params.get("preset") is None:
        ins.append(cwd / RECORD_PATH)  # a bare `bake` uses the folder's last fit
    shared = [canonical(RECORD_PATH, cwd)] if job.command == "fit" else []
    return JobFiles(inputs=ins, outputs=outs, parsed=bool(outs), side=side, folders=folders, shared=shared)


def outside(files: JobFiles, root: str | Path) -> list[Path]:
    """The paths of `files.written()` that are not strictly inside `root` (the jobs file's
    folder, resolved). A path is inside when its canonical form is below root and, if
    it is a symlink, so is its target. root itself is outside: no job replaces it."""
    root = _real(Path(root))
    bad = []
    for p in files.written():
        real = _real(p)
        if not all(q != root and q.is_relative_to(root) for q in (p, real)):
            bad.append(p)
    return bad


def _within(p: Path, folder: Path) -> bool:
    return p == folder or p.is_relative_to(folder)


def clash(files: JobFiles, writers: dict[Path, str], folders: dict[Path, str]) -> tuple[Path, str] | None:
    """(path, job) of the first path `files` writes that another job already writes: the
    same canonical path, a path inside another job's output folder, or an output folder
    holding another job's output. None when there is none."""
    for p in files.written():
        if p in writers:
            return p, writers[p]
        for f, job in folders.items():
            if _within(p, f):
                return p, job
    for f in files.folders:
        for p, job in writers.items():
            if _within(p, f):
                return f, job
    return None


_DIGESTS: dict[tuple[str, int, int], bytes] = {}


def file_digest(p: Path) -> bytes:
    """sha256 of one file's bytes, cached by (path, size, mtime): a sweep of 100 bakes of one
    large scene reads it once, and a file rewritten in between is read again."""
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        left = st.st_size  # no further: files of /proc say 0 and would go on for gigabytes
        with open(p, "rb") as f:
            while left > 0:
                chunk = f.read(min(left, 1 << 20))
                if not chunk:
                    break
                h.update(chunk)
                left -= len(chunk)
        _DIGESTS[key] = h.digest()
    return _DIGESTS[key]


def _folder_files(folder: Path) -> list[Path] | None:
    """The files in `folder` and below, sorted; symlinked folders are not followed (a link
    back up would never end). None past MAX_INPUT_FILES."""
    found = []
    for root, _, names in os.walk(folder):
        for n in names:
            found.append(Path(root) / n)
            if len(found) > MAX_INPUT_FILES:
                return None
    return sorted(found)


def _hash_path(h: "hashlib._Hash", p: Path) -> None:
    h.update(str(p).encode() + b"\0")
    try:
        regular = stat.S_ISREG(p.stat().st_mode)
    except OSError:
        regular = False
    # Only regular files are read: a FIFO or a device named as an input would block or never end.
    h.update(file_digest(p) if regular else b"<missing>")


def fingerprint(job: Job, files: JobFiles) -> str | None:
    """sha256 (hex) of the command, its args and the bytes of every input file (folders:
    every file inside, sorted). None when the inputs cannot be read, or a folder holds
    more than MAX_INPUT_FILES files: such a job runs every time."""
    h = hashlib.sha256()
    h.update(json.dumps([job.command, list(job.args)]).encode())
    try:
        for p in sorted(set(files.inputs)):
            inside = _folder_files(p) if p.is_dir() else [p]
            if inside is None:
                return None
            for f in inside:
                if f.is_file() or f == p:
                    _hash_path(h, f)
    except OSError:
        return None
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


def asks_for_help(args: Iterable[str]) -> str | None:
    """The first of --help, -h, --version in a job's args, or None. Such a job would print
    text and exit 0 without running its command."""
    for a in args:
        if a in HELP_ARGS:
            return a
    return None


def help_error(job: Job, arg: str) -> str:
    return (f"its args ask for {arg}, which prints help or version text instead of running the command; "
            f"remove {arg} from job {job.name!r} (run `pdtool {job.command} --help` in a terminal to read the "
            "options)")


_TMP_RAND = r"[a-z0-9_]{8}"  # tempfile's random part (mkstemp / mkdtemp)


def temporaries(p: Path) -> list[Path]:
    """The hidden temporaries of output `p` that exist now, as pdtool's writers name them:
    `.NAME.XXXXXXXX.part.EXT` (pd_tool.core.atomic, a file), `.NAME.XXXXXXXX.part` (a folder),
    `.NAME.XXXXXXXX.old` (the folder being replaced) and `.NAME.tmp-PID-HEX.usdc|usda`
    (usd_export's writer). Nothing else in the folder matches."""
    # a writer keeps only the first bytes of a long name, and of a long suffix, in its
    # temporaries' names: both forms are recognised
    names = "|".join(re.escape(n) for n in sorted({p.name, temp_stem(p.name)}))
    suffixes = "|".join(re.escape(x) for x in sorted({p.suffix, p.suffix[:TEMP_SUFFIX_CHARS]}))
    pattern = re.compile(rf"\.(?:{names})\.(?:{_TMP_RAND}\.(?:part(?:{suffixes})|part|old)"
                         rf"|tmp-\d+-[0-9a-f]{{8}}\.usd[ac])")
    try:
        entries = os.listdir(p.parent)
    except OSError:
        return []
    return [p.parent / e for e in entries if pattern.fullmatch(e)]


def remove_temporaries(files: Iterable[JobFiles]) -> list[Path]:
    """Remove the hidden temporaries of every path these jobs write (see `temporaries`);
    call it only once the processes that wrote them have stopped. A folder replace that was
    cut between its two renames is undone: the previous output goes back to its name.
    Returns what was removed."""
    removed = []
    for f in files:
        for p in [*f.written(), *f.shared]:
            for t in temporaries(p):
                try:
                    real_dir = t.is_dir() and not t.is_symlink()
                    if real_dir and t.name.endswith(".old"):
                        kept = t / PARKED
                        if os.path.lexists(kept) and not os.path.lexists(p):
                            os.replace(kept, p)
                    if real_dir:
                        shutil.rmtree(t)
                    else:
                        t.unlink()
                    removed.append(t)
                except OSError:
                    pass
    return removed


# ------------------------------------------------------------------------------- worker


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


def _watchdog(driver: int) -> None:
    # Portable backstop for the parent-death signal: a worker whose driver is gone is
    # reparented, so its parent pid changes.
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
    threading.Thread(target=_watchdog, args=(driver,), name="pdtool-batch-watchdog", daemon=True).start()


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
    return {"ok": error is None, "error": None if error is None else _line(error),
            "seconds": time.perf_counter() - t0, "log": [_line(s) for s in log[-20:]],
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
                out.append((f, {"ok": False, "error": _line(f"worker died: {type(e).__name__}: {e}"),
                                "seconds": 0.0, "log": []}))
        return out

    def close(self, cancel: bool = False, handles: Iterable[Any] = ()) -> None:
        pools = [self.cpu, *self.gpu]
        if cancel:
            # Stop the running jobs now rather than wait for them; each unwinds and removes
            # its temporaries. Queued jobs never start: a stopped worker exits.
            stop_processes([proc for p in pools for proc in list((getattr(p, "_processes", None) or {}).values())])
        for p in pools:
            p.shutdown(wait=not cancel, cancel_futures=cancel)
        if cancel:
            # Let each pool's manager thread finish closing its wake-up pipe now: at exit,
            # Python 3.11's concurrent.futures wakes it without a lock and can hit the pipe
            # while the thread closes it ("OSError: Bad file descriptor" on stderr).
            for p in pools:
                thread = getattr(p, "_executor_manager_thread", None)
                if thread is not None:
                    thread.join(timeout=STOP_GRACE_S)


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
                out.append((ref, {"ok": False, "error": _line(f"ray: {type(e).__name__}: {e}", 300),
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
    """Write `result.to_json()` to `path`, atomically. Raises OutputError (one line, no
    temporary left) when the destination cannot take it."""
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(result.to_json(), indent=2))
    return path


def check_outputs(jobs: list[Job], commands: CommandLines, allow_outside: bool = False) -> None:
    """Unless allow_outside, refuse the whole batch when a job writes outside its jobs
    file's folder, before any job runs. Raises JobsFileError. (run_batch finds each job's
    files again when it starts it: inputs made by earlier jobs exist by then.)"""
    if allow_outside:
        return
    for job in jobs:
        bad = outside(job_files(job, commands), job.cwd)
        if bad:
            raise JobsFileError(_outside_message(job, bad[0]))


def _outside_message(job: Job, path: Path) -> str:
    return (f"job {job.name!r} writes {path}, outside the jobs file's folder {job.cwd}; write its outputs "
            "inside that folder (relative paths such as out/{name}.usd), or pass --allow-outside if you "
            "trust this jobs file to write anywhere")


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
        finish(JobResult(job.name, job.command, FAILED, error=_line(error)))

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
                                         error=_line(f"waits for {', '.join(bad)}, which did not finish")))
                        continue
                    arg = asks_for_help(job.args)
                    if arg is not None:
                        failed(job, help_error(job, arg))
                        continue
                    files = job_files(job, commands)  # inputs made by earlier jobs exist now
                    away = [] if allow_outside else outside(files, job.cwd)
                    if away:  # a symlink changed since the start
                        failed(job, _outside_message(job, away[0]))
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
                            r.error = _line(f"wrote its outputs, but not its --resume record {record_path(files)} "
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
