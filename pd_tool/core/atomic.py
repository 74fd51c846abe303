"""Atomic output, and pdtool's rule for what it may replace.

Atomic: a file appears whole or not at all (temporary file beside it, then rename).
Temporaries are hidden dot-files in the destination folder (`.NAME.XXXX.part.EXT`), so a
process killed with SIGKILL (which runs no cleanup) leaves at most such a dot-file, never
a visible partial output. They are not fsynced: the guarantee covers killed processes,
not power loss.

Ownership: pdtool replaces only what it wrote itself.
- A folder it writes (frames, generated videos, the Blender add-on) carries a manifest,
  `.pdtool-output.json`, listing every entry and each file's size. An existing folder is
  replaced only when it is empty, or when every file in it is listed in its manifest at
  the listed size or carries pdtool's mark (below: e.g. a frame and camera.json that
  `pdtool render` wrote there); one foreign or changed file, or an empty folder pdtool
  did not make, and the run refuses, deleting nothing. The current folder and the
  folders that hold it are never replaced.
- A file it writes beside another output without being asked by name (a fit's report,
  plots, E field, preview; the fit record; camera.json in a named folder) carries a mark:
  PNG tEXt `Software=pdtool`, a PLY header comment, a JSON key `written_by`, the mp4/gif
  comment, a .glb's asset generator. Such a side output replaces only a file that carries the mark
  (`atomic_output(..., own_only=True)`). Files the user names (OUT.usd, -o x.png) are
  replaced as asked, like cp.

Write failures (a full, read-only or missing destination, a name the file system refuses)
become OutputError, one line that names the user's path, never the temporary.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import stat
import struct
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

from pd_tool.core.errors import OutputError, PdToolError

MANIFEST = ".pdtool-output.json"
WRITTEN_BY = "pdtool"  # the value of every mark
MARK_TEXT = "written by pdtool"  # PLY comment, mp4 / gif comment
MANIFEST_MAX_BYTES = 64 << 20  # a larger "manifest" is not one pdtool wrote
TEMP_NAME_BYTES = 96  # of the output's name kept in a temporary's name: NAME_MAX is 255 bytes
TEMP_SUFFIX_CHARS = 16  # of the output's suffix kept in a file temporary's name
PARKED = "previous"  # the folder being replaced, inside its `.NAME.XXXXXXXX.old` temporary
_FIX_SPACE = "free some space or choose a writable folder"
_FIX_FOLDER = "check that the output folder exists and is a folder, not a file"
_FIX = {errno.ENAMETOOLONG: "choose a shorter name", errno.ENOTDIR: _FIX_FOLDER, errno.ENOENT: _FIX_FOLDER}
# errnos that say what is wrong with the destination itself (anything else, e.g. a broken
# pipe to an encoder, is a symptom: the destination is examined for the cause)
_DEST_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EACCES, errno.EPERM, errno.EDQUOT, errno.EFBIG,
                errno.ENAMETOOLONG, errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.EMLINK,
                errno.EIO, errno.ELOOP, errno.ENOTEMPTY, errno.EBUSY, errno.ETXTBSY}


def _umask_mode(full: int) -> int:
    # mkstemp / mkdtemp create 0600 / 0700; the output should get the mode a plain open()
    # would give it (other users on a shared workstation can read it)
    umask = os.umask(0)
    os.umask(umask)
    return full & ~umask


# ----------------------------------------------------------------------------- errors


def _label(what: str | None, path: Path | str) -> str:
    return f"{what} {path}" if what else str(path)


def _first_line(e: BaseException) -> str:
    text = next((ln.strip() for ln in str(e).splitlines() if ln.strip()), "")
    return text[:200] or type(e).__name__


def path_kind(path: str | Path) -> str | None:
    """"dir", "file", "link" (a symbolic link, not followed) or "other" (a device, a
    socket...); None when nothing can be found there, including names too long to look up."""

    try:
        mode = os.lstat(path).st_mode
    except (OSError, ValueError):
        return None
    if stat.S_ISLNK(mode):
        return "link"
    return "dir" if stat.S_ISDIR(mode) else "file" if stat.S_ISREG(mode) else "other"


def _existing_ancestor(path: Path) -> Path:
    p = Path(os.path.abspath(path))
    while not os.path.exists(p) and p != p.parent:
        p = p.parent
    return p


def destination_problem(path: str | Path) -> int | None:
    """Why nothing can be written at `path` (an errno), judged from its folder: a name
    longer than the file system takes, a folder path that runs through a file, a
    read-only or full file system, no write permission. None when none of these holds
    (a write may still fail, e.g. when the disk fills up during it)."""
    path = Path(path)
    folder = _existing_ancestor(path.parent)
    try:
        name_max = os.pathconf(folder, "PC_NAME_MAX") if folder.is_dir() else 255
    except (OSError, ValueError):
        name_max = 255
    for part in Path(os.path.abspath(path)).relative_to(folder).parts:
        if len(os.fsencode(part)) > name_max:
            return errno.ENAMETOOLONG
    if not folder.is_dir():
        # gone since _existing_ancestor saw it (removed while we write): ENOENT
        return errno.ENOTDIR if folder.exists() else errno.ENOENT
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    if st.f_flag & os.ST_RDONLY:
        return errno.EROFS
    if not os.access(folder, os.W_OK | os.X_OK):
        return errno.EACCES
    if st.f_bavail == 0 and st.f_blocks > 0:  # pseudo file systems (/proc) report 0 blocks of 0
        return errno.ENOSPC
    return None


def output_error(path: str | Path, e: BaseException | int | str) -> OutputError:
    """The OutputError for a failed write of `path` (the user's path): from an exception,
    an errno or a reason. The fix depends on the cause."""
    if isinstance(e, int):
        code, reason = e, os.strerror(e)
    elif isinstance(e, OSError) and e.errno:
        code, reason = e.errno, os.strerror(e.errno)
    elif isinstance(e, str):
        code, reason = None, e
    else:
        code, reason = None, _first_line(e)
    return OutputError(f"cannot write {path}: {reason}; {_FIX.get(code, _FIX_SPACE)}", path=path)


# the OS errors a library or an encoder reports only in its message text
_TEXT_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENAMETOOLONG,
                errno.EIO)


def output_error_in_text(path: str | Path, text: str) -> OutputError | None:
    """The OutputError for `path` when a message (ffmpeg's stderr, pxr's error chain)
    quotes an OS error of the destination's (disk full, read-only, ...), else None."""
    for code in _TEXT_ERRNOS:
        if os.strerror(code) in text:
            return output_error(path, code)
    return None


def as_output_error(path: str | Path, e: BaseException) -> OutputError | None:
    """The OutputError that an exception raised while writing `path` stands for, or None
    when it does not look like a write failure (then the caller re-raises it as it is).

    An OSError naming the destination's trouble (ENOSPC, EROFS, EACCES, ...) is that
    trouble. Anything else (a broken pipe to an encoder, a library's own exception around
    a failed write) is a write failure only when the destination shows why: full,
    read-only or not writable."""
    if isinstance(e, OutputError):
        return e
    if isinstance(e, OSError) and e.errno in _DEST_ERRNOS:
        return output_error(path, e)
    code = destination_problem(path)
    if code is not None:
        return output_error(path, code)
    if isinstance(e, OSError):
        return output_error(path, e)
    return None


# ----------------------------------------------------------------------------- marks


def _png_is_own(path: Path) -> bool:
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return False
        for _ in range(64):  # pdtool writes its tEXt chunk right after IHDR
            head = fh.read(8)
            if len(head) < 8:
                return False
            length, kind = struct.unpack(">I4s", head)
            if kind in (b"IDAT", b"IEND") or length > 1 << 20:
                return False
            body = fh.read(length)
            fh.seek(4, os.SEEK_CUR)  # CRC
            if kind == b"tEXt":
                key, _, value = body.partition(b"\0")
                if key == b"Software" and value.startswith(WRITTEN_BY.encode()):
                    return True
    return False


def _ply_is_own(path: Path) -> bool:
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            return False
        for _ in range(256):
            line = fh.readline(4096)
            if not line or line.strip() == b"end_header":
                return False
            if line.startswith(b"comment") and MARK_TEXT.encode() in line:
                return True
    return False


# pdtool JSON files written before they carried `written_by`: their exact key sets
_LEGACY_JSON_KEYS = ({"scene", "material", "written"},  # .pdtool/last-fit.json
                     {"material", "losses", "seconds", "drivers", "E_range_pa", "E_percentiles_pa", "outputs",
                      "settings"})  # a fit's .report.json


def _json_is_own(path: Path) -> bool:
    if path.stat().st_size > MANIFEST_MAX_BYTES:
        return False
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError, RecursionError):
        return False
    if not isinstance(data, dict):
        return False
    written_by = data.get("written_by")
    if isinstance(written_by, str) and written_by.startswith(WRITTEN_BY):
        return True
    return set(data) in _LEGACY_JSON_KEYS


def _mp4_is_own(path: Path) -> bool:
    # walk the top-level boxes to `moov` (metadata, small) and look for the comment there
    size = path.stat().st_size
    with open(path, "rb") as fh:
        pos = 0
        for _ in range(64):
            if pos + 8 > size:
                return False
            fh.seek(pos)
            length, kind = struct.unpack(">I4s", fh.read(8))
            header = 8
            if length == 1:
                length = struct.unpack(">Q", fh.read(8))[0]
                header = 16
            elif length == 0:
                length = size - pos
            if length < header:
                return False
            if kind == b"moov":
                return MARK_TEXT.encode() in fh.read(min(length - header, 64 << 20))
            pos += length
    return False


def _gif_is_own(path: Path) -> bool:
    from PIL import Image

    try:
        with Image.open(path) as im:
            comment = im.info.get("comment", b"")
    except Exception:  # Pillow raises many types for files that are not GIFs
        return False
    return isinstance(comment, bytes) and MARK_TEXT.encode() in comment


def _glb_is_own(path: Path) -> bool:
    # the JSON chunk's asset.generator, which pd_tool.io.gltf sets to "pdtool ..."
    with open(path, "rb") as fh:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return False
        length, kind = struct.unpack("<II", head[12:20])
        if kind != 0x4E4F534A or length > MANIFEST_MAX_BYTES:
            return False
        try:
            doc = json.loads(fh.read(length).decode("utf-8"))
        except (ValueError, UnicodeDecodeError, RecursionError):
            return False
    generator = doc.get("asset", {}).get("generator") if isinstance(doc, dict) else None
    return isinstance(generator, str) and generator.startswith(WRITTEN_BY)


_MARK_READERS = {".png": _png_is_own, ".ply": _ply_is_own, ".json": _json_is_own, ".mp4": _mp4_is_own,
                 ".gif": _gif_is_own, ".glb": _glb_is_own}


def is_own_file(path: str | Path) -> bool:
    """Whether `path` is a regular file that carries pdtool's mark (see the module
    docstring). False for anything unreadable, of another type, or a symbolic link."""
    path = Path(path)
    reader = _MARK_READERS.get(path.suffix.lower())
    if reader is None or path_kind(path) != "file":
        return False
    try:
        return reader(path)
    except (OSError, ValueError, EOFError, MemoryError):
        return False


def check_own_file(path: str | Path, what: str, fix: str = "move or rename it, or write the outputs elsewhere") -> None:
    """Refuse (OutputError) when `path` exists and is not a file pdtool wrote: the side
    output `what` (e.g. "the fit's loss plot") must not replace someone else's file."""
    path = Path(path)
    kind = path_kind(path)
    if kind is None:
        return
    if kind == "dir":
        raise OutputError(f"{path}: is a folder where pdtool writes {what}; {fix}", path=path)
    if not is_own_file(path):
        raise OutputError(f"{path}: exists and was not written by pdtool, which would replace it with {what}; "
                          f"{fix}", path=path)


def png_info():
    """Pillow PngInfo carrying pdtool's mark (pass as `pnginfo=` to Image.save)."""
    from PIL.PngImagePlugin import PngInfo

    info = PngInfo()
    info.add_text("Software", WRITTEN_BY)
    return info


# ----------------------------------------------------------------------------- folders


def _load_manifest(folder: Path) -> dict[str, Any] | None:
    """The folder's pdtool manifest, checked (files {relative path: size}, folders list),
    or None when it has none that pdtool wrote."""
    m = folder / MANIFEST
    try:
        if m.is_symlink() or not m.is_file() or m.stat().st_size > MANIFEST_MAX_BYTES:
            return None
        data = json.loads(m.read_bytes().decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError):
        return None
    if not isinstance(data, dict) or data.get("written_by") != WRITTEN_BY:
        return None
    files, folders = data.get("files"), data.get("folders")
    if not isinstance(files, dict) or not isinstance(folders, list):
        return None
    if not all(isinstance(k, str) and isinstance(v, int) for k, v in files.items()):
        return None
    return data


def _read_manifest(folder: Path) -> tuple[dict[str, int], set[str]] | None:
    data = _load_manifest(folder)
    if data is None:
        return None
    return data["files"], {f for f in data["folders"] if isinstance(f, str)}


def _write_manifest(folder: Path, what: str | None) -> None:
    files: dict[str, int] = {}
    folders: list[str] = []
    for root, dirs, names in os.walk(folder):
        rel = Path(root).relative_to(folder)
        for d in dirs:
            folders.append((rel / d).as_posix())
        for n in names:
            p = rel / n
            if p.as_posix() != MANIFEST:
                files[p.as_posix()] = os.lstat(Path(root) / n).st_size
    record = {"written_by": WRITTEN_BY, "what": what or "output folder",
              "note": "pdtool made this folder and may replace it; it refuses when the folder holds anything "
                      "not listed here",
              "folders": sorted(folders), "files": dict(sorted(files.items()))}
    (folder / MANIFEST).write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")


def mark_folder(folder: str | Path, what: str) -> None:
    """Write (or rewrite) the manifest of a folder that pdtool fills in place rather than
    replacing whole (the demo's folder): it lists what the folder holds now, all pdtool's."""
    _write_manifest(Path(folder), what)


def folder_mark(folder: str | Path) -> str | None:
    """The `what` of the folder's pdtool manifest, or None when it has none."""
    data = _load_manifest(Path(folder))
    what = None if data is None else data.get("what")
    return what if isinstance(what, str) else None


def _is_cache(rel: Path) -> bool:
    # Python writes __pycache__/*.pyc inside an add-on folder when Blender imports it
    return "__pycache__" in rel.parts and (rel.name == "__pycache__" or rel.suffix in (".pyc", ".pyo"))


def _foreign_entry(folder: Path, known: frozenset[str]) -> str | None:
    """The first entry of `folder` that pdtool did not write (relative path), or None."""
    manifest = _read_manifest(folder)
    files, folders = manifest if manifest is not None else ({}, set())
    known_dirs = {p.rsplit("/", i)[0] for p in known for i in range(1, p.count("/") + 1)}

    def fail(err: OSError):
        raise err

    try:
        for root, dirs, names in os.walk(folder, onerror=fail):
            rel = Path(root).relative_to(folder)
            for d in dirs:
                r = rel / d
                if (Path(root) / d).is_symlink():
                    return r.as_posix()
                unlisted = r.as_posix() not in folders and r.as_posix() not in known_dirs and not _is_cache(r)
                if unlisted and not any(os.scandir(Path(root) / d)):  # else its entries decide
                    return r.as_posix() + "/"
            for n in names:
                r = rel / n
                key = r.as_posix()
                if key == MANIFEST and manifest is not None:
                    continue
                if _is_cache(r) or key in known:
                    continue
                p = Path(root) / n
                if p.is_symlink():
                    return key
                if files.get(key) != p.stat().st_size and not is_own_file(p):
                    return key
    except OSError as e:
        return f"an unreadable entry ({os.strerror(e.errno) if e.errno else e})"
    return None


def _holds(folder: Path, inner: Path) -> bool:
    """Whether `inner` is `folder` or lies inside it (absolute, normalised paths)."""
    return inner == folder or folder in inner.parents


def _real(p: str | Path) -> Path:
    return Path(os.path.realpath(p))


def check_replaceable_folder(path: str | Path, what: str | None = None, *, known: Iterable[str] = (),
                             fix: str | None = None) -> None:
    """Refuse (OutputError) when writing the folder `path` would delete something pdtool
    did not write: `path` is a file or a link, the current folder or one that holds it,
    or a folder holding a file that its manifest does not list (at the listed size) and
    that carries no pdtool mark, a link, or an empty folder of someone else's. Missing
    and empty folders pass. `known`: relative paths that count as pdtool's even
    without a manifest (the add-on's own files). `what`: the option, for the message;
    `fix`: what the command adds to the message about a foreign entry."""
    path = Path(path)
    label = _label(what, path)
    kind = path_kind(path)
    if kind == "link":
        raise OutputError(f"{label}: is a symbolic link; name the folder itself", path=path)
    if kind is None:
        return
    if kind != "dir":
        raise OutputError(f"{label}: is a file, not a folder; choose a folder name", path=path)
    if _holds(_real(path), _real(Path.cwd())):
        raise OutputError(f"{label}: is the current folder or holds it, and pdtool replaces the whole folder; "
                          f"name a new folder inside it instead", path=path)
    foreign = _foreign_entry(path, frozenset(known))
    if foreign is not None:
        raise OutputError(f"{label}: holds {foreign}, which pdtool did not write (or which changed since); pdtool "
                          f"replaces only folders it made itself: choose a new or empty folder, or move "
                          f"what you keep there elsewhere" + (f"; {fix}" if fix else ""), path=path)


def check_outputs(files: Mapping[str, str | Path | None], folders: Mapping[str, str | Path | None] = {},
                  inputs: Mapping[str, str | Path | None] = {}) -> None:
    """Refuse (OutputError) a set of outputs where one write would destroy another output
    or an input: two outputs naming one path, an output that is an input, or a folder
    output (which is replaced whole) that holds another output, an input or the current
    folder. Keys are the options' names as the user typed them ("OUT", "--preview"); None
    values are skipped. Paths are compared after resolving links and `..`."""
    fs = {k: _real(v) for k, v in files.items() if v is not None}
    ds = {k: _real(v) for k, v in folders.items() if v is not None}
    ins = {k: _real(v) for k, v in inputs.items() if v is not None}
    shown = {k: v for group in (inputs, folders, files) for k, v in group.items() if v is not None}
    outs = {**fs, **ds}
    names = list(outs)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if outs[a] == outs[b]:
                raise OutputError(f"{a} and {b} name the same path {shown[b]}; give each output its own name",
                                  path=shown[b])
    for o, p in outs.items():
        for k, q in ins.items():
            if p == q:
                raise OutputError(f"{o} {shown[o]} is the input {k}; writing it would destroy the input: choose "
                                  f"another name", path=shown[o])
    cwd = _real(Path.cwd())
    for d, p in ds.items():
        if _holds(p, cwd):
            raise OutputError(f"{d} {shown[d]}: is the current folder or holds it, and pdtool replaces the whole "
                              f"folder; name a new folder, e.g. {d} frames", path=shown[d])
        for o, q in outs.items():
            if o != d and _holds(p, q):
                raise OutputError(f"{d} {shown[d]} would replace the folder that holds {o} {shown[o]}, and pdtool "
                                  f"replaces the whole folder; write {o} outside it or choose another folder for "
                                  f"{d}", path=shown[d])
        for k, q in ins.items():
            if _holds(p, q) or _holds(q, p):
                raise OutputError(f"{d} {shown[d]} {'holds' if _holds(p, q) else 'lies inside'} the input {k} "
                                  f"{shown[k]}, and pdtool replaces the whole folder; choose another folder for {d}",
                                  path=shown[d])


def check_destination(path: str | Path, what: str | None = None, *, folder: bool = False) -> None:
    """Refuse (OutputError) up front, before any work, an output that cannot be written:
    a name the file system refuses, a read-only, full or unwritable destination, a
    folder where a file is to go (or the reverse)."""
    path = Path(path)
    kind = path_kind(path)
    if kind is not None and kind != "link":
        if folder and kind != "dir":
            raise OutputError(f"{_label(what, path)}: is a file, not a folder; choose a folder name", path=path)
        if not folder and kind == "dir":
            raise OutputError(f"{_label(what, path)}: is a folder; give a file name", path=path)
    code = destination_problem(path)
    if code is not None:
        raise output_error(path, code)


# ----------------------------------------------------------------------------- the writer


def temp_stem(name: str) -> str:
    """The output's name as its temporaries carry it: its first TEMP_NAME_BYTES bytes, so
    that a temporary fits NAME_MAX wherever the name does (the usd writer's too)."""
    return os.fsdecode(os.fsencode(name)[:TEMP_NAME_BYTES]).rstrip("\ufffd")


def _temp_prefix(path: Path) -> str:
    return f".{temp_stem(path.name)}."


def _map_temp(e: OutputError, tmp: Path, path: Path) -> OutputError:
    """An OutputError from a writer nested inside this one names the hidden temporary
    folder; name the user's path instead."""
    inner = getattr(e, "path", None)
    if inner is None:
        return e
    inner_abs = Path(os.path.abspath(inner))
    tmp_abs = Path(os.path.abspath(tmp))
    if not _holds(tmp_abs, inner_abs):
        return e
    mapped = path / inner_abs.relative_to(tmp_abs) if inner_abs != tmp_abs else path
    return OutputError(str(e).replace(str(inner), str(mapped)), path=mapped)


@contextlib.contextmanager
def atomic_output(path: str | Path, *, directory: bool = False, what: str | None = None, own_only: bool = False,
                  known: Iterable[str] = ()) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success rename it onto `path`.

    On any exception (or KeyboardInterrupt) the temporary is removed and `path` is left
    as it was. The temporary is in the same folder, so os.replace is atomic. A failed
    write (OSError, or any error while the destination is full or read-only) becomes
    OutputError naming `path`.

    directory=True: the temporary is a folder, given a manifest on success. An existing
    folder at `path` is replaced only under `check_replaceable_folder` (checked on entry
    and again just before the swap); it is renamed away and deleted only after the new
    one is in place: a kill at any moment leaves `path` either the old folder, the new
    one, or absent, never half deleted. `known`: see check_replaceable_folder.
    own_only=True (files): replace an existing file only when pdtool wrote it
    (`check_own_file`); `what` then names the output in the message.
    """
    path = Path(path)
    shown = path
    if own_only:
        check_own_file(path, what or "a pdtool output")
    if directory:
        check_replaceable_folder(path, what, known=known)
    if path_kind(path.parent) not in (None, "dir") and not os.path.isdir(path.parent):
        raise OutputError(f"cannot write {shown}: {path.parent} is a file, not a folder; choose a folder", path=shown)
    code = destination_problem(path)  # before any work, and before a temporary exists
    if code is not None:
        raise output_error(shown, code)
    tmp: Path | None = None
    old: Path | None = None
    made: list[Path] = []  # folders created for this output, removed again if it fails
    p = Path(os.path.abspath(path.parent))
    while path_kind(p) is None and p != p.parent:
        made.append(p)
        p = p.parent
    done = False
    try:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if directory:
                tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".part", dir=path.parent))
            else:
                fd, name = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=".part" + path.suffix[:TEMP_SUFFIX_CHARS],
                                            dir=path.parent)
                os.close(fd)
                tmp = Path(name)
        except OSError as e:
            raise output_error(shown, e) from None
        try:
            yield tmp
        except OutputError as e:
            raise _map_temp(e, tmp, shown) from None
        except Exception as e:
            mapped = None if isinstance(e, PdToolError) else as_output_error(shown, e)
            if mapped is None:
                raise
            raise mapped from None
        try:
            if directory:
                _write_manifest(tmp, what)
            os.chmod(tmp, _umask_mode(0o777 if directory else 0o666))
            if own_only:
                check_own_file(path, what or "a pdtool output")
            if directory and path_kind(path) is not None:
                check_replaceable_folder(path, what, known=known)
                old = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".old", dir=path.parent))
                os.replace(path, old / PARKED)
            try:
                os.replace(tmp, path)
            except BaseException:
                if old is not None:  # put the old folder back
                    os.replace(old / PARKED, path)
                    shutil.rmtree(old, ignore_errors=True)
                    old = None
                raise
        except OutputError:
            raise
        except OSError as e:
            raise output_error(shown, e) from None
        done = True
    finally:
        if tmp is not None and path_kind(tmp) is not None:
            with contextlib.suppress(OSError):
                if path_kind(tmp) == "dir":
                    shutil.rmtree(tmp, ignore_errors=True)
                else:
                    tmp.unlink()
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        if not done:
            for folder in made:  # deepest first; only while empty
                try:
                    folder.rmdir()
                except OSError:
                    break

