"""bench/fit_recovery.py at a tiny scale: its JSON has every region and the new-force
errors, and --oracle-v0 really hands stage 2 the true push (v0 error ~0, against a v0
fitted in one stage-1 iteration, which is far off)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TINY = ["--quality", "draft", "--device", "cpu", "--gaussians", "800", "--size", "32", "--frames", "4", "--seconds", "0.2",
        "--velocity-iters", "1", "--material-iters", "1"]


def _run(tmp_path: Path, *extra: str) -> dict:
    out = tmp_path / f"rec{len(extra)}.json"
    p = subprocess.run([sys.executable, str(REPO / "bench" / "fit_recovery.py"), *TINY, *extra, "--json", str(out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(out.read_text())


@pytest.mark.slow
def test_fit_recovery_report_and_oracle_v0(tmp_path: Path) -> None:
    fitted = _run(tmp_path)
    oracle = _run(tmp_path, "--oracle-v0", "--substeps", "60")
    for rep in (fitted, oracle):
        assert set(rep["regions"]) == {"stem", "leaf", "flower"}
        for r in rep["regions"].values():
            assert r["fitted_pa"] > 0 and r["log_space_rel_error"] >= 0
        nf = rep["new_force"]
        assert nf["rms_error_fitted"] >= 0 and nf["rms_error_uniform_baseline"] > 0
        assert set(nf["rms_error_with"]) == {"stem_true", "leaf_true", "flower_true", "region_medians",
                                             "truth_at_fitted_substeps", "capped_q99", "capped_q95"}
        # a cap never raises E, so never the substep count
        assert nf["substeps"]["capped_q95"] <= nf["substeps"]["capped_q99"] <= nf["substeps"]["fitted"]
        assert all(v >= 0 for v in nf["rms_error_with"].values())
        assert nf["substeps"]["truth"] >= 1 and nf["substeps"]["fitted"] >= 1
        if nf["substeps"]["fitted"] <= nf["substeps"]["truth"]:  # the floor changes nothing: the truth's own run
            assert nf["rms_error_with"]["truth_at_fitted_substeps"] < 1e-6
        else:
            assert nf["rms_error_with"]["truth_at_fitted_substeps"] > 0
    assert oracle["oracle_v0"] and not fitted["oracle_v0"]
    assert fitted["substeps"] is None and oracle["substeps"] == 60
    assert oracle["v0_rel_error"] < 1e-5
    assert fitted["v0_rel_error"] > 0.1  # one stage-1 iteration from a zero field is far off
    # the per-axis split adds up to the whole error
    for rep in (fitted, oracle):
        assert len(rep["v0_axis_error"]) == 3
        assert abs(sum(e * e for e in rep["v0_axis_error"]) ** 0.5 - rep["v0_rel_error"]) < 1e-6 + 1e-6 * rep["v0_rel_error"]
    # the objective at the fitted and true E and v0: the oracle's v0 is the truth's, so
    # swapping in the true v0 changes nothing there
    o = oracle["objective"]
    assert o["E_fitted/v0_fitted"] == o["E_fitted/v0_truth"] and o["E_truth/v0_fitted"] == o["E_truth/v0_truth"]
    f = fitted["objective"]
    assert f["E_truth/v0_truth"] < f["E_truth/v0_fitted"]  # a v0 far off costs loss at the true E
