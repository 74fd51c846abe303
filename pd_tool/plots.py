"""Small PNG charts (loss curves, time-vs-error scatter) drawn with Pillow, which imageio
already brings: no plotting library to install for two kinds of chart."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import numpy as np

from pd_tool.atomic import atomic_output, png_info

_COLORS = [(31, 119, 180), (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (140, 86, 75)]
W, H = 720, 440  # px
L, R, T, B = 80, 20, 40, 60  # margins, px


def _ticks(lo: float, hi: float, log: bool) -> list[float]:
    if log:
        a, b = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
        return [10.0 ** e for e in range(a, b + 1)]
    step = 10 ** math.floor(math.log10(max(hi - lo, 1e-12) / 4))
    for m in (1, 2, 5, 10):
        if (hi - lo) / (step * m) <= 6:
            step *= m
            break
    start = math.ceil(lo / step) * step
    return [start + i * step for i in range(int((hi - start) / step) + 1)]


class _Axes:
    def __init__(self, xs: np.ndarray, ys: np.ndarray, logx: bool, logy: bool) -> None:
        self.logx, self.logy = logx, logy
        fx = np.log10 if logx else (lambda v: v)
        fy = np.log10 if logy else (lambda v: v)
        self.x0, self.x1 = float(np.min(fx(xs))), float(np.max(fx(xs)))
        self.y0, self.y1 = float(np.min(fy(ys))), float(np.max(fy(ys)))
        for a in ("x", "y"):
            lo, hi = getattr(self, a + "0"), getattr(self, a + "1")
            pad = 0.05 * (hi - lo) if hi > lo else 0.5
            setattr(self, a + "0", lo - pad)
            setattr(self, a + "1", hi + pad)
        self.fx, self.fy = fx, fy

    def px(self, x: float, y: float) -> tuple[float, float]:
        u = (float(self.fx(x)) - self.x0) / (self.x1 - self.x0)
        v = (float(self.fy(y)) - self.y0) / (self.y1 - self.y0)
        return L + u * (W - L - R), H - B - v * (H - T - B)


def _frame(draw, ax: _Axes, title: str, xlabel: str, ylabel: str) -> None:
    draw.rectangle([L, T, W - R, H - B], outline=(0, 0, 0))
    draw.text((L, 12), title, fill=(0, 0, 0))
    draw.text(((W + L) / 2 - 3 * len(xlabel), H - 22), xlabel, fill=(0, 0, 0))
    draw.text((6, T - 18), ylabel, fill=(0, 0, 0))
    lo_x, hi_x = (10 ** ax.x0, 10 ** ax.x1) if ax.logx else (ax.x0, ax.x1)
    lo_y, hi_y = (10 ** ax.y0, 10 ** ax.y1) if ax.logy else (ax.y0, ax.y1)
    for t in _ticks(lo_x, hi_x, ax.logx):
        if lo_x <= t <= hi_x:
            x, _ = ax.px(t, lo_y if not ax.logy else 10 ** ax.y0)
            draw.line([x, H - B, x, H - B + 5], fill=(0, 0, 0))
            draw.text((x - 12, H - B + 8), f"{t:.3g}", fill=(0, 0, 0))
    for t in _ticks(lo_y, hi_y, ax.logy):
        if lo_y <= t <= hi_y:
            _, y = ax.px(lo_x if not ax.logx else 10 ** ax.x0, t)
            draw.line([L - 5, y, L, y], fill=(0, 0, 0))
            draw.line([L, y, W - R, y], fill=(230, 230, 230))
            draw.text((8, y - 6), f"{t:.3g}", fill=(0, 0, 0))


def line_plot(path: str | Path, series: dict[str, tuple[Sequence[float], Sequence[float]]], *, title: str,
              xlabel: str, ylabel: str, logy: bool = False, own_only: bool = False) -> Path:
    """Write a PNG with one line per series {name: (x, y)}; atomic, marked as pdtool's.
    own_only: replace an existing file only when pdtool wrote it (a side output)."""
    from PIL import Image, ImageDraw

    xs = np.concatenate([np.asarray(x, float) for x, _ in series.values()])
    ys = np.concatenate([np.asarray(y, float) for _, y in series.values()])
    ok = np.isfinite(ys) & (ys > 0 if logy else True)
    if not ok.any():
        xs, ys = np.array([0.0, 1.0]), np.array([1.0, 2.0])
    ax = _Axes(xs[ok] if ok.any() else xs, ys[ok] if ok.any() else ys, False, logy)
    img = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    _frame(draw, ax, title, xlabel, ylabel)
    for i, (name, (x, y)) in enumerate(series.items()):
        c = _COLORS[i % len(_COLORS)]
        pts = [ax.px(a, b) for a, b in zip(x, y) if math.isfinite(b) and (b > 0 or not logy)]
        if len(pts) > 1:
            draw.line(pts, fill=c, width=2)
        elif pts:
            draw.ellipse([pts[0][0] - 3, pts[0][1] - 3, pts[0][0] + 3, pts[0][1] + 3], fill=c)
        draw.text((W - R - 170, T + 8 + 14 * i), f"- {name}", fill=c)
    path = Path(path)
    with atomic_output(path, own_only=own_only, what=f"the plot '{title}'") as tmp:
        img.save(tmp, format="PNG", pnginfo=png_info())
    return path


def scatter_plot(path: str | Path, points: Sequence[tuple[float, float, str]], *, front: Sequence[int] = (),
                 highlight: dict[int, str] | None = None, title: str, xlabel: str, ylabel: str,
                 logx: bool = True, logy: bool = True, own_only: bool = False) -> Path:
    """Scatter (x, y, label) points; `front` indices are joined by a line (a Pareto front);
    `highlight` {index: name} marks and names chosen points (presets). Atomic, marked as
    pdtool's; own_only: replace an existing file only when pdtool wrote it."""
    from PIL import Image, ImageDraw

    xs = np.array([p[0] for p in points], float)
    ys = np.array([p[1] for p in points], float)
    ax = _Axes(xs, ys, logx, logy)
    img = Image.new("RGB", (W, H), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    _frame(draw, ax, title, xlabel, ylabel)
    if len(front) > 1:
        pts = sorted((ax.px(xs[i], ys[i]) for i in front))
        draw.line(pts, fill=_COLORS[1], width=2)
    for i, (x, y, _) in enumerate(points):
        u, v = ax.px(x, y)
        c = _COLORS[1] if i in front else (120, 120, 120)
        draw.ellipse([u - 3, v - 3, u + 3, v + 3], fill=c)
    for i, name in (highlight or {}).items():
        u, v = ax.px(xs[i], ys[i])
        draw.ellipse([u - 6, v - 6, u + 6, v + 6], outline=_COLORS[2], width=2)
        draw.text((u + 8, v - 14), name, fill=_COLORS[2])
    path = Path(path)
    with atomic_output(path, own_only=own_only, what=f"the plot '{title}'") as tmp:
        img.save(tmp, format="PNG", pnginfo=png_info())
    return path
