"""Stability guard: turns the kernels' per-frame counters into one clear error."""
from __future__ import annotations

import numpy as np

from pd_tool.errors import SimulationUnstable
from pd_tool.sim import kernels as K


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
            f"{where}: {collapsed} particles inverted or collapsed (det F too small); raise "
            f"the substeps (lower cfl_safety) or lower the force")
    if edge:
        raise SimulationUnstable(
            f"{where}: {edge} particles reached the edge of the simulation grid; lower the "
            f"force, or enlarge the padding around the object (domain) or boundary_pad")
