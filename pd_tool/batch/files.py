"""What a job reads and writes: its paths from the frontend's own parser (`job_files`),
canonical output paths, confinement to the jobs file's folder, clashes between jobs,
fingerprints and the `--resume` records beside the outputs, and the hidden temporaries a
stopped job may leave.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from pd_tool.batch.jobs import Job, JobsFileError
from pd_tool.core.atomic import PARKED, TEMP_SUFFIX_CHARS, atomic_output, temp_stem
from pd_tool.core.errors import OutputError
from pd_tool.io.formats import output_paths
from pd_tool.materials.file import RECORD_PATH

RECORD_SUFFIX = ".batch.json"
# Files of one input folder hashed for a fingerprint; a larger folder makes the job run every time.
MAX_INPUT_FILES = 100_000


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
# write_fit_outputs, the checkpoint in pd_tool/fit/resume.py, and the camera a clip without
# one is registered to, pd_tool/app.py registered_camera_paths); the preview falls back to
# .gif without an mp4 encoder.
_FIT_SIDE = (".loss.png", ".E.ply", ".E.png", ".preview.mp4", ".preview.gif", ".report.json")
_FIT_CAMERAS = (".camera{}.json", ".camera{}.register.png")


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
    fmt = params.get("fmt") if job.command == "bake" else None
    if fmt is not None and params.get("out") is not None:  # OUT as --format spells it out
        try:
            paths = output_paths(params["out"], *fmt)
        except OutputError:
            paths = {}  # the command refuses OUT itself, in its own words
        if paths:
            outs.remove(canonical(params["out"], cwd))
            outs[0:0] = [canonical(p, cwd) for p in paths.values()]  # the USD file (or OUT) stays first
            folders += [canonical(p, cwd) for name, p in paths.items() if name.endswith("-seq")]
    if job.command == "fit" and params.get("out") is None and params.get("scene") is not None:
        outs.insert(0, canonical(Path(params["scene"]).with_suffix(".pdmat"), cwd))  # the CLI's default
    side: list[Path] = []
    if job.command == "fit" and outs:
        main = outs[0]
        stem = main.name[: -len(main.suffix)] if main.suffix else main.name
        side = [main.with_name(main.name + ".ckpt"), *(main.with_name(stem + s) for s in _FIT_SIDE)]
        clips = params.get("videos") or ()
        tags = [""] if len(clips) <= 1 else [f"-{k}" for k in range(len(clips))]
        side += [main.with_name(stem + s.format(t)) for s in _FIT_CAMERAS for t in tags]
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


def check_outputs(jobs: list[Job], commands: CommandLines, allow_outside: bool = False) -> None:
    """Unless allow_outside, refuse the whole batch when a job writes outside its jobs
    file's folder, before any job runs. Raises JobsFileError. (run_batch finds each job's
    files again when it starts it: inputs made by earlier jobs exist by then.)"""
    if allow_outside:
        return
    for job in jobs:
        bad = outside(job_files(job, commands), job.cwd)
        if bad:
            raise JobsFileError(outside_message(job, bad[0]))


def outside_message(job: Job, path: Path) -> str:
    return (f"job {job.name!r} writes {path}, outside the jobs file's folder {job.cwd}; write its outputs "
            "inside that folder (relative paths such as out/{name}.usd), or pass --allow-outside if you "
            "trust this jobs file to write anywhere")
