"""validate_usd: OpenUSD's registered validators plus pdtool's own checks.

Our checks, for every time sample of every PointInstancer, Points and
ParticleField3DGaussianSplat prim:
- per-point arrays agree in length (positions, orientations, scales, ids,
  protoIndices, widths, colours, opacities, SH = N * (degree+1)^2);
- values are finite; quaternions are unit length (within half-float rounding
  for quath); opacities and colours lie in 0-1;
- the authored extent at that time contains every point;
- the stage has upAxis, metersPerUnit, timeCodesPerSecond, framesPerSecond,
  start/end time codes and a default prim;
- instance ids are distinct across all PointInstancers (a bake splits its
  instances between /Root/Instancer, time-sampled, and /Root/StaticInstancer,
  written once; together they hold each instance once), and at every time sample
  of any of them every instancer yields one position per instance.

`instance_positions(stage, time)` reads the positions of all instances, by id,
across that split.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdValidation

from pd_tool.core.errors import UsdExportError

from ._geom import col_max, col_min

QUAT_TOL = {"quath": 4e-3, "quatf": 1e-4}  # | |q| - 1 |: half has 11-bit mantissas
MAX_REPORTED = 8  # errors quoted in the exception message


def validate_usd(path: str | os.PathLike, *, usd_validators: bool = True,
                 every_sample: bool = True) -> list[str]:
    """Validate a baked USD file; returns the warnings, raises on any error.

    Args:
        path: a .usd/.usdc/.usda file.
        usd_validators: run every validator in pxr.UsdValidation's registry.
        every_sample: run our per-array checks at every time sample; False checks
            the first and last sample only (what UsdBakeWriter.close does: the
            writer already checked every frame's arrays on the way in).
    Returns:
        Warning messages (UsdValidation warnings; they do not fail the file).
    Raises:
        UsdExportError: one line naming the file and the first errors.
    """
    path = Path(path)
    layer = Sdf.Layer.Find(str(path))
    if layer is not None:
        layer.Reload(force=True)  # another handle in this process may be stale
    try:
        stage = Usd.Stage.Open(str(path))
    except Exception as e:
        raise UsdExportError(f"{path}: not a readable USD file ({e})") from e
    errors: list[str] = []
    warnings: list[str] = []
    errors += check_stage_metadata(stage)
    errors += check_instance_split(stage, every_sample)
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointInstancer):
            errors += check_instancer(prim, every_sample)
        elif prim.IsA(UsdGeom.Points):
            errors += check_points(prim, every_sample)
        elif prim.GetTypeName() == "ParticleField3DGaussianSplat":
            errors += check_splat_field(prim, every_sample)
    if usd_validators:  # after ours: the message quotes the first few errors
        _run_usd_validators(stage, errors, warnings)
    if errors:
        more = f" (+{len(errors) - MAX_REPORTED} more)" if len(errors) > MAX_REPORTED else ""
        raise UsdExportError(f"{path}: invalid USD: " + "; ".join(errors[:MAX_REPORTED]) + more)
    return warnings


def _run_usd_validators(stage: Usd.Stage, errors: list[str], warnings: list[str]) -> None:
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    ctx = UsdValidation.ValidationContext(validators)
    for err in ctx.Validate(stage):
        kind = err.GetType()
        msg = f"[{err.GetName()}] {err.GetMessage()}"
        if kind == UsdValidation.ValidationErrorType.Error:
            errors.append(msg)
        elif kind == UsdValidation.ValidationErrorType.Warn:
            warnings.append(msg)


def check_stage_metadata(stage: Usd.Stage) -> list[str]:
    """Stage-level metadata a DCC needs to place and time the animation."""
    root = stage.GetRootLayer()
    errs = []
    missing = [key for key in ("upAxis", "metersPerUnit", "timeCodesPerSecond",
                               "framesPerSecond", "startTimeCode", "endTimeCode")
               if not root.pseudoRoot.HasInfo(key)]
    if missing:
        errs.append(f"stage metadata not authored: {', '.join(missing)}")
    if not stage.GetDefaultPrim():
        errs.append("no default prim")
    if stage.GetEndTimeCode() < stage.GetStartTimeCode():
        errs.append("endTimeCode < startTimeCode")
    return errs


def _times(every_sample: bool, *attrs: Usd.Attribute) -> list:
    ts = sorted({t for a in attrs for t in a.GetTimeSamples()})
    if not every_sample and len(ts) > 2:
        ts = [ts[0], ts[-1]]
    return ts or [Usd.TimeCode.Default()]


def _arr(attr: Usd.Attribute, t) -> np.ndarray | None:
    v = attr.Get(t)
    if v is None:
        return None
    # Vt arrays expose a buffer (quaternions as x, y, z, w); float32 for the checks.
    return np.asarray(v).astype(np.float32, copy=False)


def _check_common(name: str, t, arrays: dict[str, np.ndarray | None], n: int,
                  extent: np.ndarray | None, positions: np.ndarray) -> list[str]:
    errs = []
    for key, a in arrays.items():
        if a is None:
            continue
        if len(a) != n:
            errs.append(f"{name}.{key} has {len(a)} elements at time {t}, expected {n}")
        elif not np.isfinite(a).all():
            errs.append(f"{name}.{key} holds NaN/inf at time {t}")
    if extent is None:
        errs.append(f"{name}.extent is missing at time {t}")
    elif n and np.isfinite(positions).all():
        lo, hi = extent[0], extent[1]
        if (col_min(positions) < lo).any() or (col_max(positions) > hi).any():
            errs.append(f"{name}.extent at time {t} does not contain all points")
    return errs


def _check_quats(name: str, t, q: np.ndarray | None, kind: str) -> list[str]:
    if q is None or len(q) == 0:
        return []
    dev = np.abs(np.linalg.norm(q.astype(np.float64), axis=1) - 1.0).max()
    if dev > QUAT_TOL[kind]:
        return [f"{name}.orientations not unit length at time {t} (max | |q|-1 | = {dev:.2g})"]
    return []


def _check_range(name: str, key: str, a: np.ndarray | None) -> list[str]:
    if a is None or len(a) == 0:
        return []
    if a.min() < 0 or a.max() > 1:
        return [f"{name}.{key} outside 0-1 ({a.min():g}..{a.max():g})"]
    return []


def _instancers(stage: Usd.Stage) -> list[UsdGeom.PointInstancer]:
    return [UsdGeom.PointInstancer(p) for p in stage.Traverse() if p.IsA(UsdGeom.PointInstancer)]


_WIDTHS = {"positions": 3, "orientations": 4, "scales": 3}  # what instance_arrays reads


def instance_arrays(stage: Usd.Stage, time=Usd.TimeCode.Default(),
                    names: tuple[str, ...] = ("positions",)) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """(ids [N] int64 sorted, static [N] bool, {name: [N, k] float32}) of every instance of
    every PointInstancer on the stage at `time`: the moving and the static prims together,
    which is what a DCC shows at that frame. `names` of positions [N, 3], orientations
    [N, 4] (as stored: x, y, z, w) and scales [N, 3]; `static`: the instance sits in a
    Static* prim, written once."""
    ids, static, cols = [], [], {n: [] for n in names}
    for inst in _instancers(stage):
        prim = inst.GetPrim()
        for n in names:
            v = prim.GetAttribute(n).Get(time)
            cols[n].append(np.zeros((0, _WIDTHS[n]), np.float32) if v is None
                           else np.asarray(v, dtype=np.float32).reshape(-1, _WIDTHS[n]))
        i = inst.GetIdsAttr().Get()
        count = len(i) if i is not None else len(cols[names[0]][-1]) if names else 0
        ids.append(np.arange(count, dtype=np.int64) if i is None else np.asarray(i, dtype=np.int64))
        static.append(np.full(count, prim.GetName().startswith("Static")))
    if not ids:
        return (np.zeros(0, np.int64), np.zeros(0, bool),
                {n: np.zeros((0, _WIDTHS[n]), np.float32) for n in names})
    ids_all = np.concatenate(ids)
    order = np.argsort(ids_all, kind="stable")
    return ids_all[order], np.concatenate(static)[order], {n: np.concatenate(c)[order] for n, c in cols.items()}


def instance_positions(stage: Usd.Stage, time=Usd.TimeCode.Default()) -> tuple[np.ndarray, np.ndarray]:
    """(ids [N] int64 sorted, positions [N, 3] float32) of every instance at `time`
    (instance_arrays)."""
    ids, _, cols = instance_arrays(stage, time)
    return ids, cols["positions"]


def check_instance_split(stage: Usd.Stage, every_sample: bool = True) -> list[str]:
    """Instances split over several PointInstancers: each id once, and at every time any
    of them is sampled (a static prim has none) each yields one position per instance."""
    insts = _instancers(stage)
    if len(insts) < 2:
        return []
    errs = []
    all_ids = [np.asarray(i.GetIdsAttr().Get() or [], np.int64) for i in insts]
    ids = np.concatenate(all_ids)
    if np.unique(ids).size != ids.size:
        errs.append("instance ids repeat across " + ", ".join(str(i.GetPath()) for i in insts))
    times = _times(every_sample, *(i.GetPositionsAttr() for i in insts))
    for t in times:
        for inst, i in zip(insts, all_ids):
            p = inst.GetPositionsAttr().Get(t)
            if p is None or len(p) != len(i):
                errs.append(f"{inst.GetPath()}.positions has {0 if p is None else len(p)} elements at time "
                            f"{t}, expected {len(i)}")
    return errs


def check_instancer(prim: Usd.Prim, every_sample: bool = True) -> list[str]:
    inst = UsdGeom.PointInstancer(prim)
    name = str(prim.GetPath())
    errs = []
    proto = inst.GetProtoIndicesAttr().Get()
    n = 0 if proto is None else len(proto)
    targets = inst.GetPrototypesRel().GetTargets()
    if proto is not None and n and (np.asarray(proto).max() >= len(targets) or np.asarray(proto).min() < 0):
        errs.append(f"{name}.protoIndices point past the {len(targets)} prototypes")
    ids = inst.GetIdsAttr().Get()
    if ids is not None and len(ids) != n:
        errs.append(f"{name}.ids has {len(ids)} elements, expected {n}")
    pv = UsdGeom.PrimvarsAPI(prim)
    for key in ("displayColor", "displayOpacity"):
        p = pv.GetPrimvar(key)
        if p and p.HasValue():
            v = np.asarray(p.Get())
            if len(v) != n:
                errs.append(f"{name}.primvars:{key} has {len(v)} elements, expected {n}")
            errs += _check_range(name, f"primvars:{key}", v)
    pos_a, ori_a, sc_a, ext_a = (inst.GetPositionsAttr(), inst.GetOrientationsAttr(),
                                 inst.GetScalesAttr(), inst.GetExtentAttr())
    for t in _times(every_sample, pos_a, ori_a, sc_a):
        pos = _arr(pos_a, t)
        if pos is None:
            errs.append(f"{name}.positions missing at time {t}")
            continue
        ori, sc = _arr(ori_a, t), _arr(sc_a, t)
        errs += _check_common(name, t, {"positions": pos, "orientations": ori,
                                        "scales": sc}, n, _arr(ext_a, t), pos)
        errs += _check_quats(name, t, ori, "quath")
        if sc is not None and len(sc) and not (sc > 0).all():
            errs.append(f"{name}.scales not positive at time {t}")
    return errs


def check_points(prim: Usd.Prim, every_sample: bool = True) -> list[str]:
    pts = UsdGeom.Points(prim)
    name = str(prim.GetPath())
    errs = []
    p_a, ext_a = pts.GetPointsAttr(), pts.GetExtentAttr()
    widths = pts.GetWidthsAttr().Get()
    color = pts.GetDisplayColorPrimvar().Get() if pts.GetDisplayColorPrimvar().HasValue() else None
    opac = pts.GetDisplayOpacityPrimvar().Get() if pts.GetDisplayOpacityPrimvar().HasValue() else None
    for t in _times(every_sample, p_a):
        pos = _arr(p_a, t)
        if pos is None:
            errs.append(f"{name}.points missing at time {t}")
            continue
        n = len(pos)
        errs += _check_common(name, t, {
            "widths": None if widths is None else np.asarray(widths),
            "primvars:displayColor": None if color is None else np.asarray(color),
            "primvars:displayOpacity": None if opac is None else np.asarray(opac)},
            n, _arr(ext_a, t), pos)
    errs += _check_range(name, "primvars:displayColor", None if color is None else np.asarray(color))
    return errs


def check_splat_field(prim: Usd.Prim, every_sample: bool = True) -> list[str]:
    name = str(prim.GetPath())
    errs = []
    # the schema's orientations (quatf) win over orientationsh (quath) when both are authored
    ori_a = prim.GetAttribute("orientations")
    quat_kind = "quatf"
    if not ori_a.HasAuthoredValue() and prim.GetAttribute("orientationsh").HasAuthoredValue():
        ori_a, quat_kind = prim.GetAttribute("orientationsh"), "quath"
    pos_a, sc_a = prim.GetAttribute("positions"), prim.GetAttribute("scales")
    ext_a = prim.GetAttribute("extent")
    deg = prim.GetAttribute("radiance:sphericalHarmonicsDegree").Get()
    sh = prim.GetAttribute("radiance:sphericalHarmonicsCoefficients").Get()
    opac = prim.GetAttribute("opacities").Get()
    for t in _times(every_sample, pos_a, ori_a, sc_a):
        pos = _arr(pos_a, t)
        if pos is None:
            errs.append(f"{name}.positions missing at time {t}")
            continue
        n = len(pos)
        ori = _arr(ori_a, t)
        sc = _arr(sc_a, t)
        errs += _check_common(name, t, {"orientations": ori, "scales": sc,
                                        "opacities": None if opac is None else np.asarray(opac)},
                              n, _arr(ext_a, t), pos)
        errs += _check_quats(name, t, ori, quat_kind)
        if sc is not None and len(sc) and not (sc > 0).all():
            errs.append(f"{name}.scales not positive at time {t}")
        if sh is not None and deg is not None and len(sh) != n * (deg + 1) ** 2:
            errs.append(f"{name}: {len(sh)} SH coefficients for {n} splats of degree {deg}, "
                        f"expected {n * (deg + 1) ** 2}")
    errs += _check_range(name, "opacities", None if opac is None else np.asarray(opac))
    return errs
