"""What is in a splat file: counts, bounds, statistics (behind `pdtool info`)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from pd_tool.core.scene import GaussianScene
from pd_tool.prepare.orient import guess_up, object_heights

ROBUST_QUANTILE = 0.01  # the robust box ignores this fraction of points at each end, per axis


def _stats(values: np.ndarray) -> dict[str, float]:
    return {
        "min": float(values.min()),
        "median": float(np.median(values)),
        "mean": float(values.mean()),
        "max": float(values.max()),
    }


def scene_summary(scene: GaussianScene) -> dict[str, Any]:
    """A JSON-ready summary of a scene (scene units throughout)."""
    pos = scene.positions.detach().cpu().double().numpy()
    scales = scene.scales.detach().cpu().double().numpy()
    opac = scene.opacities.detach().cpu().double().numpy()
    lo = np.quantile(pos, ROBUST_QUANTILE, axis=0)
    hi = np.quantile(pos, 1 - ROBUST_QUANTILE, axis=0)
    out: dict[str, Any] = {
        "file": str(scene.source) if scene.source else None,
        "format": scene.source_format,
        "count": scene.count,
        "sh_degree": scene.sh_degree,
        "bbox_min": pos.min(axis=0).tolist(),
        "bbox_max": pos.max(axis=0).tolist(),
        "robust_bbox_min": lo.tolist(),
        "robust_bbox_max": hi.tolist(),
        "robust_extent": (hi - lo).tolist(),
        "opacity": _stats(opac),
        "transparent_fraction": float((opac < 1.0 / 255.0).mean()),
        "scale": _stats(scales.max(axis=1)),
        "memory_bytes": scene.nbytes(),
        "extra_properties": list(scene.extra),
    }

    guess = guess_up(pos, scales, opac)
    bottom, top = object_heights(pos, guess.axis, opac)
    out["up"] = {"axis": guess.axis, "sure": guess.sure, "axis_margin": guess.axis_gap, "end_margin": guess.sign_gap,
                 "bottom": bottom, "top": top, "height": top - bottom}
    if scene.source is not None and Path(scene.source).exists():
        out["file_bytes"] = Path(scene.source).stat().st_size
    return out


def format_bytes(n: float) -> str:
    """1536 -> '1.5 KiB'."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if n < 1024 or unit == "GiB":
            return f"{n:.1f} {unit}" if unit != "B" else f"{int(n)} B"
        n /= 1024
    return f"{n:.1f} GiB"


def format_summary(s: dict[str, Any]) -> str:
    """Human-readable text for scene_summary's dict."""
    def vec(v: list[float]) -> str:
        return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"

    lines = [
        f"file          {s['file']}",
        f"format        {s['format']}",
        f"Gaussians     {s['count']:,}",
        f"SH degree     {s['sh_degree']}",
        f"bbox          {vec(s['bbox_min'])} .. {vec(s['bbox_max'])}",
        f"robust bbox   {vec(s['robust_bbox_min'])} .. {vec(s['robust_bbox_max'])}  (1%..99% per axis)",
        f"opacity       min {s['opacity']['min']:.3g}  median {s['opacity']['median']:.3g}  "
        f"max {s['opacity']['max']:.3g}  ({100 * s['transparent_fraction']:.1f}% invisible)",
        f"scale (max)   min {s['scale']['min']:.3g}  median {s['scale']['median']:.3g}  max {s['scale']['max']:.3g}",
        f"memory        {format_bytes(s['memory_bytes'])} in pdtool"
        + (f", {format_bytes(s['file_bytes'])} on disk" if "file_bytes" in s else ""),
    ]
    if "up" in s:
        u = s["up"]
        lines.append(f"up (guess)    {u['axis']}, {'sure' if u['sure'] else 'not sure'} (margins {u['axis_margin']:.2f} "
                     f"axis, {u['end_margin']:.2f} end; --up auto uses it{'' if u['sure'] else ' and says so'})")
        lines.append(f"height        {u['height']:.4g} along {u['axis']}: bottom at {u['bottom']:.4g}, top at "
                     f"{u['top']:.4g} (--static-below takes a coordinate along {u['axis']}, e.g. "
                     f"{u['bottom'] + 0.15 * u['height']:.4g} = 15% up, or the percentage 15%)")
    if s["extra_properties"]:
        lines.append(f"extra props   {', '.join(s['extra_properties'])} (kept on write)")
    return "\n".join(lines)
