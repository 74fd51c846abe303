"""`pdtool bake` end to end on CPU: synthetic plant, a real capture, guard and input errors."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli import main
from pd_tool.io import save_splats
from pd_tool.io.synthetic import POT_TOP, make_plant
from pd_tool.materials.presets import load_preset


@pytest.fixture(scope="module")
def plant_ply(tmp_path_factory) -> Path:
    return save_splats(make_plant(3000, seed=0), tmp_path_factory.mktemp("plant") / "plant.ply")


def _bake(args: list[str], cwd: Path):
    old = os.getcwd()
    os.chdir(cwd)
    try:
        return CliRunner().invoke(main, ["bake", *args], catch_exceptions=False)
    finally:
        os.chdir(old)


def test_bake_plant_flower_preset_validates(plant_ply: Path, tmp_path: Path) -> None:
    from pxr import Usd

    from usd_export import validate_usd

    out = tmp_path / "out.usd"
    res = _bake(["--scene", str(plant_ply), "--preset", "flower", "--force", "0,0,1", "--seconds", "1",
                 "--quality", "draft", "--static-below", str(POT_TOP), "--device", "cpu", str(out)], tmp_path)
    assert res.exit_code == 0, res.output
    assert "31 frames" in res.output and "substeps/frame" in res.output
    validate_usd(out)  # raises on any validator error
    stage = Usd.Stage.Open(str(out))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 30
    assert stage.GetTimeCodesPerSecond() == 30
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporary files left behind"


def test_bake_donut_poke_decays(shared_data: Path, tmp_path: Path) -> None:
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.io import load_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material

    scene = load_splats(shared_data / "donut_fused.ply")
    result = bake(
        scene, tmp_path / "donut.usd",
        force=ForceSpec.from_interaction("poke", (0.0, 0.0, -3.0)),
        material=Material.from_preset("jelly"),
        prepare_options=PrepareOptions(static_below=0.01),
        settings=BakeSettings(seconds=2.5, fps=20, quality="draft", fmt="instancer", stop_at_rest=False),
    )
    disp = np.array(result.displacement_per_frame)
    assert np.isfinite(disp).all()
    assert disp.max() > 1e-4  # the poke moves the donut (scene units; the donut is 0.2 across)
    first, last = disp[1:21].max(), disp[-20:].max()
    assert last < first, f"motion did not decay: first second {first:.3g}, last second {last:.3g}"


def test_guard_stop_leaves_no_file(plant_ply: Path, tmp_path: Path) -> None:
    out = tmp_path / "boom.usd"
    res = _bake(["--scene", str(plant_ply), "--preset", "jelly", "--force", "0,0,1e9", "--frames", "6",
                 "--substeps", "2", "--quality", "draft", "--device", "cpu", str(out)], tmp_path)
    assert res.exit_code == 2, res.output
    assert res.output.startswith("Error:") and ("substeps" in res.output or "force" in res.output)
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".boom")]


def test_no_material_names_the_options(tmp_path: Path) -> None:
    res = _bake(["--force", "0,0,1", str(tmp_path / "x.usd")], tmp_path)
    assert res.exit_code == 2 and "--scene" in res.output and "--preset" in res.output


def test_force_pointing_at_nothing(plant_ply: Path, tmp_path: Path) -> None:
    res = _bake(["--scene", str(plant_ply), "--preset", "flower", "--force", "1,0,0", "--at", "5,5,5",
                 "--radius", "0.1", "--frames", "3", "--quality", "draft", "--device", "cpu",
                 str(tmp_path / "x.usd")], tmp_path)
    assert res.exit_code == 2 and "holds no free particle" in res.output
    assert not (tmp_path / "x.usd").exists()


def test_bad_output_suffix(plant_ply: Path, tmp_path: Path) -> None:
    res = _bake(["--scene", str(plant_ply), "--preset", "flower", "--force", "0,0,1", str(tmp_path / "x.abc")], tmp_path)
    assert res.exit_code == 2 and ".usd" in res.output


@pytest.fixture(scope="module")
def thin_plant_ply(tmp_path_factory) -> Path:
    # 8,000 Gaussians fill a 64-cell grid with 5.6 particles per occupied cell (at least 4 needed)
    return save_splats(make_plant(8000, seed=0, thin=True), tmp_path_factory.mktemp("thin") / "thin.ply")


def test_bake_raises_the_grid_for_thin_leaves_unless_told_not_to(thin_plant_ply: Path, tmp_path: Path) -> None:
    common = ["--scene", str(thin_plant_ply), "--preset", "leafy-plant", "--force", "1,0,0", "--seconds", "0.2",
              "--quality", "draft", "--static-below", str(POT_TOP), "--device", "cpu"]
    res = _bake([*common, str(tmp_path / "raised.usd")], tmp_path)
    assert res.exit_code == 0, res.output
    line = next(x for x in res.output.splitlines() if x.startswith("thin parts:"))
    assert "simulating on 64 cells" in line and "--no-refine-thin keeps 32" in line, line
    assert "x64 grid" in res.output
    # draft's ratio gives the raised grid's cells too few drivers: the floor's, from sub-particles
    assert "drivers: 8 in each moving cell" in res.output, res.output
    driven = int(res.output.split("driven by ")[1].split(" particles")[0].replace(",", ""))
    draft = load_preset("quality", "draft")
    (tmp_path / "no_floor.toml").write_text("[no-floor]\n" + "".join(
        f"{k} = {v}\n" for k, v in {**draft, "min_drivers_per_cell": 0}.items() if k != "note"))
    common[common.index("draft")] = str(tmp_path / "no_floor.toml")
    res = _bake([*common, "--no-refine-thin", str(tmp_path / "own.usd")], tmp_path)
    assert res.exit_code == 0, res.output
    assert "x32 grid" in res.output and "try " in res.output  # the notice names what would resolve them
    assert "drivers:" not in res.output  # a quality without the floor keeps its ratio
    assert int(res.output.split("driven by ")[1].split(" particles")[0].replace(",", "")) < driven / 4


def test_a_thin_grid_that_would_run_too_long_falls_back_to_the_quality_grid(thin_plant_ply: Path, tmp_path: Path,
                                                                           monkeypatch) -> None:
    import pd_tool.prepare.work as W

    real = W.check_bake_work

    def only_coarse(prep, **kw):
        if max(prep.grid_dims) > 40:
            raise W.WorkTooLarge("too long")
        return real(prep, **kw)

    monkeypatch.setattr(W, "check_bake_work", only_coarse)
    res = _bake(["--scene", str(thin_plant_ply), "--preset", "leafy-plant", "--force", "1,0,0", "--seconds", "0.2",
                 "--quality", "draft", "--static-below", str(POT_TOP), "--device", "cpu",
                 str(tmp_path / "o.usd")], tmp_path)
    assert res.exit_code == 0, res.output
    assert "x32 grid" in res.output
    assert "thin parts: kept the 32-cell grid; 64 cells would take longer than --max-minutes allows" in res.output


def test_force_in_object_sizes_moves_any_capture_scale_the_same(plant_ply: Path, tmp_path: Path) -> None:
    # The same plant captured in centimetres (100x the coordinates): --force 1,0,0 in the
    # default units (object sizes per s^2) moves both the same fraction of their size; in
    # scene units the centimetre capture would barely move.
    from dataclasses import replace

    from pxr import Usd

    from pd_tool.io import load_splats
    from usd_export import instance_positions

    base = load_splats(plant_ply)
    big = replace(base, positions=base.positions * 100.0, scales=base.scales * 100.0, raw=None)
    peaks = {}
    for name, scene, units in (("m", base, "size"), ("cm", big, "size"), ("cm_scene", big, "scene")):
        ply = save_splats(scene, tmp_path / f"{name}.ply")
        out = tmp_path / f"{name}.usd"
        res = _bake(["--scene", str(ply), "--preset", "flower", "--force", "1,0,0", "--force-units", units,
                     "--seconds", "0.5", "--quality", "draft", "--static-below", "20%", "--up", "+z",
                     "--format", "instancer", "--device", "cpu", str(out)], tmp_path)
        assert res.exit_code == 0, res.output
        stage = Usd.Stage.Open(str(out))
        rest = instance_positions(stage, 0)[1]
        size = float(np.ptp(rest, axis=0).max())
        peaks[name] = max(float(np.abs(instance_positions(stage, f)[1] - rest).max()) for f in range(1, 16)) / size
    assert 0.005 < peaks["m"] < 0.5, peaks  # visible, nothing flies off
    assert abs(peaks["cm"] / peaks["m"] - 1) < 0.05, peaks
    assert peaks["cm_scene"] < 0.05 * peaks["m"], peaks


def test_drivers_are_built_on_the_bakes_device(tmp_path, device) -> None:
    """K-Means and the nearest drivers run where the bake runs: clustering 100k Gaussians on
    the CPU takes 6-16 s, against 0.1 s of GPU simulation. On CPU-only machines this checks
    the CPU case alone."""
    import torch

    from pd_tool.bake import BakeSettings, ForceSpec
    from pd_tool.bake.baker import Baker
    from pd_tool.io.synthetic import POT_TOP, make_plant
    from pd_tool.materials.presets import Material
    from pd_tool.prepare.preparation import PrepareOptions

    with Baker(make_plant(600, seed=0), tmp_path / "b.usd", force=ForceSpec.from_interaction("poke", (2.0, 0.0, 0.0)),
               material=Material.from_preset("flower"), prepare_options=PrepareOptions(static_below=POT_TOP),
               settings=BakeSettings(seconds=1 / 30, fps=30, fmt="instancer", quality="draft", device=device)) as b:
        want = torch.device(device).type
        assert b.drivers.positions.device.type == want and b.drivers.neighbors.device.type == want
    assert not (tmp_path / "b.usd").exists()  # left before finish(): nothing published
