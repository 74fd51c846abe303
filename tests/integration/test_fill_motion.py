"""The fill benchmark at a small scale: a clamped rod scanned as a closed shell, simulated
hollow and filled under the same poke. Filled must be heavier, ring lower and swing further,
as beam theory says for a solid rod against a thin tube (bench/fill_motion.py)."""
from __future__ import annotations

import math

from _bench import load_bench


def test_filled_rod_is_heavier_and_rings_lower():
    fm = load_bench("fill_motion")
    # R = 3 cells, L = 24 cells, 0.45 s: about 2 filled periods; ~20 s on one CPU core.
    out = fm.run(radius_cells=3, slender=8.0, seconds=0.45, cfl=0.7, device="cpu",
                 log=lambda s: None)
    assert out["fill"]["decision"], out["fill"]["reason"]  # a closed tube: auto fills
    hollow, filled = out["runs"]["hollow"], out["runs"]["filled"]
    ratio = out["ratios_filled_over_hollow"]
    for r in (hollow, filled):
        assert math.isfinite(r["frequency_hz"]), "no whole period of free vibration"
    # heavier: the interior outweighs a one-cell shell of a 3-cell rod (theory: 1.7x)
    assert ratio["free_mass"] > 1.5
    # lower frequency: I/A of a solid rod is half a thin tube's
    assert filled["frequency_hz"] < 0.97 * hollow["frequency_hz"]
    # and a larger swing under the same acceleration
    assert filled["peak_displacement_m"] > 1.05 * hollow["peak_displacement_m"]
    # the filled rod is a resolved solid: within 10% of beam theory for its own particles
    assert abs(filled["frequency_hz"] / filled["theory"]["frequency_hz"] - 1) < 0.10
    # the one-particle-thick shell is softer than its particles' I says, never stiffer
    assert 0.75 < hollow["frequency_hz"] / hollow["theory"]["frequency_hz"] < 1.02
