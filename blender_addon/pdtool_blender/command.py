"""The `pdtool bake` command line the add-on runs, and what it reads back from it.

No bpy here (and no relative imports): the tests load this file on its own, and
all physics stays in pdtool; this module only spells its CLI.
"""
from __future__ import annotations

import os
import re
import shutil
from pathlib import Path
from typing import Sequence

# `python -c` shim: the console script is `pdtool = cli:main`; prog_name keeps
# pdtool's usage lines reading "pdtool ..." instead of "-c ...".
PYTHON_SHIM = "import sys; from cli import main; sys.exit(main(prog_name='pdtool'))"
_PYTHON_NAME = re.compile(r"^python[0-9.]*(w)?(\.exe)?$", re.IGNORECASE)
# tqdm bar of `pdtool bake`: "bake:  50%|█████     | 2/4 [00:03<00:02, ...]"
_TQDM_COUNT = re.compile(r"(\d+)/(\d+)\s*\[")


class LauncherError(ValueError):
    """pdtool cannot be found from the preference; the message says how to fix it."""


def launcher(path: str = "", kind: str = "AUTO") -> list[str]:
    """The argv prefix that starts pdtool.

    Args:
        path: the add-on preference: a `pdtool` executable, a Python interpreter of an
            environment where pdtool is installed, or "" to look `pdtool` up on PATH.
        kind: "PDTOOL", "PYTHON" or "AUTO" (a file named python*, python3.11, python.exe
            is taken as an interpreter).
    Returns:
        e.g. ["/env/bin/pdtool"] or ["/env/bin/python", "-c", PYTHON_SHIM].
    """
    path = os.path.expanduser(path.strip()) if path else ""
    if not path:
        found = shutil.which("pdtool")
        if found is None:
            raise LauncherError("pdtool not found on PATH; set its path (or a Python with pdtool installed) "
                                "in Preferences > Add-ons > pdtool")
        return [found]
    if not os.path.isfile(path):
        raise LauncherError(f"pdtool path {path!r} is not a file; set the `pdtool` executable or a Python "
                            "interpreter in Preferences > Add-ons > pdtool")
    is_python = kind == "PYTHON" or (kind == "AUTO" and _PYTHON_NAME.match(os.path.basename(path)) is not None)
    return [path, "-c", PYTHON_SHIM] if is_python else [path]


def _num(v: float) -> str:
    return f"{float(v):.6g}"


def _vec(vals: Sequence[float]) -> str:
    return ",".join(_num(v) for v in vals)


def bake_command(prefix: Sequence[str], *, scene: str | Path, out: str | Path, force: Sequence[float],
                 static_box: Sequence[float] | None = None, at: Sequence[float] | None = None,
                 radius: float | None = None, preset: str | None = None, material: str | Path | None = None,
                 quality: str = "default", seconds: float = 2.0, fps: float = 30.0,
                 up: str | None = None, formats: str | None = None, extra: Sequence[str] = ()) -> list[str]:
    """argv for `pdtool bake`. All geometry is in the splat's scene units.

    Args:
        prefix: from `launcher()`.
        force: acceleration (3,), scene units / s^2.
        static_box: (x0, y0, z0, x1, y1, z1) or None.
        at, radius: centre (3,) and radius of the pushed region, or None (whole object).
        preset / material: a material preset name or a fitted .pdmat; exactly one.
        formats: `--format`, e.g. "both,ply-seq" (the .ply sequence goes beside `out`,
            in sequence_folder(out)); None: pdtool's default, USD only.
    """
    if (preset is None) == (material is None):
        raise ValueError("give a material preset or a material file, not both or neither")
    # the arrow is drawn in the splat's own units, so the force is too
    cmd = [*prefix, "bake", "--scene", str(scene), "--force", _vec(force), "--force-units", "scene"]
    cmd += ["--preset", preset] if preset is not None else ["--material", str(material)]
    if static_box is not None:
        cmd += ["--static-box", _vec(static_box)]
    if at is not None:
        cmd += ["--at", _vec(at)]
    if radius is not None:
        cmd += ["--radius", _num(radius)]
    if up is not None:
        cmd += ["--up", up]
    if formats is not None:
        cmd += ["--format", formats]
    cmd += ["--quality", quality, "--seconds", _num(seconds), "--fps", _num(fps), *extra, str(out)]
    return cmd


def sequence_folder(out: str | Path) -> Path:
    """Where `pdtool bake --format both,ply-seq OUT.usd` writes the .ply sequence."""
    out = Path(out)
    return out.with_name(out.stem + "_ply")


# `pdtool bake` records the scene's up axis in the sequence's manifest; the 3DGS add-on
# takes one of three
UP_AXIS_4DGS = {"-y": "NEG_Y", "+y": "POS_Y", "+z": "POS_Z"}


def progress(stderr_text: str) -> tuple[int, int] | None:
    """(frames done, frames total) from the last tqdm update in pdtool's stderr, or None."""
    found = _TQDM_COUNT.findall(stderr_text[-4000:])
    if not found:
        return None
    done, total = found[-1]
    return int(done), int(total)


def error_line(stderr_text: str, returncode: int) -> str:
    """The one line pdtool printed for a user error (exit code 2), as printed.

    Click prints usage lines before its "Error: ..." line, and tqdm's carriage-return
    updates may share the line; both are stripped. A crash (a traceback) gives its
    last line.
    """
    lines = [seg.strip() for line in stderr_text.splitlines() for seg in line.split("\r")]
    lines = [l for l in lines if l]
    for line in reversed(lines):
        if line.startswith("Error:"):
            return line
    tail = [l for l in lines if _TQDM_COUNT.search(l) is None]
    if tail:
        return tail[-1]
    return f"pdtool exited with code {returncode} and printed nothing"
