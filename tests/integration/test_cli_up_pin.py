"""--up auto, --static-below PCT%, --pin auto, select --quality and inverted boxes,
through the command line: refusals are one line with exit code 2."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from cli import main


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def _one_error_line(res) -> str:
    assert res.exit_code == 2, (res.exit_code, res.stdout, res.stderr)
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and "Traceback" not in res.stderr, res.stderr
    return lines[0]


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    return save_splats(make_plant(1500, seed=0, thin=True), tmp_path_factory.mktemp("plant") / "plant.ply")


def test_info_prints_the_up_guess_and_heights(shared_data: Path) -> None:
    res = _run(["info", shared_data / "tree_100k.splat"])
    assert res.exit_code == 0
    assert re.search(r"up \(guess\)\s+-y, sure", res.stdout) and "along -y: bottom at" in res.stdout
    data = json.loads(_run(["info", shared_data / "donut_fused.ply", "--json"]).stdout)
    assert data["up"]["axis"] == "+z" and data["up"]["sure"] and data["up"]["height"] > 0


def test_select_pin_auto_reports_the_pot_and_the_quality(plant, tmp_path) -> None:
    res = _run(["select", plant, "-o", tmp_path / "s.ply", "--pin", "auto", "--quality", "draft"])
    assert res.exit_code == 0, res.output
    assert res.stdout.startswith("quality draft: prepared as `pdtool fit --quality draft` and a bake of its material "
                                 "prepare it, on a 24-cell grid")
    assert re.search(r"pin auto: [\d,]+ Gaussians \(2\d\.\d%\), heights .* along \+z", res.stdout), res.stdout
    assert "up axis +z" in res.stdout and res.stderr == ""


def test_select_uses_the_qualitys_fit_grid(plant, tmp_path) -> None:
    grids = {}
    for q in ("draft", "default"):
        res = _run(["select", plant, "-o", tmp_path / "s.ply", "--quality", q, "--up", "+z"])
        assert res.exit_code == 0, res.output
        grids[q] = re.search(r"(\d+)x(\d+)x(\d+) grid", res.stdout).groups()
    assert max(map(int, grids["draft"])) == 24 and max(map(int, grids["default"])) == 32
    line = _one_error_line(_run(["select", plant, "-o", tmp_path / "s.ply", "--quality", "superb"]))
    assert "superb" in line


def _preparation_lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if re.match(r"(fill|pin auto|thin parts|[\d,]+ Gaussians simulated)", ln)]


@pytest.mark.parametrize("quality", ["draft", "default"])
def test_select_for_bake_shows_what_a_preset_bake_simulates(plant, tmp_path, quality) -> None:
    # the grid (raised for the thin leaves at default), the fill decision and the static set
    # that select prints are the bake's own report lines
    common = ["--pin", "auto", "--quality", quality, "--device", "cpu"]
    sel = _run(["select", plant, "-o", tmp_path / "s.ply", "--for", "bake", *common])
    assert sel.exit_code == 0, sel.output
    assert sel.stdout.startswith(f"quality {quality}: prepared as `pdtool bake --preset NAME --quality {quality}`")
    baked = _run(["bake", "--scene", plant, "--preset", "leafy-plant", "--force", "1,0,0", "--frames", "2",
                  "--format", "instancer", *common, tmp_path / "b.usd"])
    assert baked.exit_code == 0, baked.output
    want = _preparation_lines(baked.stdout)
    assert len(want) >= 3 and any("Gaussians simulated" in ln for ln in want), baked.stdout
    assert _preparation_lines(sel.stdout) == want
    fit_sel = _run(["select", plant, "-o", tmp_path / "s.ply", *common])
    assert _preparation_lines(fit_sel.stdout) != want  # the fit's grid is coarser


def test_static_below_percent_and_warnings(plant, tmp_path) -> None:
    res = _run(["select", plant, "-o", tmp_path / "s.ply", "--static-below", "20%"])
    assert res.exit_code == 0 and "warning" not in res.stderr
    # the README's old --static-below 0.2 under the wrong up axis pins almost everything
    res = _run(["select", plant, "-o", tmp_path / "s.ply", "--static-below", "0.2", "--up", "-y"])
    assert res.exit_code == 0
    assert re.match(r"warning: --static-below 0.2 pins (9\d|100)\.\d% of the object", res.stderr), res.stderr
    res = _run(["select", plant, "-o", tmp_path / "s.ply", "--static-below", "-3"])
    assert res.exit_code == 0 and res.stderr.startswith("warning: --static-below -3.0 pins nothing"), res.stderr


@pytest.mark.parametrize("value", ["0%", "101%", "abc%", "nan%", "%", "-5%"])
def test_bad_percentages_are_refused(plant, tmp_path, value) -> None:
    line = _one_error_line(_run(["select", plant, "-o", tmp_path / "s.ply", f"--static-below={value}"]))
    assert "--static-below" in line and "percentage" in line


def test_render_up_auto_is_the_default(plant, tmp_path) -> None:
    res = _run(["render", plant, "-o", tmp_path / "r.png", "--width", "32", "--height", "18"])
    assert res.exit_code == 0 and res.stderr == "", res.output  # the thin plant's guess is sure: no note
    assert "[default: auto]" in _run(["render", "--help"]).stdout


INVERTED = "0,0,0.5,1,1,0.2"  # z1 below z0


@pytest.mark.parametrize("args", [
    ["select", "{plant}", "-o", "{tmp}/s.ply", "--static-box", INVERTED],
    ["select", "{plant}", "-o", "{tmp}/s.ply", "--foreground-box", INVERTED],
    ["fit", "{plant}", "{tmp}", "--static-box", INVERTED],
    ["fit", "{plant}", "{tmp}", "--foreground-box", INVERTED],
    ["bake", "{tmp}/o.usd", "--scene", "{plant}", "--preset", "flower", "--force", "0,0,1", "--static-box", INVERTED],
    ["bake", "{tmp}/o.usd", "--scene", "{plant}", "--preset", "flower", "--force", "0,0,1",
     "--foreground-box", INVERTED],
    ["bake", "{tmp}/o.usd", "--scene", "{plant}", "--preset", "flower", "--force", "0,0,1", "--box", INVERTED],
    ["generate", "{plant}", "--model", "{tmp}", "-o", "{tmp}/gen", "--static-box", INVERTED],
], ids=["select static", "select foreground", "fit static", "fit foreground", "bake static", "bake foreground",
        "bake box", "generate static"])
def test_inverted_boxes_are_one_line(plant, tmp_path, args) -> None:
    line = _one_error_line(_run([a.format(plant=plant, tmp=tmp_path) for a in args]))
    assert "box is inverted: z1 (0.2) is below z0 (0.5)" in line and "low corner first" in line
    assert not (tmp_path / "o.usd").exists() and not (tmp_path / "s.ply").exists()
