"""INRIA 3DGS .ply reading and writing (binary little/big endian and ASCII).

Stored values in the file: opacity is a logit, scale_* are log standard deviations,
rot_* a quaternion (w, x, y, z) not necessarily normalised, f_dc_* the degree-0 SH
coefficients, f_rest_* the higher ones grouped by colour channel (all R, then G, then B).
"""
from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import torch

from pd_tool.core.atomic import MARK_TEXT, atomic_output
from pd_tool.core.errors import PlyFormatError
from pd_tool.core.scene import REQUIRED_PLY_PROPERTIES, GaussianScene, sh_coeff_count

NORMAL_PROPERTIES = ("nx", "ny", "nz")
LABEL_PROPERTY = "region"  # optional integer region label (pdtool's synthetic scenes write it)
# the labels' names, in a header comment: "pdtool region_names pot,stem,leaf,flower"
REGION_NAMES_COMMENT = "pdtool region_names "
_REGION_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_REST_RE = re.compile(r"^f_rest_(\d+)$")
_VALID_REST_COUNTS = {3 * (sh_coeff_count(d) - 1): d for d in range(4)}  # 0, 9, 24, 45
F32_MAX = float(np.finfo(np.float32).max)  # the scene holds float32: larger values would become inf


def _read_plydata(path: Path):
    from plyfile import PlyData

    if path.stat().st_size == 0:
        raise PlyFormatError(f"{path}: file is empty; export the splat again")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic[:3] != b"ply":
        raise PlyFormatError(f"{path}: not a PLY file (it does not start with 'ply'); pass a 3DGS .ply or .splat file")
    try:
        # plyfile / numpy warn on some malformed bodies (loadtxt: "input contained no data");
        # the values are validated after parsing, and a warning would break the one-line error
        with warnings.catch_warnings(), open(path, "rb") as fh:
            warnings.simplefilter("ignore")
            ply = PlyData.read(fh)
            if not ply.text:
                # plyfile stops after the counted records: a header that undercounts would
                # silently drop Gaussians, and trailing bytes would go unnoticed
                extra = len(fh.read(1 << 16))
                if extra:
                    raise PlyFormatError(
                        f"{path}: {'at least ' * (extra == 1 << 16)}{extra} bytes follow the "
                        f"{_counts(ply)} the header declares; the header's element count is wrong or the "
                        f"file is corrupt; export the splat again")
    except PlyFormatError:
        raise
    except MemoryError:
        raise PlyFormatError(f"{path}: header declares more data than memory holds; the file is corrupt") from None
    except Exception as e:  # plyfile raises several types (PlyParseError, ValueError, EOFError...)
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        hint = "the file is truncated or corrupt; export it again"
        raise PlyFormatError(f"{path}: cannot parse PLY ({msg}); {hint}") from None
    if ply.text:
        _check_ascii_rows(path, ply)
    return ply


def _counts(ply) -> str:
    return ", ".join(f"{el.count:,} {el.name} records" for el in ply.elements) or "no elements"


def _check_ascii_rows(path: Path, ply) -> None:
    # plyfile reads one line per record and ignores whatever follows the counted ones
    with open(path, "rb") as fh:
        for line in fh:
            if line.strip() == b"end_header":
                break
        rows = sum(1 for line in fh if line.strip())
    declared = sum(el.count for el in ply.elements)
    if rows != declared:
        raise PlyFormatError(f"{path}: the body holds {rows:,} rows but the header declares {_counts(ply)}; "
                             f"the header's element count is wrong or the file is corrupt; export the splat again")


def load_ply(path: str | Path, device: str | torch.device = "cpu") -> GaussianScene:
    """Read an INRIA-layout 3DGS .ply into a GaussianScene.

    The SH degree (0-3) is inferred from the number of f_rest_* properties, normals are
    optional, unknown extra properties are kept in `raw` and written back by save_ply.
    Raises PlyFormatError with one line for every malformed input.
    """
    path = Path(path)
    ply = _read_plydata(path)
    try:
        vertex = ply["vertex"]
    except KeyError:
        raise PlyFormatError(f"{path}: no 'vertex' element; a 3DGS PLY stores Gaussians as vertices") from None
    data = vertex.data
    names = list(data.dtype.names or ())
    missing = [p for p in REQUIRED_PLY_PROPERTIES if p not in names]
    if missing:
        raise PlyFormatError(
            f"{path}: missing {', '.join(repr(m) for m in missing)}; a 3DGS PLY needs "
            f"x y z f_dc_0..2 opacity scale_0..2 rot_0..3 (found: {', '.join(names) or 'none'})"
        )
    if len(data) == 0:
        raise PlyFormatError(f"{path}: holds 0 Gaussians; export a non-empty splat")
    rest_idx = sorted(int(m.group(1)) for n in names if (m := _REST_RE.match(n)))
    if len(rest_idx) not in _VALID_REST_COUNTS or rest_idx != list(range(len(rest_idx))):
        raise PlyFormatError(
            f"{path}: {len(rest_idx)} f_rest_* properties; expected f_rest_0..N-1 with N in 0, 9, 24, 45 "
            f"(SH degree 0-3)"
        )
    degree = _VALID_REST_COUNTS[len(rest_idx)]
    known = set(REQUIRED_PLY_PROPERTIES) | set(NORMAL_PROPERTIES) | {f"f_rest_{i}" for i in rest_idx}
    extra = tuple(n for n in names if n not in known)
    # plyfile stores a `property list ...` as an object array of arrays; 3DGS values are scalars
    lists = [p for p in names if p in known and data.dtype[p].kind not in "biuf"]
    if lists:
        raise PlyFormatError(f"{path}: {', '.join(repr(p) for p in lists[:3])} declared as a list property; "
                             f"a 3DGS PLY stores one number per property (export the splat again)")

    def col(*props: str) -> np.ndarray:
        # a signalling NaN (garbage bytes) raises numpy's "invalid value in cast" warning when
        # widened; NaNs are refused with one line below, so the warning would only add a line
        with np.errstate(invalid="ignore"):
            return np.stack([np.asarray(data[p], dtype=np.float64) for p in props], axis=1)

    xyz = col("x", "y", "z")
    log_scales = col("scale_0", "scale_1", "scale_2")
    rot = col("rot_0", "rot_1", "rot_2", "rot_3")
    opacity_logits = col("opacity")[:, 0]
    f_dc = col("f_dc_0", "f_dc_1", "f_dc_2")
    k = sh_coeff_count(degree)
    if degree > 0:
        f_rest = col(*[f"f_rest_{i}" for i in rest_idx]).reshape(-1, 3, k - 1).transpose(0, 2, 1)
        sh = np.concatenate([f_dc[:, None, :], f_rest], axis=1)
    else:
        sh = f_dc[:, None, :]

    for label, arr, props, limit in (
        ("position", xyz, "x y z", F32_MAX),
        ("scale", log_scales, "scale_0..2", F32_MAX),
        ("rotation", rot, "rot_0..3", F32_MAX),  # a double beyond 1e154 would overflow the norm
        ("opacity", opacity_logits, "opacity", F32_MAX),
        ("colour", sh, "f_dc/f_rest", F32_MAX),
    ):
        # a double-precision PLY can hold finite values that are inf once stored as float32
        bad = ~(np.abs(arr.reshape(len(arr), -1)) <= limit).all(axis=1)  # also true for NaN
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise PlyFormatError(
                f"{path}: {int(bad.sum())} Gaussians have NaN/inf {label} ({props}), first at index {first}; "
                f"remove them in your splat editor or export again"
            )
    norms = np.linalg.norm(rot, axis=1)
    zero = norms < 1e-12
    if zero.any():
        raise PlyFormatError(
            f"{path}: {int(zero.sum())} Gaussians have a zero-length rotation quaternion (rot_0..3), "
            f"first at index {int(np.flatnonzero(zero)[0])}; remove them or export again"
        )
    with np.errstate(over="ignore"):
        scales = np.exp(log_scales)
    if not (scales <= F32_MAX).all():
        raise PlyFormatError(f"{path}: scale_* values overflow exp() (log-scale > 88.7, beyond float32); the file is corrupt")

    with np.errstate(over="ignore"):  # exp(-logit) -> inf for logits below -709 gives opacity 0, as it should
        opacities = 1.0 / (1.0 + np.exp(-opacity_logits))

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, dtype=torch.float32).to(device)

    # integer labels only: casting a float or list 'region' would warn or fail (it stays in raw)
    has_labels = LABEL_PROPERTY in names and data.dtype[LABEL_PROPERTY].kind in "iu"
    labels = np.asarray(data[LABEL_PROPERTY], np.int32) if has_labels else None
    label_names = _region_names(ply.comments, labels)

    return GaussianScene(
        positions=t(xyz),
        quats=t(rot / norms[:, None]),
        scales=t(scales),
        opacities=t(opacities),
        sh=t(sh),
        raw=np.array(data),  # own a contiguous copy independent of the PlyData object
        source=path,
        source_format="ply-ascii" if ply.text else f"ply-binary-{'le' if ply.byte_order in ('<', '=') else 'be'}",
        extra=extra,
        labels=labels,
        label_names=label_names,
    )


def _region_names(comments: list[str], labels: np.ndarray | None) -> tuple[str, ...]:
    """The labels' names from the header's region_names comment, or (): without labels, or
    when the comment is missing, names fewer regions than the labels use, or holds anything
    but short plain names (it is a file from anywhere: text, never code)."""
    if labels is None or labels.min(initial=0) < 0:
        return ()
    for c in comments:
        if c.startswith(REGION_NAMES_COMMENT):
            names = tuple(c[len(REGION_NAMES_COMMENT):].strip().split(","))
            ok = len(names) <= 256 and all(_REGION_NAME_RE.match(n) for n in names)
            return names if ok and len(names) > labels.max(initial=-1) else ()
    return ()


def scene_to_records(scene: GaussianScene) -> np.ndarray:
    """Raw INRIA vertex records for a scene: its own raw values when it has them,
    otherwise values computed from the activated ones (logit, log, grouped f_rest)."""
    if scene.raw is not None:
        return scene.raw
    n = scene.count
    k = scene.sh.shape[1]
    rest_names = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    fields = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest_names,
              "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    dtype = [(f, "<f4") for f in fields]
    if scene.labels is not None:
        dtype.append((LABEL_PROPERTY, "<i4"))
    rec = np.zeros(n, dtype=dtype)
    if scene.labels is not None:
        rec[LABEL_PROPERTY] = scene.labels
    pos = scene.positions.detach().cpu().double().numpy()
    sh = scene.sh.detach().cpu().double().numpy()
    op = scene.opacities.detach().cpu().double().numpy().clip(1e-7, 1 - 1e-7)
    sc = scene.scales.detach().cpu().double().numpy().clip(1e-30, None)
    q = scene.quats.detach().cpu().double().numpy()
    for i, c in enumerate("xyz"):
        rec[c] = pos[:, i]
    for i in range(3):
        rec[f"f_dc_{i}"] = sh[:, 0, i]
        rec[f"scale_{i}"] = np.log(sc[:, i])
    rest = sh[:, 1:, :].transpose(0, 2, 1).reshape(n, -1)  # channel-major, as the INRIA layout stores it
    for i, name in enumerate(rest_names):
        rec[name] = rest[:, i]
    rec["opacity"] = np.log(op / (1 - op))
    for i in range(4):
        rec[f"rot_{i}"] = q[:, i]
    return rec


def save_ply(scene: GaussianScene, path: str | Path, *, text: bool = False, byte_order: str = "<",
             own_only: bool = False, what: str = "a splat file") -> Path:
    """Write the scene as an INRIA-layout .ply; atomic (temporary file, then rename).

    A scene read by load_ply is written from its raw records, so a round trip is
    bit-identical in every value, extra properties included. The header carries the
    comment "written by pdtool" (pd_tool.core.atomic's mark), and a labelled scene's region
    names (REGION_NAMES_COMMENT). own_only: replace an existing
    file only when pdtool wrote it (a side output); `what` names it in that refusal.
    Raises OutputError when the file cannot be written.
    """
    from plyfile import PlyData, PlyElement

    path = Path(path)
    records = scene_to_records(scene)
    el = PlyElement.describe(records, "vertex")
    with atomic_output(path, own_only=own_only, what=what) as tmp:
        comments = [MARK_TEXT]
        if scene.labels is not None and scene.label_names:
            comments.append(REGION_NAMES_COMMENT + ",".join(scene.label_names))
        PlyData([el], text=text, byte_order=byte_order, comments=comments).write(str(tmp))
    return path
