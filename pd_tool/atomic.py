"""Atomic output: a file appears whole or not at all (temporary file beside it, then rename).

Temporaries are hidden dot-files in the destination folder (`.NAME.XXXX.part.EXT`), so a
process killed with SIGKILL (which runs no cleanup) leaves at most such a dot-file, never
a visible partial output. They are not fsynced: the guarantee covers killed processes,
not power loss.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator


def _umask_mode(full: int) -> int:
    # mkstemp / mkdtemp create 0600 / 0700; the output should get the mode a plain open()
    # would give it (other users on a shared workstation can read it)
    umask = os.umask(0)
    os.umask(umask)
    return full & ~umask


@contextlib.contextmanager
def atomic_output(path: str | Path, *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path`.

    On any exception (or KeyboardInterrupt) the temporary is removed and `path` is left
    as it was. The temporary is in the same folder, so os.replace is atomic. With
    directory=True an existing folder at `path` is first renamed away (to a hidden name)
    and deleted only after the new one is in place: a kill at any moment leaves `path`
    either the old folder, the new one, or absent, never half deleted.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if directory:
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent))
    else:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part" + path.suffix, dir=path.parent)
        os.close(fd)
        tmp = Path(name)
    old = None
    try:
        yield tmp
        os.chmod(tmp, _umask_mode(0o777 if directory else 0o666))
        if directory and path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
            os.replace(path, old / path.name)
        try:
            os.replace(tmp, path)
        except BaseException:
            if old is not None:  # put the old folder back
                os.replace(old / path.name, path)
            raise
    finally:
        if tmp.exists():
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink()
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
