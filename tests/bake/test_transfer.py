"""Matching a fitted material's motion on another discretisation: the search on analytic
responses, the amplitude against a direct computation, and a bake of the thin plant."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pd_tool.bake.transfer import (MAX_FACTOR, MAX_RUNS, MAX_STEP, TOLERANCE, Discretisation, amplitude,
                                   match_fit_motion, next_log_factor, window_frames)


def _analytic(stiffer: float, exponent: float, q: int = 50, frames: int = 6) -> tuple[Discretisation, Discretisation]:
    """A fit whose drivers swing 1 mm at its E, and a bake whose drivers are `stiffer` times
    as stiff at the same E, both swinging as E**exponent (a tap: -0.5, a slow push: -1)."""
    static = np.zeros(q, bool)
    static[:5] = True
    shape = np.sin(np.linspace(0.0, math.pi, frames))[:, None] ** 2  # [T, 1]: one swing

    def make(k: float) -> Discretisation:
        E0 = np.full(q, 2e5)

        def run(E: np.ndarray, n: int) -> np.ndarray:
            assert n == frames
            amp = 1e-3 * (k * E / E0) ** exponent  # m, per driver
            sq = shape * amp[None] ** 2
            sq[:, static] = 0.0
            return sq

        return Discretisation(static=static, weight=np.ones(q), E=E0, run=run, scale=0.5)

    return make(1.0), make(stiffer)


@pytest.mark.parametrize("stiffer,exponent", [(0.05, -0.5), (0.05, -1.0), (8.0, -0.5), (30.0, -0.3), (1.0, -0.5)])
def test_match_finds_the_factor(stiffer: float, exponent: float) -> None:
    fit, bake = _analytic(stiffer, exponent)
    m = match_fit_motion(fit, bake, 6)
    assert m.matched and m.runs <= 5, (m.runs, m.factor)
    # the bake moves as the fit when its E is the fit's over `stiffer`
    assert abs(math.log(m.factor * stiffer)) <= TOLERANCE / abs(exponent) + 1e-9, m.factor
    np.testing.assert_allclose(m.E, bake.E * m.factor)
    assert abs(m.ratio - 1.0) <= math.expm1(TOLERANCE)
    if stiffer == 1.0:
        assert m.runs == 1 and m.factor == 1.0  # already the same: one run, no change


def test_match_stops_at_the_limits() -> None:
    # a bake 1e6 times too stiff cannot be matched within MAX_FACTOR: the best run is kept,
    # at the limit, and the result says it is not matched
    fit, bake = _analytic(1e6, -1.0)
    m = match_fit_motion(fit, bake, 6, max_runs=5)
    assert not m.matched and m.runs == 5
    assert m.factor == pytest.approx(1.0 / MAX_FACTOR)
    assert "still moves" in m.line(32, 128) and "--no-match-fit" in m.line(32, 128)


def test_next_log_factor_brackets_and_limits() -> None:
    # one run, too much motion: a tap's slope, at most MAX_STEP
    assert next_log_factor([(0.0, 0.2)]) == pytest.approx(0.4)
    assert next_log_factor([(0.0, 5.0)]) == pytest.approx(MAX_STEP)
    # a bracket: regula falsi between its tightest ends
    x = next_log_factor([(0.0, 0.4), (2.0, -0.4), (1.0, 0.1)])
    assert 1.0 < x < 2.0 and x == pytest.approx(1.0 + 0.1 / 0.5 * 1.0)
    # a measured slope steers the step; never past the largest factor
    assert next_log_factor([(0.0, 0.3), (0.5, 0.2)]) == pytest.approx(0.5 + 0.2 / 0.2)
    assert next_log_factor([(4.0, 0.5), (4.5, 0.49)]) == pytest.approx(math.log(MAX_FACTOR))


def test_amplitude_against_a_direct_computation() -> None:
    # the largest over frames of the 99th percentile over Gaussians of the displacement:
    # each point stands for its weight in Gaussians; expand them and take it directly
    rng = np.random.default_rng(1)
    disp = rng.normal(size=(7, 400, 3))
    moving = rng.random(400) > 0.3
    weight = rng.integers(1, 5, 400).astype(float)
    sq = (disp ** 2).sum(-1)
    direct = 0.0
    for frame in np.sqrt(sq):
        expanded = np.sort(np.repeat(frame[moving], weight[moving].astype(int)))
        direct = max(direct, expanded[int(np.ceil(0.99 * len(expanded))) - 1])
    assert amplitude(sq, moving, weight, 2.0) == pytest.approx(direct / 2.0)
    # not the percentile of each point's own largest displacement
    peaks = np.sort(np.repeat(np.sqrt(sq.max(axis=0))[moving], weight[moving].astype(int)))
    assert amplitude(sq, moving, weight, 2.0) != pytest.approx(peaks[int(np.ceil(0.99 * len(peaks))) - 1] / 2.0)
    assert amplitude(sq, np.zeros(400, bool), weight, 2.0) == 0.0
    # one point: its largest displacement
    assert amplitude(sq[:, :1], np.ones(1, bool), np.ones(1), 1.0) == pytest.approx(np.sqrt(sq[:, 0].max()))


def test_window_frames() -> None:
    assert window_frames(2.0, 0.1, 30) == 33  # the force and a second of ringing
    assert window_frames(0.3, 0.1, 30) == 9  # never past the bake
    assert window_frames(0.0, 0.0, 30) == 1


def test_thin_plant_baked_at_draft_moves_as_fitted(tmp_path) -> None:
    """A material fitted on 16 cells (a file as a fit writes it, with a smooth E field),
    baked at draft: on draft's grid, raised for the 3 mm leaves, with draft's drivers, the
    fitted E alone moves its farthest Gaussian 1.6x as far as the fit's simulation did;
    matched, within draft's bound."""
    from pd_tool.bake import BakeSettings, ForceSpec, bake
    from pd_tool.io.synthetic import make_plant
    from pd_tool.materials.file import MaterialFile
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.prepare.work import WorkEstimate, work_policy

    scene = make_plant(3000, seed=0, thin=True)
    pos = scene.positions.double().numpy()
    h = (pos[:, 2] - pos[:, 2].min()) / np.ptp(pos[:, 2])
    E = 10 ** (6.3 - 1.5 * h) * np.where(pos[:, 0] > np.median(pos[:, 0]), 3.0, 1.0)
    mf = MaterialFile(driver_E=E, driver_v0=np.zeros((len(E), 3), np.float32), driver_rest=pos,
                      meta={"simulation": {"grid_res": 16, "driver_ratio": 0.1, "driver_seed": 0, "cfl_safety": 0.5},
                            "nu": 0.3, "density": 700.0})
    opts = PrepareOptions(up_axis="+z", static_below=float(pos[:, 2].min() + 0.1 * np.ptp(pos[:, 2])),
                          density_kg_m3=700.0)
    force = ForceSpec(accel=(4.0, 0.0, 0.0), at="top", radius_fraction=0.3, duration=0.1, units="size")
    peaks = {}
    for name, quality, match in (("fitted", None, True), ("plain", "draft", False), ("matched", "draft", True)):
        calls: list[tuple[str, int, int]] = []
        estimates: list[WorkEstimate] = []
        with work_policy(None, estimates.append):
            r = bake(scene, tmp_path / f"{name}.usd", force=force, material_file=mf, prepare_options=opts,
                     settings=BakeSettings(seconds=0.6, fps=30, quality=quality, fmt="instancer", match_fit=match,
                                           stop_at_rest=False),
                     progress=lambda d, t: calls.append(("frame", d, t)),
                     match_progress=lambda d, t: calls.append(("match", d, t)))
        peaks[name] = r.peak_displacement / r.object_size
        runs = [c for c in calls if c[0] == "match"]
        if name == "matched":
            line = next(x for x in r.report if x.startswith("fitted material matched to this grid: E x"))
            assert float(line.split("E x")[1].split(",")[0]) > 1.5, line  # the finer grid is softer here
            # one call for the fit's run, then one per run on draft's grid, all before the frames
            n_runs = int(line.split("(")[1].split(" runs")[0])
            assert [c[1] for c in runs] == list(range(1, n_runs + 2)) and {c[2] for c in runs} == {MAX_RUNS + 1}
            assert calls[: len(runs)] == runs
            # the run's estimate adds the match's runs, as estimated before it, to the frames
            # at the matched E (estimated after it)
            before, after = estimates[-2:]
            match_frames = (MAX_RUNS + 1) * window_frames(0.6, 0.1, 30)
            share = match_frames / (r.frames + match_frames - 1)  # of the simulated frames (not frame 0)
            assert r.work_estimate.seconds == pytest.approx(after.seconds + share * before.terms["simulate"])
            assert r.work_estimate.seconds > after.seconds
        else:
            assert runs == []  # nothing to match
        assert calls[-1][0] == "frame" and calls[-1][1] == calls[-1][2]
    assert peaks["fitted"] > 0.02, peaks  # the poke moves it
    # draft's bound, as for a preset against a converged reference: within 25%. The match
    # is on the 99th percentile of the Gaussians' swing, this check on the farthest
    # Gaussian; one factor for the whole object leaves the motion's shape as the finer grid
    # makes it
    assert abs(peaks["plain"] / peaks["fitted"] - 1.0) > 0.25, peaks  # the gap the match closes
    assert peaks["matched"] == pytest.approx(peaks["fitted"], rel=0.25), peaks


def test_motion_that_does_not_answer_E_keeps_the_fitted_E() -> None:
    # 20% more motion on the bake's grid whatever E is (a part that flies off): two runs,
    # then the fitted E as it is, and the report says why
    fit, bake = _analytic(1.0, -0.5)

    def run(E: np.ndarray, n: int) -> np.ndarray:
        return fit.run(fit.E, n) * 1.2 ** 2 * (E[0] / fit.E[0]) ** -0.02

    flat = Discretisation(static=bake.static, weight=bake.weight, E=bake.E, run=run, scale=bake.scale)
    m = match_fit_motion(fit, flat, 6)
    assert m.flat and m.runs == 2 and m.factor == 1.0 and not m.matched
    np.testing.assert_array_equal(m.E, flat.E)
    assert m.ratio == pytest.approx(1.2) and "baked as it is" in m.line(32, 64)


def test_a_search_that_stalls_keeps_its_best_run_with_the_least_change() -> None:
    # twice the fit's motion at the fitted E, falling as a tap's until a floor at 1.5x: the
    # search stalls on the floor and keeps the first run that reached it (E x4), not x30
    fit, bake = _analytic(1.0, -0.5)

    def run(E: np.ndarray, n: int) -> np.ndarray:
        f = E[0] / fit.E[0]
        return fit.run(fit.E, n) * max(2.0 * f ** -0.5, 1.5) ** 2

    floor = Discretisation(static=bake.static, weight=bake.weight, E=bake.E, run=run, scale=bake.scale)
    m = match_fit_motion(fit, floor, 6)
    assert not m.flat and not m.matched and m.runs == 3
    assert m.factor == pytest.approx(4.0) and m.ratio == pytest.approx(1.5)


def test_match_reads_the_gaussians_the_bake_writes(tmp_path) -> None:
    """The match's measure of a discretisation is the motion of the very Gaussians the bake
    writes: a run of the bake's own discretisation gives, for the sampled Gaussians, the
    squared displacements of the bake's frames 1..T; the sample moves in both
    preparations and is capped at MATCH_GAUSSIANS."""
    from pd_tool.bake import BakeSettings, ForceSpec
    from pd_tool.bake import baker as baker_module
    from pd_tool.bake.baker import Baker
    from pd_tool.io.synthetic import make_plant
    from pd_tool.materials.file import MaterialFile
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene

    scene = make_plant(2000, seed=1, thin=True)
    pos = scene.positions.double().numpy()
    mf = MaterialFile(driver_E=np.full(len(pos), 3e5), driver_v0=np.zeros((len(pos), 3), np.float32),
                      driver_rest=pos, meta={"simulation": {"grid_res": 16, "driver_ratio": 0.1, "driver_seed": 0,
                                                            "cfl_safety": 0.5}, "nu": 0.3, "density": 700.0})
    opts = PrepareOptions(up_axis="+z", static_below=float(pos[:, 2].min() + 0.1 * np.ptp(pos[:, 2])),
                          density_kg_m3=700.0)
    force = ForceSpec(accel=(4.0, 0.0, 0.0), at="top", radius_fraction=0.3, duration=0.1, units="size")
    frames: list[np.ndarray] = []

    class Recording(Baker):
        def _frame_arrays(self, d_now):
            p, q, disp = super()._frame_arrays(d_now)
            frames.append(p.copy())
            return p, q, disp

    n = 5
    with Recording(scene, tmp_path / "b.usd", force=force, material_file=mf, prepare_options=opts,
                   settings=BakeSettings(seconds=n / 30, fps=30, fmt="instancer", stop_at_rest=False)) as b:
        while not b.done:
            b.step()
        b.finish()
        coarse = prepare_scene(scene, b.opts.updated(grid_res=12))
        sample = b._match_sample(coarse)
        moving = [set(np.asarray(p.foreground)[~np.asarray(p.static[:p.count], bool)]) for p in (b.prep, coarse)]
        assert 0 < len(sample) and set(sample) <= moving[0] & moving[1]
        E = mf.E_at(b.prep.transform.to_scene(b.drivers.positions.double().cpu().numpy()))
        disc = b._discretisation_of(b.prep, b.drivers, E, b.cfl_safety, sample)
        sq = disc.run(E, n)
        moved = np.stack(frames[1:n + 1])[:, sample] - frames[0][sample]
        written = (moved ** 2).sum(-1) * disc.scale ** 2
        assert written.max() > 1e-6  # the poke moves them
        # the displacement the baker records per frame (on the scene's device) is the frames'
        every = np.sqrt(((np.stack(frames) - frames[0]) ** 2).sum(-1)).max(1)
        np.testing.assert_allclose(b.disp, every, rtol=1e-5, atol=1e-7 * every.max())
        np.testing.assert_allclose(sq, written, rtol=1e-3, atol=1e-4 * written.max())
        baker_module.MATCH_GAUSSIANS, cap = 50, baker_module.MATCH_GAUSSIANS
        try:
            assert len(b._match_sample(coarse)) == 50
        finally:
            baker_module.MATCH_GAUSSIANS = cap
