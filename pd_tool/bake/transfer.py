"""Carry a fitted material to another discretisation, so that it moves as it did in its fit.

A fit finds E on its own grid, driver ratio and CFL safety. Where parts are thinner than a
few cells, MPM's stiffness depends on the cell (docs/benchmarks.md, "Convergence against a
fine reference"): the fitted E, baked on the finer grid of another quality, moves
differently from the motion the fit matched to the video. `match_fit_motion` scales E by
one factor until the bake's discretisation moves as the fit's does under the bake's own
force, over a short window.

The motion compared is how far the object swings, as the convergence benchmark's peak: the
largest over the window's frames of the 99th percentile over the Gaussians of their
displacement from rest, in scene units. The baker measures the same sample of Gaussians on
both discretisations, each moved by its own drivers as the bake moves it, so that two
discretisations with different drivers compare as the eye sees them. (Taking each
Gaussian's largest displacement first and the percentile of those, the tree baked at final
matched within 0.2% and its peak still read 7% less: the parts of a tree swing at different
times, and the two measures weigh that differently on two discretisations.)

The motion falls as E rises (as 1/E for a slow push, as 1/sqrt(E) for a tap, and more
weakly while the push itself sets the motion), so the factor is found by a safeguarded
secant search on log(motion) against log(factor): secant steps while the sign of the error
holds, regula falsi inside the bracket once it changes. Where the motion barely answers E
(a part that flies off, a push that sets the motion), no factor matches, and the fitted E
is kept as it is.

One factor for the whole object. Factors per part (k-means parts, thin and thick apart,
with Broyden steps) did not converge in five runs on the thin plant: a leaf rides on its
stem, so a part's motion answers its neighbours' E as much as its own (docs/fitting.md).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

TOLERANCE = 0.03  # |log(motion / the fit's motion)| at which the bake counts as matched
MAX_RUNS = 5  # simulations on the bake's discretisation, the first (unscaled) included
MAX_FACTOR = 100.0  # E is never scaled beyond this either way
MAX_STEP = math.log(10.0)  # a run changes the factor at most tenfold
FIRST_SLOPE = -0.5  # d log(motion) / d log(E) before two runs measure it: a tap's
SLOPES = (-2.0, -0.1)  # measured slopes are clipped to this range
# a measured slope flatter than this: the motion under this force barely depends on E (a
# part that flies off, a push that sets the motion), so E is left as fitted
FLAT_SLOPE = 0.1
QUANTILE = 0.99  # of the Gaussians: how far the object swings, as bench/convergence.py's peak
RING_S = 1.0  # s of motion after the force ends that the window keeps


@dataclass
class Discretisation:
    """One way of simulating the object: its drivers' E [Q] (Pa), and a `run(E, frames)`
    that simulates `frames` frames from rest under the bake's force and returns the squared
    displacement of each measured point [P] at each frame [frames, P] (m^2). The points are
    what the motion is read from (the baker: a sample of the moving Gaussians); static [P]
    marks those that do not count, weight [P] what each counts for; `scale`: metres per
    scene unit."""

    static: np.ndarray
    weight: np.ndarray
    E: np.ndarray
    run: Callable[[np.ndarray, int], np.ndarray]
    scale: float


@dataclass
class MotionMatch:
    """The result: E [Q] (Pa) for the bake's drivers, the factor it applied, the bake's
    motion over the fit's after the last run, runs on the bake's discretisation, seconds
    (both discretisations' runs), the window (s) and whether it is within the tolerance."""

    E: np.ndarray
    factor: float
    ratio: float
    runs: int
    seconds: float
    window_s: float
    matched: bool
    flat: bool = False  # the motion barely answered E: the fitted E is kept

    def line(self, fit_grid: int, grid: int) -> str:
        """The report line of the bake."""
        if self.flat:
            return (f"fitted material baked as it is: under this force the motion barely depends on E, so no factor "
                    f"makes {grid} cells move as the fit's {fit_grid} did ({self.ratio - 1:+.0%} off; {self.runs} "
                    f"runs of {self.window_s:.2g} s, {self.seconds:.1f} s)")
        head = (f"fitted material matched to this grid: E x{self.factor:.3g}, so that {grid} cells move as the fit's "
                f"{fit_grid} did under this force ({self.runs} runs of {self.window_s:.2g} s, {self.seconds:.1f} s)")
        if self.matched:
            return head + f"; within {abs(self.ratio - 1):.0%}"
        return head + (f"; it still moves {self.ratio - 1:+.0%} off after {self.runs} runs (--no-match-fit bakes "
                       f"the fitted E as it is)")


def window_frames(seconds: float, force_end: float, fps: float) -> int:
    """Frames (at fps) the match simulates: the force and RING_S s of ringing after it,
    never more than the bake's `seconds`; at least one."""
    return max(1, int(math.ceil(min(seconds, force_end + RING_S) * fps)))


def amplitude(sq: np.ndarray, moving: np.ndarray, weight: np.ndarray, scale: float) -> float:
    """How far the object swings, as bench/convergence.py's peak: the largest over the
    frames of the QUANTILE, by weight, of the moving points' displacements, scene units.
    sq [T, P]: squared displacements, m^2; moving [P] bool; weight [P]: what each point
    counts for (1 for Gaussians; a driver would count for the Gaussians it carries)."""
    w = np.where(moving, np.asarray(weight, np.float64), 0.0)
    if w.sum() <= 0:
        return 0.0
    d = np.sqrt(np.asarray(sq, np.float64)[:, w > 0])
    w = w[w > 0]
    order = np.argsort(d, axis=1)
    cum = np.cumsum(w[order], axis=1) / w.sum()
    at = np.minimum((cum < QUANTILE).sum(axis=1), d.shape[1] - 1)  # the first point at or past it
    return float(np.take_along_axis(d, order, 1)[np.arange(len(d)), at].max()) / scale


def next_log_factor(tried: list[tuple[float, float]]) -> float:
    """The next log factor to try from (log factor, log motion error) pairs so far, the
    error falling as the factor rises: regula falsi once the errors bracket zero, else a
    secant step (FIRST_SLOPE until two runs measure the slope), at most MAX_STEP, within
    +-log(MAX_FACTOR)."""
    x, e = tried[-1]
    above = [p for p in tried if p[1] > 0]  # moves too much: needs a larger factor
    below = [p for p in tried if p[1] < 0]
    if above and below:
        (x0, e0), (x1, e1) = max(above), min(below)  # the tightest bracket
        t = e0 / (e0 - e1)
        return x0 + min(max(t, 0.1), 0.9) * (x1 - x0)
    slope = FIRST_SLOPE
    if len(tried) > 1:
        (xa, ea), (xb, eb) = tried[-2], tried[-1]
        if abs(xb - xa) > 1e-9:
            slope = min(max((eb - ea) / (xb - xa), SLOPES[0]), SLOPES[1])
    step = min(max(-e / slope, -MAX_STEP), MAX_STEP)
    return min(max(x + step, -math.log(MAX_FACTOR)), math.log(MAX_FACTOR))


def match_fit_motion(fit: Discretisation, bake: Discretisation, frames: int, *, tolerance: float = TOLERANCE,
                     max_runs: int = MAX_RUNS, window_s: float = 0.0,
                     progress: Callable[[int, int], None] | None = None) -> MotionMatch:
    """E for the bake's drivers, the fitted E times one factor, that makes them swing as far
    as the fit's drivers do with the fitted E, over `frames` frames of the bake's force from
    rest. Stops within `tolerance` (in log motion) or after `max_runs` runs on the bake's
    discretisation, keeping the best run. progress(done, total) after each run."""
    t0 = time.perf_counter()
    total = max_runs + 1
    target = amplitude(fit.run(fit.E, frames), ~fit.static, fit.weight, fit.scale)
    if progress:
        progress(1, total)
    moving = ~bake.static
    tried: list[tuple[float, float]] = []
    x, flat = 0.0, False
    while target > 0 and len(tried) < max_runs:
        got = amplitude(bake.run(bake.E * math.exp(x), frames), moving, bake.weight, bake.scale)
        tried.append((x, math.log(max(got, 1e-300) / target)))
        if progress:
            progress(len(tried) + 1, total)
        if abs(tried[-1][1]) <= tolerance:
            break
        if len(tried) > 1:
            (xa, ea), (xb, eb) = tried[-2], tried[-1]
            if abs(eb - ea) < FLAT_SLOPE * abs(xb - xa):
                flat = len(tried) == 2  # from the start: E does not set this motion
                break  # later: the search has stalled; the best run so far stands
        x = next_log_factor(tried)
    if not tried:  # nothing moves in the fit's simulation: nothing to match
        return MotionMatch(bake.E, 1.0, 1.0, 0, time.perf_counter() - t0, window_s, True)
    if flat:  # keep the fitted E: a factor that changes nothing visible is no match
        best_x, best_e = tried[0]
    else:  # the best run; of runs as good within the tolerance, the smallest change
        least = min(abs(e) for _, e in tried)
        best_x, best_e = min((p for p in tried if abs(p[1]) <= least + tolerance), key=lambda p: abs(p[0]))
    return MotionMatch(E=bake.E * math.exp(best_x), factor=math.exp(best_x), ratio=math.exp(best_e), runs=len(tried),
                       seconds=time.perf_counter() - t0, window_s=window_s, matched=abs(best_e) <= tolerance,
                       flat=flat)
