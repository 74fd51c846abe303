"""The jobs file: `[[job]]` tables read within limits, sweeps expanded into a cartesian
product, `{name}` templates filled, `after` edges resolved and checked for cycles.

A jobs file is data from anywhere: it is size- and depth-limited before it is parsed, and
its templates are plain `{name}` substitutions (no format mini-language).
"""
from __future__ import annotations

import itertools
import re
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable

from pd_tool.core.errors import PdToolError
from pd_tool.core.inputs import regular_file_problem

COMMANDS = ("bake", "fit")
JOB_KEYS = {"name", "command", "args", "after", "sweep"}

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
# Characters kept of one log line or error in the summary.
MAX_LINE_CHARS = 1000


class JobsFileError(PdToolError):
    """The jobs file is unreadable or inconsistent (unknown key, bad sweep, cycle...)."""


def one_line(text: str, limit: int = MAX_LINE_CHARS) -> str:
    """One line of at most `limit` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


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
                raise JobsFileError(f"{where}: unclosed {{ in {one_line(template, 80)!r}; write {{{{ for a literal brace")
            inner = template[i + 1:end]
            m = _FIELD.fullmatch(inner)
            if m is None:
                raise JobsFileError(f"{where}: placeholder {{{one_line(inner, 80)}}} is not allowed; write {{key}} or "
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
            raise JobsFileError(f"{where}: single }} in {one_line(template, 80)!r}; write }}}} for a literal brace")
        else:
            nxt = min((p for p in (template.find("{", i), template.find("}", i)) if p >= 0), default=n)
            piece, i = template[i:nxt], nxt
        size += len(piece)
        if size > limit:
            raise JobsFileError(f"{where}: {one_line(template, 80)!r} expands to more than {limit:,} characters; "
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
        raise JobsFileError(f"{source}: unknown top-level key(s) {one_line(', '.join(sorted(map(str, extra))), 200)}; "
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
            raise JobsFileError(f"{where}: unknown key(s) {one_line(', '.join(sorted(map(str, unknown))), 200)} "
                                f"(allowed: {', '.join(sorted(JOB_KEYS))})")
        name = t.get("name")
        if not isinstance(name, str) or not name.strip():
            raise JobsFileError(f"{where}: needs name = \"...\"")
        if not name.isprintable() or len(name) > MAX_NAME_CHARS:
            raise JobsFileError(f"{where}: name must be printable text of at most {MAX_NAME_CHARS} characters, "
                                f"got {one_line(repr(name), 80)}")
        where = f"{source}: job {name!r}"
        command = t.get("command")
        if command not in COMMANDS:
            raise JobsFileError(f"{where}: command must be one of {', '.join(COMMANDS)}, "
                                f"got {one_line(repr(command), 80)}")
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
                raise JobsFileError(f"{where}: sweep key {one_line(repr(k), 80)} must be a name of letters, digits "
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
        raise JobsFileError(f"{path}: not valid TOML ({one_line(e, 200)}); fix the file") from None
    except RecursionError:
        raise JobsFileError(too_deep) from None
    if _data_depth(data) > MAX_DEPTH:
        raise JobsFileError(too_deep)
    return parse_jobs(data, cwd=path.resolve().parent, source=str(path))


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
