"""Reading a small file that came from elsewhere (a camera file, a preset, a record).

Such a path may name anything: a folder, a pipe that blocks forever, `/dev/zero` that never
ends, a file of gigabytes. Only a regular file of bounded size is read; anything else is one
line of the caller's error type.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

from pd_tool.core.errors import PdToolError

MiB = 1 << 20


def regular_file_problem(path: str | Path) -> str | None:
    """Why `path` is not a regular file to read (missing, a folder, a pipe or device), or None."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "no such file"
    except OSError as e:
        return f"cannot be read ({e.strerror})"
    if stat.S_ISDIR(mode):
        return "is a folder, not a file"
    if not stat.S_ISREG(mode):
        return "is not a regular file (a pipe or a device?)"
    return None


def read_small_file(path: str | Path, *, limit: int, error: type[PdToolError], fix: str) -> bytes:
    """The bytes of the regular file `path`, at most `limit` of them.

    Raises `error` with one line "PATH: what is wrong; FIX" for a missing file, a folder, a
    pipe or device, a file over `limit` bytes, or a read error.
    """
    problem = regular_file_problem(path)
    if problem is None:
        try:
            with open(path, "rb") as fh:
                data = fh.read(limit + 1)
        except OSError as e:
            problem = f"cannot be read ({e.strerror})"
        else:
            if len(data) <= limit:
                return data
            problem = f"is larger than {limit / MiB:g} MiB, far more than such a file holds"
    raise error(f"{path}: {problem}; {fix}")
