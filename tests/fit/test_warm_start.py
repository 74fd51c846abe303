"""A fit that starts from an earlier fit's E (`--init-material`), and the whole-clip loss
every fit records (losses["final"])."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from test_outputs import _tiny_fit


@pytest.fixture(scope="module")
def first_fit(fit_dir: Path, tmp_path_factory):
    """(folder, FitResult) of a one-iteration-per-stage fit of the fixture's plant."""
    from pd_tool.fit.settings import FitSettings

    folder = tmp_path_factory.mktemp("warm")
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=2, working_long_side=24)
    return folder, _tiny_fit(fit_dir, folder / "first.pdmat", settings)[2]


def test_a_warm_start_carries_the_earlier_fit_s_E_to_every_driver(fit_dir: Path, first_fit) -> None:
    """Fitting only v0 (no stage 2, no level) from an earlier fit of the same scene on the
    same drivers leaves each driver at that fit's E, not at the uniform start."""
    from pd_tool.fit.settings import FitSettings
    from pd_tool.materials.file import MaterialFile

    folder, first = first_fit
    assert np.ptp(np.log(first.driver_E)) > 1e-3  # the earlier fit moved E away from uniform
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=0, stage1_level=False,
                           working_long_side=24, init_material=str(folder / "first.pdmat"))
    warm = _tiny_fit(fit_dir, folder / "warm.pdmat", settings)[2]
    np.testing.assert_allclose(warm.driver_E, first.driver_E, rtol=2e-5)
    mf = MaterialFile.load(folder / "warm.pdmat")
    assert mf.meta["settings"]["init_material"] == str(folder / "first.pdmat")
    # the whole-clip loss of the result is recorded, as a number, in both files a fit leaves
    final = warm.losses["final"]
    assert len(final) == 1 and np.isfinite(final[0]) and final[0] > 0
    assert mf.meta["metrics"]["loss_final"] == final[0]


def test_the_final_loss_is_the_whole_clip_loss_of_what_was_fitted(fit_dir: Path, first_fit) -> None:
    """losses["final"] against the whole clip simulated again, from the material file's
    E and the fit's own v0, by a fresh FitProblem."""
    import torch

    from pd_tool.fit.problem import FitProblem, sequence_loss
    from pd_tool.fit.settings import FitSettings
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import POT_TOP
    from pd_tool.materials.file import MaterialFile
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.video.folder import load_reference_video

    folder, first = first_fit
    settings = FitSettings(quality="draft", velocity_iters=1, material_iters=2, working_long_side=24).resolved()
    pb = FitProblem(load_splats(fit_dir / "plant.ply"), [load_reference_video(fit_dir / "video", working_size=24)],
                    PrepareOptions(static_below=POT_TOP, up_axis="+z"), settings)
    pb.start_from(MaterialFile.load(folder / "first.pdmat"))
    with torch.no_grad():
        again = float(sequence_loss(pb, pb.driver_E(), [torch.as_tensor(first.driver_v0s[0], dtype=torch.float32)],
                                    None))
    assert again == pytest.approx(first.losses["final"][0], rel=1e-3)


def test_stage_2_s_start_is_recorded_on_the_final_loss_s_footing(first_fit) -> None:
    """losses["start"] is the whole-clip loss when stage 2 starts, under the E stage 1 left
    (the uniform start times its level) and stage 1's v0, in the material file's metrics too."""
    from pd_tool.materials.file import MaterialFile

    folder, first = first_fit
    start = first.losses["start"]
    assert len(start) == 1 and 0 < start[0] < 1
    assert MaterialFile.load(folder / "first.pdmat").meta["metrics"]["loss_start"] == start[0]
    # two stage-2 steps from that start: the whole clip moved
    assert first.losses["final"][0] != start[0]


def test_the_report_says_when_stage_2_raised_the_whole_clip_loss() -> None:
    from pd_tool.fit.run import whole_clip_note, whole_clip_text

    note = whole_clip_note({"start": [0.0257], "final": [0.0333]})  # a fit that keeps no best state
    assert note is not None and "0.0257 -> 0.0333" in note and "another video" in note
    assert whole_clip_note({"start": [0.03], "final": [0.02]}) is None
    assert whole_clip_note({"final": [0.02]}) is None  # no stage 2: nothing to compare
    assert whole_clip_text({"start": [0.0257], "final": [0.0333], "material": [0.5]}) == "0.0257 -> 0.0333"
    assert whole_clip_text({"final": [0.02]}) == "0.0200"


def test_a_warm_start_is_refused_for_another_scene_or_as_the_output(fit_dir: Path, first_fit, tmp_path: Path) -> None:
    """One line, exit 2, nothing written: a material fitted to another scene file, and an
    output that would replace the material the fit starts from."""
    from click.testing import CliRunner

    from cli import main

    folder, _ = first_fit
    start = folder / "first.pdmat"
    other = tmp_path / "other.ply"
    data = bytearray((fit_dir / "plant.ply").read_bytes())
    data[-1] ^= 1  # another file: another fingerprint
    other.write_bytes(bytes(data))
    runs = {
        "another scene": ["fit", str(other), str(fit_dir / "video"), "-o", str(tmp_path / "a.pdmat")],
        "its own output": ["fit", str(fit_dir / "plant.ply"), str(fit_dir / "video"), "-o", str(start)],
    }
    before = start.read_bytes()
    for what, args in runs.items():
        res = CliRunner().invoke(main, [*args, "--init-material", str(start), "--quality", "draft",
                                        "--working-size", "24", "--no-preview", "--device", "cpu"])
        assert res.exit_code == 2, (what, res.output)
        lines = [line for line in res.output.splitlines() if line.strip()]
        assert len(lines) == 1 and "Traceback" not in res.output, (what, res.output)
        assert ("fitted to" in lines[0]) if what == "another scene" else ("--init-material" in lines[0]), lines[0]
    assert start.read_bytes() == before
    assert not (tmp_path / "a.pdmat").exists()
    assert not any(p.suffix in (".json", ".png") for p in tmp_path.iterdir()), list(tmp_path.iterdir())
