"""Running pdtool's command line in-process, as the tests that check refusals need it."""
from __future__ import annotations

import contextlib
from pathlib import Path

from click.testing import CliRunner, Result


def invoke(args: list, cwd: Path | None = None) -> Result:
    """`pdtool ARGS` through click's runner (stdout and stderr apart), in folder `cwd`."""
    from cli import main

    with contextlib.chdir(cwd) if cwd is not None else contextlib.nullcontext():
        return CliRunner().invoke(main, [str(a) for a in args])


def visible_lines(text: str) -> list[str]:
    """stderr as a terminal shows it: the text after the last carriage return of each line."""
    return [ln.rsplit("\r", 1)[-1] for ln in text.splitlines() if ln.rsplit("\r", 1)[-1].strip()]


def refusal_line(res: Result, *words: str, bar: bool = False) -> str:
    """Check a refusal: exit 2 with exactly one `Error:` line (the only line, unless
    `bar`: a progress bar may have drawn before it), no traceback, each of `words` in it.
    Returns the line."""
    assert res.exit_code == 2, (res.exit_code, res.output, res.exception)
    lines = visible_lines(res.stderr)
    errors = [ln for ln in lines if ln.startswith("Error:")]
    assert len(errors) == 1 and lines[-1] == errors[0], res.stderr
    if not bar:
        assert len(lines) == 1, res.stderr
    assert "Traceback" not in res.output and "Exception ignored" not in res.stderr
    for w in words:
        assert w in errors[0], (w, errors[0])
    return errors[0]
