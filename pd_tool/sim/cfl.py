"""CFL choice of the MPM substep: elastic wave speed of the stiffest particle plus speed."""
from __future__ import annotations

import math

import numpy as np


def lame_np(E: np.ndarray | float, nu: float) -> tuple[np.ndarray, np.ndarray]:
    """(mu, lambda) in Pa from Young's modulus E (Pa) and Poisson's ratio nu."""
    E = np.asarray(E, dtype=np.float64)
    return E / (2.0 * (1.0 + nu)), E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def wave_speed(E: np.ndarray, density: np.ndarray, nu: float, quantile: float = 1.0) -> float:
    """Fastest dilatational wave speed sqrt((lambda + 2 mu) / rho) over particles, in m/s;
    with quantile < 1, that quantile of the particles' speeds instead of the fastest.

    Args:
        E: [N] Young's modulus, Pa.
        density: [N] mass / volume, kg/m^3.
        quantile: (0, 1]; 1 is the maximum.
    """
    mu, lam = lame_np(E, nu)
    c2 = (lam + 2.0 * mu) / np.asarray(density, dtype=np.float64)
    return float(np.sqrt(np.max(c2) if quantile >= 1.0 else np.quantile(c2, quantile)))


def cfl_substeps(frame_dt: float, dx: float, c: float, vmax: float, safety: float) -> int:
    """Substeps per frame so that dt <= safety * dx / (c + vmax).

    Args:
        frame_dt: output frame length, s.
        dx: grid spacing, m.
        c: wave speed, m/s (wave_speed()).
        vmax: fastest particle speed, m/s.
        safety: CFL number (0, 1]; smaller is more stable.
    """
    dt_max = safety * dx / max(c + vmax, 1e-12)
    return max(1, int(math.ceil(frame_dt / dt_max - 1e-9)))
