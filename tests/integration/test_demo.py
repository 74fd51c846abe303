"""`pdtool demo --quality draft` end to end, as CI runs it, then a bare `pdtool bake` that
picks up the demo's fit: the fit works on CPU, the USD validates, the stiff stem comes
out stiffer than the soft leaves, the loss fell."""
from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main

STIFF_OVER_SOFT = 1.2  # recovered E(stem) / E(leaf) must exceed this (the uniform start gives 1.0; truth 60x)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo")
    res = CliRunner().invoke(main, ["demo", "--quality", "draft", "--out", str(out), "--device", "cpu"],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    (out.parent / f"{out.name}.stdout.txt").write_text(res.output)  # beside it: the folder is the demo's
    return out


def test_demo_outputs(demo_dir: Path) -> None:
    for name in ("plant.ply", "video/camera.json", "video/frame_0000.png", "plant.pdmat", "plant.report.json",
                 "plant.loss.png", "plant.E.png", "plant.E.ply", "plant.preview.mp4", "poke.usd", "poke.mp4"):
        assert (demo_dir / name).is_file(), name
    text = (demo_dir.parent / f"{demo_dir.name}.stdout.txt").read_text()
    assert "fit " in text and "bake " in text and "truth" in text


def test_demo_folder_is_the_demos_own(demo_dir: Path, tmp_path: Path) -> None:
    """The demo writes fixed names: it may write again into a folder it made, never into
    one that holds a user's file."""
    from pd_tool.core.atomic import folder_mark
    from pd_tool.demo import DEMO_MARK, _claim_folder

    assert folder_mark(demo_dir) == DEMO_MARK
    _claim_folder(demo_dir)  # a second demo into the same folder is allowed
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "plant.ply").write_text("my own scan")
    res = CliRunner().invoke(main, ["demo", "--quality", "draft", "--out", str(mine), "--device", "cpu"])
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and "holds plant.ply, which pdtool did not write" in lines[0], lines
    assert sorted(p.name for p in mine.iterdir()) == ["plant.ply"]
    assert (mine / "plant.ply").read_text() == "my own scan"


def test_demo_usd_validates_and_moves(demo_dir: Path) -> None:
    import numpy as np
    from pxr import Usd, UsdGeom

    from usd_export import validate_usd

    validate_usd(demo_dir / "poke.usd")  # raises on any error
    stage = Usd.Stage.Open(str(demo_dir / "poke.usd"))
    assert stage.GetEndTimeCode() - stage.GetStartTimeCode() == 60  # 2 s at 30 fps
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    rest = np.asarray(inst.GetPositionsAttr().Get(stage.GetStartTimeCode()))
    moved = max(float(np.abs(np.asarray(inst.GetPositionsAttr().Get(f)) - rest).max()) for f in range(1, 61, 5))
    size = float((rest.max(0) - rest.min(0)).max())
    assert 0.002 * size < moved < size, (moved, size)  # the poke shows, and nothing flies off


def test_demo_fit_separates_stiff_and_soft(demo_dir: Path) -> None:
    import numpy as np

    from pd_tool.io import load_splats
    from pd_tool.materials.file import MaterialFile
    from pd_tool.io.synthetic import REGIONS

    mf = MaterialFile.load(demo_dir / "plant.pdmat")
    scene = load_splats(demo_dir / "plant.ply")
    E = mf.E_at(scene.positions.double().numpy())
    med = {name: float(np.median(E[scene.labels == i])) for i, name in enumerate(REGIONS)}
    assert med["stem"] > STIFF_OVER_SOFT * med["leaf"], med
    report = json.loads((demo_dir / "plant.report.json").read_text())
    losses = report["losses"]["velocity"] + report["losses"]["material"]
    assert losses[-1] < 0.5 * losses[0], losses


def test_bare_bake_uses_the_fit(demo_dir: Path) -> None:
    old = os.getcwd()
    os.chdir(demo_dir)
    try:
        res = CliRunner().invoke(main, ["bake", "--force", "0,0,1", "--frames", "4", "--device", "cpu", "again.usd"],
                                 catch_exceptions=False)
        coarse = CliRunner().invoke(main, ["bake", "--force", "0,0,1", "--frames", "4", "--quality", "draft",
                                           "--device", "cpu", "coarse.usd"], catch_exceptions=False,
                                    env={"PDTOOL_PROGRESS": "1"})
        plain = CliRunner().invoke(main, ["bake", "--force", "0,0,1", "--frames", "4", "--quality", "draft",
                                          "--no-match-fit", "--device", "cpu", "plain.usd"], catch_exceptions=False)
    finally:
        os.chdir(old)
    assert res.exit_code == 0, res.output
    assert (demo_dir / "again.usd").is_file()
    # without --quality the bake simulates on the fit's grid with the fit's drivers, one to one
    from pd_tool.materials.file import MaterialFile

    mf = MaterialFile.load(demo_dir / "plant.pdmat")
    sim = mf.fit_simulation()
    assert f"{sim['grid_res']}-cell grid" in res.output and "as the fit did" in res.output
    assert f"driven by {len(mf.driver_E):,} particles" in res.output
    # a named quality with another grid matches the fit's motion first and says so; without
    # the match it says that the fitted E moves differently there
    assert coarse.exit_code == 0, coarse.output
    assert "fitted material matched to this grid: E x" in coarse.output, coarse.output
    # the match has its own bar, before the frames' (PDTOOL_PROGRESS=1: bars on a pipe)
    assert 0 <= coarse.output.index("matching the fitted E to this grid") < coarse.output.index("bake"), coarse.output
    assert plain.exit_code == 0, plain.output
    assert "moves differently" in plain.output and "matched" not in plain.output


def test_default_demo_fits_two_videos_seen_from_two_sides(tmp_path: Path, monkeypatch) -> None:
    """The default demo's second video, seen from another side, reaches the fit. Run at a
    tiny size: the path, not the accuracy."""
    from pd_tool import demo

    _, _, _, _, _, videos = demo.DEMO_SIZES["default"]
    assert videos == 2
    monkeypatch.setitem(demo.DEMO_SIZES, "default", (500, 4, 48, 1, 1, videos))
    res = demo.run_demo(tmp_path / "d", quality="default", say=lambda _: None)
    assert {"video", "video2"} <= set(res.paths)
    report = json.loads((res.out_dir / "plant.report.json").read_text())
    assert [Path(v).name for v in report["videos"]] == ["video", "video2"]
    cams = [json.loads((res.paths[k] / "camera.json").read_text()) for k in ("video", "video2")]
    assert cams[0] != cams[1]  # seen from two sides
