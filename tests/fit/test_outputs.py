"""What a fit's side outputs show: the E picture carries a colour bar in Pa and the E
statistics under the render, and report.json records the settings the fit ran at (resolved
from the quality preset) with the per-region E medians."""
from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

# a rendered ramp pixel is the colormap's colour rounded to 8 bits: within sqrt(3) * 0.5 of
# it, plus the LUT's own step (1001 samples of a ramp with five stops)
RAMP_TOL = 3.0  # 8-bit RGB distance


def _reference_ticks(lo: float, hi: float) -> list[float] | None:
    """Decades inside [lo, hi] when there are three or more, else 1-2-5 values when there
    are two or more; None when neither (the linear fallback, checked by its properties)."""
    def inside(t: float) -> bool:
        return lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9)

    decades = [10.0 ** k for k in range(-30, 31) if inside(10.0 ** k)]
    if len(decades) >= 3:
        return decades
    fine = sorted(m * 10.0 ** k for k in range(-30, 31) for m in (1, 2, 5) if inside(m * 10.0 ** k))
    return fine if len(fine) >= 2 else None


@pytest.mark.parametrize("lo,hi", [(1e3, 1e8), (1e4, 1e6), (2e4, 3e6), (1.1e5, 1.1e6), (5.2e4, 9.9e4),
                                   (3.0e5, 4.5e5), (0.7, 1.3)])
def test_log_ticks_follow_the_range(lo: float, hi: float) -> None:
    from pd_tool.render.plots import log_ticks

    ticks = log_ticks(lo, hi)
    assert ticks == sorted(ticks) and len(set(ticks)) == len(ticks)
    assert all(lo * (1 - 1e-9) <= t <= hi * (1 + 1e-9) for t in ticks), ticks
    assert len(ticks) >= 2, ticks
    want = _reference_ticks(lo, hi)
    if want is not None:
        assert ticks == pytest.approx(want, rel=1e-12)
    else:  # evenly spaced, on a 1-2-5 step
        steps = np.diff(ticks)
        assert np.allclose(steps, steps[0], rtol=1e-6)
        mantissa = steps[0] / 10 ** math.floor(math.log10(steps[0]))
        assert min(abs(mantissa - m) for m in (1, 2, 5)) < 1e-6, steps[0]


def test_log_ticks_on_random_ranges_match_the_reference() -> None:
    from pd_tool.render.plots import log_ticks

    rng = np.random.default_rng(0)
    for _ in range(200):
        a, b = sorted(10 ** rng.uniform(2, 9, 2))
        want = _reference_ticks(a, b)
        got = log_ticks(a, b)
        assert all(a * (1 - 1e-9) <= t <= b * (1 + 1e-9) for t in got), (a, b, got)
        if want is not None:
            assert got == pytest.approx(want, rel=1e-12), (a, b)


def test_log_ticks_refuse_a_range_a_log_scale_cannot_show() -> None:
    from pd_tool.render.plots import log_ticks

    for lo, hi in [(0.0, 1e5), (-1.0, 1e5), (1e6, 1e5), (1e5, math.inf)]:
        with pytest.raises(ValueError, match="0 < lo <= hi"):
            log_ticks(lo, hi)
    assert log_ticks(2e5, 2e5) == [2e5]


def test_sci_label_reads_back_as_its_value() -> None:
    from pd_tool.render.plots import sci_label

    assert [sci_label(v) for v in (1e4, 2.5e5, 1e6, 1.15e5)] == ["1e4", "2.5e5", "1e6", "1.15e5"]
    for v in 10 ** np.random.default_rng(1).uniform(-3, 9, 100):
        assert float(sci_label(v)) == pytest.approx(v, rel=5e-3)


def _ramp_runs(strip: np.ndarray) -> list[np.ndarray]:
    """For each row of the strip, the colormap positions u (0-1) along its longest run of
    pixels that are the colormap's colours, when that run spans half the strip or more."""
    from pd_tool.fit.outputs import colormap

    lut_u = np.linspace(0.0, 1.0, 1001)
    lut = colormap(lut_u) * 255
    runs = []
    for row in strip.astype(np.float64):
        d = np.linalg.norm(row[:, None, :] - lut[None], axis=2)
        ok = d.min(axis=1) < RAMP_TOL
        best, start = (0, 0), None
        for x, good in enumerate(np.append(ok, False)):
            if good and start is None:
                start = x
            elif not good and start is not None:
                best = max(best, (x - start, start))
                start = None
        n, s = best
        if n >= len(row) // 2:
            runs.append(lut_u[d[s:s + n].argmin(axis=1)])
    return runs


@pytest.fixture(scope="module")
def plant_fit(tmp_path_factory):
    """A 400-Gaussian plant prepared as the demo's fit prepares it, with an E per simulated
    Gaussian near its region's true E, in a FitResult ready for write_fit_outputs."""
    from pd_tool.core.cameras import auto_camera
    from pd_tool.fit.run import FitResult
    from pd_tool.fit.settings import FitSettings
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, make_plant

    scene = make_plant(400, seed=3)
    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=24))
    rng = np.random.default_rng(3)
    truth = np.array([REGION_TRUTH_E[r] for r in REGIONS])
    gaussian_E = truth[scene.labels[prep.foreground]] * np.exp(rng.normal(0.0, 0.3, prep.count))
    result = FitResult(material_path=Path("fit.pdmat"), driver_E=np.ones(10), driver_v0=np.zeros((10, 3)),
                       gaussian_E=gaussian_E, losses={"velocity": [1.0, 0.5], "material": [0.4, 0.3]}, seconds={},
                       prep=prep, drivers=None, settings=FitSettings(quality="draft").resolved(), cfl_safety=0.6,
                       substeps=(4, 9))
    video = SimpleNamespace(camera=auto_camera(scene.positions.numpy(), 40, 30), folder=None, camera_path=None)
    return scene, result, video


def test_e_picture_is_the_render_over_a_colour_bar(plant_fit, tmp_path: Path) -> None:
    from PIL import Image

    from pd_tool.fit.outputs import e_field_scene, write_fit_outputs
    from pd_tool.fit.settings import FitSettings
    from pd_tool.render.plots import STRIP_MIN_WIDTH
    from pd_tool.render.views import render_image

    scene, result, video = plant_fit
    paths = write_fit_outputs(tmp_path, "fit", scene, result, [video], FitSettings(quality="draft"), preview=False)
    png = np.asarray(Image.open(paths["e_field_png"]).convert("RGB"))
    e_scene, _ = e_field_scene(scene, result.prep.foreground, result.gaussian_E)
    render = render_image(e_scene, video.camera, background=(1.0, 1.0, 1.0))
    h, w = render.shape[:2]
    assert png.shape[0] > h and png.shape[1] == max(w, STRIP_MIN_WIDTH), (png.shape, render.shape)
    assert np.array_equal(png[:h, :w], render)  # the bar does not cover the render
    runs = _ramp_runs(png[h:])
    assert runs, "no colour ramp in the strip under the render"
    for u in runs:  # low E on the left, high E on the right, the whole ramp
        assert u[0] < 0.02 and u[-1] > 0.98, (u[0], u[-1])
        assert np.all(np.diff(u) >= -0.002), u
    assert len(runs) >= 8  # a bar, not a stray line
    text = png[h:][:, :, :].min(axis=2) < 80  # dark pixels: ticks and text
    assert text.sum() > 200


def test_e_picture_notes_give_the_percentiles_and_region_medians(plant_fit) -> None:
    from pd_tool.fit.outputs import e_picture_notes, e_statistics
    from pd_tool.render.plots import colorbar_strip, sci_label
    from pd_tool.io.synthetic import REGIONS

    scene, result, _ = plant_fit
    prep, E = result.prep, result.gaussian_E
    stats = e_statistics(scene, prep.foreground, prep.static, E)
    notes = " | ".join(e_picture_notes(stats, prep.count))
    for q in (5, 50, 95):
        assert f"{q}% {sci_label(np.percentile(E, q))}" in notes, notes
    labels = scene.labels[prep.foreground]
    for i, name in enumerate(REGIONS):
        assert f"{name} {sci_label(np.median(E[labels == i]))}" in notes, notes
    assert "pot " in notes and "(fixed)" in notes.split("pot ")[1].split(",")[0]  # below POT_TOP: held
    # every note is drawn: the strip grows by a line per note
    bare = colorbar_strip(300, 1e4, 1e6, lambda u: np.zeros((len(u), 3)), label="E")
    noted = colorbar_strip(300, 1e4, 1e6, lambda u: np.zeros((len(u), 3)), label="E", notes=["a", "b"])
    assert len(noted) > len(bare) and (noted[len(bare) - 10:] < 128).any()


def test_e_statistics_without_region_labels_or_names(plant_fit) -> None:
    import dataclasses

    from pd_tool.fit.outputs import e_picture_notes, e_statistics

    scene, result, _ = plant_fit
    unnamed = dataclasses.replace(scene, label_names=())
    regions = e_statistics(unnamed, result.prep.foreground, result.prep.static, result.gaussian_E)["regions"]
    assert list(regions) == [f"region {i}" for i in np.unique(scene.labels)]
    named = e_statistics(scene, result.prep.foreground, result.prep.static, result.gaussian_E)["regions"]
    assert [r["E_median_pa"] for r in regions.values()] == [r["E_median_pa"] for r in named.values()]
    bare = dataclasses.replace(scene, labels=None, label_names=())
    stats = e_statistics(bare, result.prep.foreground, result.prep.static, result.gaussian_E)
    assert stats["regions"] == {}
    assert stats["percentiles_pa"]["50"] == pytest.approx(float(np.median(result.gaussian_E)))
    assert not any("region" in n for n in e_picture_notes(stats, result.prep.count))


def test_report_records_what_the_fit_ran_at(fit_dir: Path, tmp_path: Path) -> None:
    """A real (one iteration per stage) fit with the settings as the CLI gives them, most
    left to the quality preset: the report holds the values it resolved to and ran at."""
    from pd_tool.fit.outputs import write_fit_outputs
    from pd_tool.fit.settings import FitSettings
    from pd_tool.materials.file import MaterialFile
    from pd_tool.materials.presets import fit_simulation, load_preset
    from pd_tool.io.synthetic import POT_TOP, REGIONS

    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=1, working_long_side=24)
    assert settings.driver_ratio is None  # left to the preset: the report must say what it became
    scene, refs, result = _tiny_fit(fit_dir, tmp_path / "fit.pdmat", settings)
    paths = write_fit_outputs(tmp_path, "fit", scene, result, refs, settings, preview=False)
    report = json.loads(paths["report"].read_text())
    grid, cfl, ratio = fit_simulation(load_preset("quality", "draft"))
    sim = report["simulation"]
    assert sim["quality"] == "draft"
    assert (sim["grid_res"], sim["cfl_safety"], sim["driver_ratio"]) == (grid, pytest.approx(cfl), pytest.approx(ratio))
    assert sim["grid_dims"] == list(result.prep.grid_dims) and max(sim["grid_dims"]) == grid
    assert sim["iterations"] == {"rounds": 1, "velocity": 1, "material": 1, "polish": 0, "calibrate": 0}
    lo, hi = sim["substeps_per_frame"]
    assert 1 <= lo <= hi
    assert report["settings"]["driver_ratio"] == pytest.approx(ratio)  # resolved, not None
    assert report["settings"]["velocity_iters"] == 1
    prep = report["prepare"]
    assert prep["static_below"] == POT_TOP and prep["up_axis"] == "+z" and prep["grid_res"] == grid
    assert prep["meters_per_unit"] is None and sim["meters_per_unit"] == pytest.approx(result.prep.transform.scale)
    # the material file, which a bake simulates from, agrees with the report
    mf = MaterialFile.load(tmp_path / "fit.pdmat")
    assert mf.meta["simulation"]["cfl_safety"] == pytest.approx(sim["cfl_safety"])
    assert mf.meta["simulation"]["grid_res"] == sim["grid_res"]
    assert mf.meta["prepare"] == prep
    labels = scene.labels[result.prep.foreground]
    names = list(REGIONS)  # the PLY keeps the labels and, in its header, their names
    assert list(report["E_region_median_pa"]) == names
    for i, name in enumerate(names):
        assert report["E_region_median_pa"][name] == pytest.approx(np.median(result.gaussian_E[labels == i]))
        assert report["region_gaussians"][name]["simulated"] == int((labels == i).sum())
    for q in ("5", "50", "95"):
        assert report["E_percentiles_pa"][q] == pytest.approx(np.percentile(result.gaussian_E, int(q)))


def test_a_fit_with_a_floor_of_drivers_a_cell_is_baked_on_the_same_drivers(fit_dir: Path, tmp_path: Path) -> None:
    """A quality's fit_min_drivers_per_cell clusters the fit's drivers up to that many in
    each moving cell; the material file records it, and a bake that simulates as the fit
    did (no --quality) builds the same drivers, where a floorless rebuild would have fewer."""
    from click.testing import CliRunner

    from cli import main
    from pd_tool.fit.settings import FitSettings
    from pd_tool.materials.file import MaterialFile

    quality = tmp_path / "floored.toml"
    quality.write_text((Path(__file__).resolve().parents[2] / "presets" / "quality.toml").read_text()
                       .split("[default]")[0].split("[draft]")[1] + "fit_min_drivers_per_cell = 8\n")
    settings = FitSettings(quality=str(quality), velocity_iters=1, material_iters=1, working_long_side=24).resolved()
    assert settings.min_drivers_per_cell == 8.0
    result = _tiny_fit(fit_dir, tmp_path / "fit.pdmat", settings)[2]
    p = result.prep
    mf = MaterialFile.load(tmp_path / "fit.pdmat")
    assert mf.fit_simulation()["min_per_cell"] == 8.0
    q = len(mf.driver_E)
    assert p.splits(settings.driver_ratio, 8.0)  # 300 Gaussians at 0.1 are far fewer than 8 a cell
    assert q >= 0.9 * 8 * p.moving_cells()
    assert len(p.build_drivers(ratio=settings.driver_ratio, seed=settings.seed).positions) < q / 4
    res = CliRunner().invoke(main, ["bake", "--material", str(tmp_path / "fit.pdmat"), "--force", "0,0,1",
                                    "--frames", "2", "--device", "cpu", str(tmp_path / "out.usd")],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "at least 8 a moving cell" in res.output and f"driven by {q:,} particles" in res.output, res.output


def _tiny_fit(fit_dir: Path, out: Path, settings):
    """(scene, reference videos, FitResult) of the fit fixture's plant fitted to `out` at
    24 px on one torch thread (the suite's 2 cores)."""
    import torch

    from pd_tool.fit.run import run_fit
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.video.folder import load_reference_video

    scene = load_splats(fit_dir / "plant.ply")
    refs = [load_reference_video(fit_dir / "video", working_size=24)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return scene, refs, run_fit(scene, fit_dir / "plant.ply", refs, out,
                                    prepare_options=PrepareOptions(static_below=POT_TOP, up_axis="+z"),
                                    settings=settings)
    finally:
        torch.set_num_threads(threads)
