"""Stability guard: turns the kernels' per-frame counters into one clear error."""
from __future__ import annotations

import math

import numpy as np

from pd_tool.core.errors import SimulationUnstable
from pd_tool.sim import kernels as K
from pd_tool.sim.cfl import wave_speed


def check_stats(stats: np.ndarray, frame: int, time_s: float, substeps: int) -> None:
    """Raise SimulationUnstable if the frame's counters show NaN, escape or collapse.

    Args:
        stats: [kernels.N_STATS] counters read once at the end of the frame.
        frame: index of the frame that was just simulated (0-based).
        time_s: simulation time at the end of that frame, s.
        substeps: substeps per frame used, for the message.
    """
    where = f"simulation unstable at frame {frame} (t={time_s:.3f} s, {substeps} substeps/frame)"
    nonfinite = int(stats[K.STAT_NONFINITE])
    edge = int(stats[K.STAT_EDGE])
    collapsed = int(stats[K.STAT_COLLAPSED])
    if nonfinite:
        raise SimulationUnstable(
            f"{where}: {nonfinite} particles became NaN/inf; raise the substeps "
            f"(lower cfl_safety), lower the force or the Young's modulus")
    if collapsed:
        raise SimulationUnstable(
            f"{where}: {collapsed} particles inverted or collapsed (det F too small); lower the "
            f"force first (a push that turns a soft material inside out does so at any substep "
            f"count), then raise the substeps (lower cfl_safety)")
    if edge:
        raise SimulationUnstable(
            f"{where}: {edge} particles reached the edge of the simulation grid; lower the "
            f"force, or enlarge the padding around the object (domain) or boundary_pad")


# A force that needs this many times the stress the stiffest material can give (strain far
# beyond 1: the object tears or turns inside out) and that would also carry a free particle
# out of the simulation box cannot end stable. Simulating it anyway costs the most: its
# speed sets the CFL substep count (tens of thousands per frame) before the per-frame
# guard can see the NaN.
HOPELESS_STRAIN = 10.0
# The push the refusal suggests instead: one whose speed stays below this fraction of the
# material's wave speed and whose free flight during the push stays within the free space
# around the object. Both keep a body away from the two ways a push ends unstable here
# (a shock faster than the material can carry, and an impact on the box's wall); on the
# test plant a jelly pushed whole ran at 1.4x its wave speed and collapsed at 1.9x.
SAFE_MACH = 0.8


def safe_acceleration(duration_s: float, wave_speed_m_s: float, gap_m: float) -> float:
    """m/s^2 of a push that stays stable: speed after `duration_s` at most SAFE_MACH x the
    wave speed, and a free flight of at most `gap_m` (the free space around the object)."""
    return min(SAFE_MACH * wave_speed_m_s / duration_s, 2.0 * gap_m / duration_s ** 2)


def _round_down(x: float) -> float:
    """x rounded down to two significant digits (a suggested limit must not round up)."""
    if not (x > 0 and math.isfinite(x)):
        return 0.0
    step = 10.0 ** (math.floor(math.log10(x)) - 1)
    return math.floor(x / step * (1 + 1e-12)) * step


def check_force(accel_m_s2: float, duration_s: float, pushed_extent_m: float, density: float,
                E_max: float, box_m: float, unit_m_s2: float, *, nu: float = 0.3, gap_m: float | None = None,
                magnitude: float = 1.0, unit: str = "scene units/s^2") -> None:
    """Raise SimulationUnstable before simulating when a force cannot end stable.

    The message names a --force length that simulates stably (safe_acceleration).

    Args:
        accel_m_s2: |acceleration| the force applies, m/s^2.
        duration_s: how long it pushes, s (already clipped to the animation).
        pushed_extent_m: size of the pushed region (longest side), m.
        density: kg/m^3.  E_max: stiffest free particle's Young's modulus, Pa.  nu: Poisson's ratio.
        box_m: longest side of the simulation box, m.
        unit_m_s2: m/s^2 of one unit of --force (metres per scene unit, or g), to quote the
            limit in the user's units; unit: that unit's name.
        gap_m: free space between the object and the box's walls, m (None: a fifth of box_m).
        magnitude: the force preset's factor between --force and the acceleration.
    """
    if accel_m_s2 <= 0 or duration_s <= 0:
        return
    travel = 0.5 * accel_m_s2 * duration_s ** 2  # a free particle's displacement, m
    strain = density * accel_m_s2 * max(pushed_extent_m, 1e-9) / E_max  # stress needed / E
    if travel > box_m and strain > HOPELESS_STRAIN:

        ok = safe_acceleration(duration_s, wave_speed(E_max, density, nu), box_m / 5.0 if gap_m is None else gap_m)
        hint = _round_down(ok / (unit_m_s2 * magnitude))
        raise SimulationUnstable(
            f"the force cannot end stable: {accel_m_s2 / unit_m_s2:.3g} {unit} for {duration_s:g} s would "
            f"carry the object {travel:.3g} m (the simulation box is {box_m:.3g} m) and needs {strain:.3g}x the "
            f"stress E = {E_max:.3g} Pa can give; lower --force below about {hint:g} (a push of that length "
            f"simulates stably), shorten --duration, or raise E")


def fold_stat_lanes(stats: np.ndarray) -> np.ndarray:
    """Host side of frame_stats: put the lanes' max speed and total kinetic energy into
    kernels.STAT_VMAX and STAT_KINETIC of `stats` (a numpy copy of the device array)."""
    stats[K.STAT_VMAX] = stats[K.N_STATS::2].max()
    stats[K.STAT_KINETIC] = stats[K.N_STATS + 1::2].sum()
    return stats
