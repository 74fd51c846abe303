"""bench/convergence.py's measures and the strip's theory, on signals whose answer is known,
and one tiny strip simulated through it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests._bench import load_bench

conv = load_bench("convergence")


@pytest.mark.parametrize("f,decay", [(1.58, 0.0), (2.3, 1.5), (0.9, 0.5)])
def test_first_frequency_of_a_damped_sine(f: float, decay: float) -> None:
    t = np.arange(0, 2.5, 1 / conv.FPS)
    s = np.exp(-decay * t) * np.sin(2 * np.pi * f * (t - 0.05))
    assert conv.first_frequency(s, conv.FPS, 0.1) == pytest.approx(f, rel=0.01)


@pytest.mark.parametrize("f,decay", [(1.58, 0.0), (2.3, 0.4), (0.9, 1.5)])
def test_decay_per_period_of_a_damped_sine(f: float, decay: float) -> None:
    # exp(-decay t) loses exp(decay / f) a period; sampled peaks read it within 2%
    t = np.arange(0, 2.5, 1 / conv.FPS)
    s = np.exp(-decay * t) * np.sin(2 * np.pi * f * (t - 0.05))
    assert conv.decay_per_period(s, conv.FPS, 0.1) == pytest.approx(math.exp(decay / f), rel=0.02)


def test_first_frequency_is_nan_without_a_full_swing() -> None:
    t = np.arange(0, 1.0, 1 / conv.FPS)
    assert math.isnan(conv.first_frequency(np.sin(2 * np.pi * 0.6 * t), conv.FPS, 0.1))
    assert math.isnan(conv.first_frequency(np.full(len(t), 0.3), conv.FPS, 0.1))
    assert math.isnan(conv.decay_per_period(np.sin(2 * np.pi * 0.6 * t), conv.FPS, 0.1))


def test_peak_is_the_99th_percentile_at_the_worst_frame() -> None:
    x = np.zeros((3, 200, 3))
    x[1, :, 0] = np.linspace(0, 1, 200)  # frame 1: displacements 0..1
    x[2, :, 0] = 0.5
    moving = np.ones(200, bool)
    assert conv.peak_of(x, moving, 2.0) == pytest.approx(np.percentile(np.linspace(0, 1, 200), 99) / 2.0)


def test_strip_frequency_is_kirchhoff_plate_theory() -> None:
    from pd_tool.io.synthetic import clamped_strip_frequency

    E, nu, rho, L, t = 2.5e7, 0.3, 700.0, 0.9, 0.04
    D = E * t ** 3 / (12 * (1 - nu ** 2))
    expected = 1.8751 ** 2 / (2 * math.pi * L ** 2) * math.sqrt(D / (rho * t))
    assert clamped_strip_frequency(E, nu, rho, L, t) == pytest.approx(expected, rel=1e-12)
    # doubling the thickness doubles the frequency; the length enters squared
    assert clamped_strip_frequency(E, nu, rho, L, 2 * t) == pytest.approx(2 * expected, rel=1e-12)
    assert clamped_strip_frequency(E, nu, rho, 2 * L, t) == pytest.approx(expected / 4, rel=1e-12)


def test_a_tiny_strip_through_the_benchmark_compares_with_itself() -> None:
    case = conv.Case("strip", "+z", 2.5e6, 700.0, 6.0, (1.0, 0.0, 0.0), duration=0.1, seconds=0.25)
    scene = conv.load_scene("strip", 800)
    a = conv.simulate(scene, case, 12, 0.5, 0.5, "cpu")
    b = conv.simulate(scene, case, 16, 0.5, 0.5, "cpu")
    runs = conv.compare({"reference": a, "other": b}, case)
    ref, other = runs
    assert ref.peak_ratio == pytest.approx(1.0) and ref.rms == 0.0
    assert ref.peak > 0 and other.peak > 0 and other.rms > 0
    assert a[0].shape == (int(round(0.25 * conv.FPS)) + 1, 800, 3)


def test_a_split_reference_simulates_sub_particles_of_the_same_mass() -> None:
    from dataclasses import replace

    case = replace(conv.CASES["plant"], seconds=0.1)
    scene = conv.load_scene("plant", 400)
    x_one, moving, one = conv.simulate(scene, case, 32, 0.5, 1.0, "cpu")
    x_split, _, split = conv.simulate(scene, case, 32, 0.5, 1.0, "cpu", split=2)
    assert split.extra["split"] == 2 and one.extra["split"] == 0
    assert split.drivers > one.drivers and split.per_cell > one.per_cell
    assert split.extra["mass_kg"] == pytest.approx(one.extra["mass_kg"])
    assert x_split.shape == x_one.shape and np.linalg.norm(x_split[-1] - x_split[0], axis=1)[moving].max() > 0


def test_even_strip_weights_share_the_strip_volume_evenly(monkeypatch) -> None:
    from pd_tool.prepare import preparation
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene

    monkeypatch.setattr(preparation, "surface_volumes", preparation.surface_volumes)  # restored after
    monkeypatch.setitem(conv.STRIP, "thickness", 0.012)
    scene = conv.load_scene("strip", 4000)
    options = PrepareOptions(grid_res=24, up_axis="+z", static_below=1e-6, fill="off")
    shell = prepare_scene(scene, options)
    conv.even_strip_weights()
    even = prepare_scene(scene, options)
    strip = np.asarray(scene.labels) == 1
    vol = even.volumes[: even.count][strip[even.foreground]]
    s = conv.STRIP
    assert np.allclose(vol, vol[0]) and vol.sum() == pytest.approx(s["length"] * s["width"] * s["thickness"], rel=1e-9)
    # the base keeps the shell rule's weights
    block = ~strip[even.foreground]
    np.testing.assert_allclose(even.volumes[: even.count][block], shell.volumes[: shell.count][block])
    assert not np.allclose(shell.volumes[: shell.count][~block], vol[0])


def test_strip_beam_peak_is_a_tap_on_the_first_mode() -> None:
    """A short tap on the whole strip: the first swing is the first mode's impulse
    response, tip amplitude a tau gamma1 phi1(L) / omega1 (gamma1 = 0.7830 and phi1(L) = 2
    for modes with int phi^2 = L), with the higher modes adding at most about 9%; it
    scales with the push, and a push on the top alone moves the strip less."""
    E, rho, L, w, t = 1e8, 700.0, 0.9, 0.25, 0.012
    tau, a = 0.005, 6.0
    peak, end = conv.strip_beam_peak(E, rho, L, w, t, a, tau, 0.0, 10.0)
    f1 = 1.8751 ** 2 / (2 * np.pi * L ** 2) * np.sqrt(E * t ** 2 / (12 * rho))
    assert end == pytest.approx(tau + 0.5 / f1)
    tap = a * tau * 0.7830 * 2.0 / (2 * np.pi * f1) / L
    assert peak == pytest.approx(tap, rel=0.1)
    assert conv.strip_beam_peak(E, rho, L, w, t, 2 * a, tau, 0.0, 10.0)[0] == pytest.approx(2 * peak, rel=1e-9)
    assert conv.strip_beam_peak(E, rho, L, w, t, a, tau, 0.0, 0.3)[0] < 0.9 * peak
