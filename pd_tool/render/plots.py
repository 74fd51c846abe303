"""Small PNG charts (loss curves, time-vs-error scatter) and a labelled colour bar, drawn
with Pillow, which imageio already brings: no plotting library to install for them."""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from pd_tool.core.atomic import atomic_output, png_info

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


def log_ticks(lo: float, hi: float) -> list[float]:
    """Ticks for a log axis from lo to hi (both > 0), ascending, all inside [lo, hi]: the
    powers of ten there when there are at least three; else 1, 2 and 5 times them when
    that gives two or more; else evenly spaced values (a range under about a factor of 2.5)."""
    if not (0.0 < lo <= hi and math.isfinite(hi)):
        raise ValueError(f"log_ticks needs 0 < lo <= hi, finite; got lo={lo}, hi={hi}")
    if lo == hi:
        return [lo]
    # lo and hi often come back from 10 ** log10(E): a decade they sit on must not fall out
    a, b = lo * (1 - 1e-9), hi * (1 + 1e-9)
    decades = [t for t in _ticks(lo, hi, True) if a <= t <= b]
    if len(decades) >= 3:
        return decades
    e0, e1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    fine = [m * 10.0 ** e for e in range(e0, e1 + 1) for m in (1, 2, 5) if a <= m * 10.0 ** e <= b]
    if len(fine) >= 2:
        return fine
    return [t for t in _ticks(lo, hi, False) if a <= t <= b]


def sci_label(v: float) -> str:
    """A short label for a tick on a log axis: 1e4, 2.5e5, 1.15e5 (three digits at most)."""
    m, e = f"{v:.2e}".split("e")
    return f"{m.rstrip('0').rstrip('.')}e{int(e)}"


STRIP_MIN_WIDTH = 256  # px: room for a line of statistics under a small render
_PAD = 10  # px, the strip's margins
_BAR_H = 14  # px, height of the colour ramp


def colorbar_strip(width: int, lo: float, hi: float, cmap: Callable[[np.ndarray], np.ndarray], *, label: str,
                   notes: Sequence[str] = ()) -> np.ndarray:
    """A white strip to put under a picture: `label`, then a horizontal colour ramp for
    values lo..hi on a log scale (left = lo, colour cmap(u) for u in 0-1 along it), ticks at
    log_ticks(lo, hi) labelled with sci_label, then each note, wrapped to the width.

    cmap: u [N] in 0-1 -> RGB [N, 3] in 0-1. Returns uint8 [h, width, 3]; h follows the
    text. Raises ValueError for lo, hi not 0 < lo <= hi or a width under 2 * margin + 2."""
    from PIL import Image, ImageDraw

    if width < 2 * _PAD + 2:
        raise ValueError(f"colorbar_strip: width {width} px leaves no room for the bar")
    ticks = log_ticks(lo, hi)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    line_h = probe.textbbox((0, 0), "Ag")[3] + 4
    lines = [ln for note in notes for ln in _wrap(probe, note, width - 2 * _PAD)]
    h = _PAD + line_h + _BAR_H + 6 + line_h + 4 + line_h * len(lines) + _PAD
    img = Image.new("RGB", (width, h), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    draw.text((_PAD, _PAD), label, fill=(0, 0, 0))
    x0, n, y0 = _PAD, width - 2 * _PAD, _PAD + line_h
    ramp = np.clip(np.asarray(cmap(np.linspace(0.0, 1.0, n)), np.float64) * 255 + 0.5, 0, 255).astype(np.uint8)
    img.paste(Image.fromarray(np.repeat(ramp[None], _BAR_H, axis=0)), (x0, y0))
    span = math.log10(hi / lo) if hi > lo else 1.0
    right = -1.0  # x where the last drawn tick label ends: a label that would overlap it is left out
    for t in ticks:
        x = x0 + (math.log10(t / lo) / span if hi > lo else 0.5) * (n - 1)
        draw.line([x, y0 + _BAR_H, x, y0 + _BAR_H + 4], fill=(0, 0, 0))
        text = sci_label(t)
        tw = draw.textlength(text)
        left = min(max(x - tw / 2, 0.0), width - tw)
        if left > right + 4:
            draw.text((left, y0 + _BAR_H + 6), text, fill=(0, 0, 0))
            right = left + tw
    y = y0 + _BAR_H + 6 + line_h + 4
    for ln in lines:
        draw.text((_PAD, y), ln, fill=(0, 0, 0))
        y += line_h
    return np.asarray(img)


def _wrap(draw, text: str, width: float) -> list[str]:
    """text in lines no wider than width px, broken after a comma or colon where it can be
    (a value stays with its name), else at spaces; a longer word keeps its own line."""
    out: list[str] = []
    for chunk in re.split(r"(?<=[,:]) ", text):
        if out and draw.textlength(out[-1] + " " + chunk) <= width:
            out[-1] += " " + chunk
            continue
        out.append("")
        for word in chunk.split(" "):
            if out[-1] and draw.textlength(out[-1] + " " + word) > width:
                out.append(word)
            else:
                out[-1] = f"{out[-1]} {word}" if out[-1] else word
    return out


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
