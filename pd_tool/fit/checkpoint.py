"""The fit checkpoint file (`OUT.pdmat.ckpt`): nested state without pickles.

A checkpoint is data from disk like any other input, so reading one never runs code: it
is a zip of plain members, every one of them stored (not compressed), in this order:

    pdtool-fit-checkpoint   the bytes MAGIC: what the file is (see `is_pdtool_checkpoint`)
    header.json             UTF-8 JSON: format, version, the fit's problem key, the state
                            tree and the list of arrays (dtype, shape)
    arrays/<i>.npy          the tree's tensors, numpy .npy (no object dtypes), i = 0, 1, ...
    sha256                  hex sha256 over the members above (names and bytes)

The state tree holds None, bools, ints, finite floats, strings, lists, and four tagged
JSON objects: {"dict": [[key, value], ...]} (keys str or int, so an optimiser's integer
parameter ids survive), {"tuple": [...]}, {"tensor": i} (member arrays/<i>.npy) and
{"float": "nan" | "inf" | "-inf"} (written so that saving never fails, refused on
reading). Reading is strict: only those members, those tags and a few little-endian
dtypes; every array's .npy header must account for its member's bytes exactly; the
checksum must match; every number must be finite, but for the arrays under the paths the
caller names as records (the fit's loss histories). What the tree must hold for a given
fit (keys, shapes, ranges) is checked by the fit itself (pd_tool.fit.resume.check_checkpoint).

The first member makes a checkpoint recognisable from its first bytes alone, even when
it is truncated: `is_pdtool_checkpoint` decides whether a file at the checkpoint's path
is one pdtool wrote (and may replace) or someone else's (which the fit leaves alone).
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import stat
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import torch

from pd_tool.core.atomic import atomic_output
from pd_tool.core.errors import PdToolError

FORMAT = "pdtool-fit-checkpoint"
VERSION = 1
MAGIC = b"pdtool fit checkpoint: zip of JSON and .npy members, no pickles\n"
MAGIC_MEMBER = FORMAT
HEADER_MEMBER = "header.json"
CHECKSUM_MEMBER = "sha256"
MAX_HEADER_BYTES = 16 << 20  # the tree is scalars and short lists (tensors are members): a few kB
MAX_DEPTH = 32  # nesting of the tree; a fit's state is 6 deep
# little-endian (or byte-sized) dtypes a fit's state uses: weights, moments, counters, RNG
_DTYPES = {np.dtype("<f4"), np.dtype("<f8"), np.dtype("<i8"), np.dtype("<i4"), np.dtype("|u1"), np.dtype("|b1")}
_NONFINITE = ("nan", "inf", "-inf")
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed: the same state gives the same bytes


class CheckpointError(PdToolError):
    """A fit checkpoint is unreadable, damaged, or not one this fit can continue from."""


class ForeignCheckpointFile(CheckpointError):
    """Something other than a pdtool checkpoint sits at the checkpoint's path."""


# ---------------------------------------------------------------------- writing
def _encode(obj: Any, arrays: list[np.ndarray]) -> Any:
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else {"float": "nan" if obj != obj else ("inf" if obj > 0 else "-inf")}
    if isinstance(obj, torch.Tensor):
        arrays.append(np.array(obj.detach().cpu().numpy(), order="C"))  # ascontiguousarray makes 0-d 1-d
        return {"tensor": len(arrays) - 1}
    if isinstance(obj, tuple):
        return {"tuple": [_encode(v, arrays) for v in obj]}
    if isinstance(obj, list):
        return [_encode(v, arrays) for v in obj]
    if isinstance(obj, dict):
        items = []
        for k, v in obj.items():
            if isinstance(k, bool) or not isinstance(k, (str, int)):
                raise TypeError(f"checkpoint dict keys must be str or int, got {type(k).__name__}")
            items.append([k, _encode(v, arrays)])
        return {"dict": items}
    raise TypeError(f"a fit checkpoint cannot hold a {type(obj).__name__}")


def _plain(obj: Any) -> Any:
    """A JSON-ready problem key with any non-finite float as its name (such a key matches no
    fit's, so the checkpoint is refused on resuming, not the save on writing)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return repr(obj)
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _digest(members: list[tuple[str, bytes]]) -> str:
    h = hashlib.sha256()
    for name, data in members:
        h.update(name.encode("utf-8") + b"\0" + struct.pack("<Q", len(data)))
        h.update(data)
    return h.hexdigest()


def checkpoint_bytes(state: dict[str, Any], problem: dict[str, Any]) -> bytes:
    """The file's bytes for `state` (a tree of the types the module docstring lists, torch
    tensors among them) and `problem` (the fit's JSON-ready problem key)."""
    arrays: list[np.ndarray] = []
    tree = _encode(state, arrays)
    header = {"format": FORMAT, "version": VERSION, "problem": _plain(problem), "state": tree,
              "arrays": [{"dtype": a.dtype.str, "shape": list(a.shape)} for a in arrays]}
    members = [(MAGIC_MEMBER, MAGIC),
               (HEADER_MEMBER, json.dumps(header, sort_keys=True, allow_nan=False).encode("utf-8"))]
    for i, a in enumerate(arrays):
        buf = io.BytesIO()
        np.lib.format.write_array(buf, a, allow_pickle=False)
        members.append((f"arrays/{i}.npy", buf.getvalue()))
    members.append((CHECKSUM_MEMBER, _digest(members).encode("ascii")))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members:
            zf.writestr(zipfile.ZipInfo(name, date_time=_ZIP_DATE), data)
    return out.getvalue()


def write_checkpoint(path: str | Path, state: dict[str, Any], problem: dict[str, Any]) -> None:
    """Write the checkpoint atomically (a hidden temporary beside `path`, then a rename).
    A full or read-only disk raises OutputError (one line naming the path) and leaves no
    temporary: atomic_output turns every OSError of the write into one."""
    data = checkpoint_bytes(state, problem)
    with atomic_output(Path(path)) as tmp:
        tmp.write_bytes(data)


# ---------------------------------------------------------------------- identity
def is_pdtool_checkpoint(path: str | Path) -> tuple[bool, str]:
    """Whether `path` is a file pdtool wrote as a fit checkpoint, from its first bytes (so a
    truncated checkpoint still counts); else (False, what it is instead). Follows nothing:
    a symbolic link, a folder or a device is not a checkpoint. Reads at most 512 bytes."""
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False, "absent"
    except OSError as e:
        return False, f"unreadable: {e.strerror or type(e).__name__}"
    if stat.S_ISLNK(st.st_mode):
        return False, "a symbolic link"
    if stat.S_ISDIR(st.st_mode):
        return False, "a folder"
    if not stat.S_ISREG(st.st_mode):  # a FIFO would block the read below
        return False, "not a regular file"
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError as e:
        return False, f"unreadable: {e.strerror or type(e).__name__}"
    # the zip's first local header: signature, ..., method @8, name length @26, extra @28
    if len(head) >= 30 and head[:4] == b"PK\x03\x04":
        method, = struct.unpack_from("<H", head, 8)
        n_name, n_extra = struct.unpack_from("<HH", head, 26)
        name = head[30:30 + n_name]
        data = head[30 + n_name + n_extra:30 + n_name + n_extra + len(MAGIC)]
        if method == 0 and name == MAGIC_MEMBER.encode() and data == MAGIC:
            return True, "a pdtool fit checkpoint"
        if b"data.pkl" in head:
            return False, "a torch pickle, which pdtool never loads"
        return False, "a zip archive of another kind"
    if not head:
        return False, "an empty file"
    return False, "not a pdtool file"


# ---------------------------------------------------------------------- reading
def _npy(data: bytes, name: str, fail) -> np.ndarray:
    """One .npy member, strictly: a known dtype, C order, and exactly the bytes its header
    declares (no trailing bytes, no short data)."""
    fh = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(fh)
    except ValueError:
        raise fail(f"{name} is not a .npy array") from None
    readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
    if version not in readers:
        raise fail(f"{name} is .npy format {version}")
    try:
        shape, fortran, dtype = readers[version](fh)
    # numpy parses the header dict with tokenize and ast.literal_eval (no code), whose failures
    # vary in type (ValueError, SyntaxError, tokenize.TokenError, RecursionError, ...)
    except Exception as e:
        raise fail(f"{name} has no readable .npy header ({type(e).__name__})") from None
    if any(d < 0 for d in shape):
        raise fail(f"{name} declares the shape {tuple(shape)}")
    if dtype not in _DTYPES or fortran:
        raise fail(f"{name} holds {dtype.str}{' in Fortran order' if fortran else ''}, not a fit's numbers")
    count = math.prod(shape)
    if fh.tell() + dtype.itemsize * count != len(data):
        raise fail(f"{name} declares shape {tuple(shape)} but holds {len(data) - fh.tell()} bytes of data")
    return np.frombuffer(data, dtype=dtype, count=count, offset=fh.tell()).reshape(shape).copy()


def _strict_json(raw: bytes, fail) -> Any:
    def constant(name: str) -> Any:
        raise fail(f"its header holds {name}")

    def number(text: str) -> float:
        v = float(text)
        if not math.isfinite(v):  # '1e999' parses as inf
            raise fail(f"its header holds the number {text[:20]}, beyond a float")
        return v

    def pairs(items: list[tuple[str, Any]]) -> dict:
        out = dict(items)
        if len(out) != len(items):
            raise fail("its header repeats a key")
        return out

    try:
        return json.loads(raw.decode("utf-8"), parse_constant=constant, parse_float=number, object_pairs_hook=pairs)
    except CheckpointError:
        raise
    # JSONDecodeError, UnicodeDecodeError and an integer past Python's digit limit are ValueErrors
    except (ValueError, RecursionError) as e:
        raise fail(f"its header is not JSON ({type(e).__name__})") from None


class _Decoder:
    def __init__(self, arrays: list[np.ndarray], fail, nonfinite: tuple[str, ...] = ()) -> None:
        self.arrays = arrays
        self.used = [False] * len(arrays)
        self.fail = fail
        self.nonfinite = nonfinite

    def may_be_nonfinite(self, where: str) -> bool:
        return any(where == p or where.startswith(p + ".") for p in self.nonfinite)

    def __call__(self, node: Any, where: str, depth: int = 0) -> Any:
        if depth > MAX_DEPTH:
            raise self.fail(f"{where} is nested more than {MAX_DEPTH} deep")
        if node is None or isinstance(node, (bool, int, float, str)):
            return node
        if isinstance(node, list):
            return [self(v, f"{where}[{i}]", depth + 1) for i, v in enumerate(node)]
        if not isinstance(node, dict) or len(node) != 1:
            raise self.fail(f"{where} is not a value a checkpoint holds")
        tag, body = next(iter(node.items()))
        if tag == "tuple" and isinstance(body, list):
            return tuple(self(v, f"{where}[{i}]", depth + 1) for i, v in enumerate(body))
        if tag == "dict" and isinstance(body, list):
            out: dict = {}
            for item in body:
                ok = isinstance(item, list) and len(item) == 2
                key = item[0] if ok else None
                if not ok or isinstance(key, bool) or not isinstance(key, (str, int)) or key in out:
                    raise self.fail(f"{where} has a malformed or repeated key")
                out[key] = self(item[1], f"{where}.{key}", depth + 1)
            return out
        if tag == "tensor" and isinstance(body, int) and not isinstance(body, bool):
            if not 0 <= body < len(self.arrays) or self.used[body]:
                raise self.fail(f"{where} names array {body}, which is missing or used twice")
            self.used[body] = True
            a = self.arrays[body]
            if a.dtype.kind == "f" and not np.isfinite(a).all() and not self.may_be_nonfinite(where):
                raise self.fail(f"{where} holds NaN/inf")
            return torch.from_numpy(a)
        if tag == "float" and body in _NONFINITE:
            raise self.fail(f"{where} holds {body}")
        raise self.fail(f"{where} is not a value a checkpoint holds")


def read_checkpoint(path: str | Path, *, max_bytes: int,
                    nonfinite: tuple[str, ...] = ()) -> tuple[dict[str, Any], dict[str, Any]]:
    """(problem key, state tree) of a checkpoint, read without pickles (module docstring).

    max_bytes: the largest file the caller's fit can have written; a larger file is refused
    before anything is read into memory. nonfinite: paths in the tree ("state.losses", and
    what lies under it) whose arrays are records that may hold NaN/inf, as a loss measured
    on a diverged state does. Raises ForeignCheckpointFile when the file is not one pdtool
    wrote, CheckpointError for one that is damaged: truncated, a checksum that does not
    match, unknown members or tags, arrays whose header and size disagree, NaN/inf
    anywhere but under `nonfinite`. Messages are one line naming `path`; the fix is the
    caller's to add.
    """
    path = Path(path)
    ours, what = is_pdtool_checkpoint(path)
    if not ours:
        raise ForeignCheckpointFile(f"{path}: is not a pdtool fit checkpoint ({what})")

    def fail(why: str) -> CheckpointError:
        return CheckpointError(f"{path}: damaged fit checkpoint: {why}")

    size = path.stat().st_size
    if size > max_bytes:
        raise fail(f"{size:,} bytes where this fit writes at most {max_bytes:,}")
    members: dict[str, bytes] = {}
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            order = [info.filename for info in infos]
            n_arrays = len(order) - 3
            # names and sizes first, so that nothing is read from a file laid out otherwise
            # (members that overlap could make a small file read as many times its size)
            if order != [MAGIC_MEMBER, HEADER_MEMBER, *(f"arrays/{i}.npy" for i in range(n_arrays)), CHECKSUM_MEMBER]:
                raise fail("its members are not those of a fit checkpoint")
            for info in infos:
                if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
                    raise fail(f"member {info.filename} is compressed or encrypted")
                if info.file_size != info.compress_size:
                    raise fail(f"member {info.filename} claims {info.file_size:,} bytes in {info.compress_size:,}")
            if sum(info.file_size for info in infos) > size:
                raise fail(f"its members claim more bytes than the file's {size:,}")
            if infos[1].file_size > MAX_HEADER_BYTES:
                raise fail(f"a header of {infos[1].file_size:,} bytes")
            for info in infos:
                members[info.filename] = zf.read(info)
    except CheckpointError:
        raise
    # zipfile raises many types for damaged archives (a cut-off central directory, a bad
    # CRC, an offset past the end of the file, ...)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, ValueError, OSError, EOFError, KeyError,
            NotImplementedError, RuntimeError, struct.error, MemoryError) as e:
        raise fail(f"truncated or corrupt ({type(e).__name__})") from None
    stored = members[CHECKSUM_MEMBER]
    if stored != _digest([(n, members[n]) for n in order[:-1]]).encode("ascii"):
        raise fail("its sha256 checksum does not match its contents")
    header = _strict_json(members[HEADER_MEMBER], fail)
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise fail("its header is not a fit checkpoint's")
    version = header.get("version")
    if type(version) is not int or version != VERSION:
        raise CheckpointError(f"{path}: a fit checkpoint of version {version!r:.20}; this pdtool reads version "
                              f"{VERSION}")
    if set(header) != {"format", "version", "problem", "state", "arrays"}:
        raise fail("its header lacks keys or holds unknown ones")
    listing = header["arrays"]
    if not isinstance(listing, list) or len(listing) != n_arrays:
        raise fail("its array list does not match its members")
    arrays = []
    for i, want in enumerate(listing):
        a = _npy(members[f"arrays/{i}.npy"], f"arrays/{i}.npy", fail)
        if not isinstance(want, dict) or want != {"dtype": a.dtype.str, "shape": list(a.shape)}:
            raise fail(f"arrays/{i}.npy is not the array its header lists")
        arrays.append(a)
    decode = _Decoder(arrays, fail, nonfinite)
    state = decode(header["state"], "state")
    if not all(decode.used):
        raise fail("it holds arrays its state does not use")
    if not isinstance(state, dict) or not isinstance(header["problem"], dict):
        raise fail("its header is not a fit checkpoint's")
    return header["problem"], state
