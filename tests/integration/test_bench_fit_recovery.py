"""bench/fit_recovery.py at a tiny scale: its JSON has every region, the new-force errors,
the v0 error against the true push and the objective at the fitted and true E and v0."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
TINY = ["--quality", "draft", "--device", "cpu", "--gaussians", "800", "--size", "32", "--frames", "4", "--seconds", "0.2",
        "--velocity-iters", "1", "--material-iters", "1"]


def _run(tmp_path: Path, *extra: str) -> dict:
    out = tmp_path / f"rec{len(extra)}.json"
    p = subprocess.run([sys.executable, str(REPO / "bench" / "fit_recovery.py"), *TINY, *extra, "--json", str(out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(out.read_text())


@pytest.mark.slow
def test_fit_recovery_report(tmp_path: Path) -> None:
    rep = _run(tmp_path, "--substeps", "60")
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
    assert rep["substeps"] == 60
    assert rep["v0_rel_error"] > 0.1  # one stage-1 iteration from a zero field is far off
    # the per-axis split adds up to the whole error
    assert len(rep["v0_axis_error"]) == 3
    assert abs(sum(e * e for e in rep["v0_axis_error"]) ** 0.5 - rep["v0_rel_error"]) < 1e-6 + 1e-6 * rep["v0_rel_error"]
    f = rep["objective"]
    assert f["E_truth/v0_truth"] < f["E_truth/v0_fitted"]  # a v0 far off costs loss at the true E
    # the loss curves: one entry an iteration, and the whole-clip loss the fit ended on
    assert len(rep["losses"]["velocity"]) == 1 and len(rep["losses"]["material"]) == 1
    assert rep["losses"]["start"][0] == pytest.approx(rep["fit_metrics"]["loss_start"], rel=1e-6)


@pytest.mark.slow
def test_fit_recovery_lean_run_saves_drivers_and_gradients(tmp_path: Path) -> None:
    import numpy as np

    from pd_tool.io.synthetic import REGION_TRUTH_E

    npz = tmp_path / "drivers.npz"
    rep = _run(tmp_path, "--material-iters", "2", "--no-variants", "--residual-gradients", "--save-drivers", str(npz),
               "--set", "residual_eps=1e-16")
    assert rep["overrides"] == {"residual_eps": 1e-16}
    nf = rep["new_force"]
    assert "rms_error_with" not in nf and set(nf["substeps"]) == {"truth", "fitted"}
    g = rep["residual_gradients"]
    assert g["iterations"] == 2  # one record per stage-2 iteration
    assert {"stem", "leaf", "flower"} <= set(g)
    for name in ("stem", "leaf", "flower"):
        q = g[name]["rms_q10_q50_q90"]
        assert 0 <= q[0] <= q[1] <= q[2] and 0 <= g[name]["sign_consistency"] <= 1
    assert g["stem"]["rms_q10_q50_q90"][1] > 0  # the stem's E moves the image
    d = np.load(npz)
    q = rep["drivers"]
    assert d["position"].shape == (q, 3) and d["fitted_v0"].shape == (q, 3)
    assert len(d["fitted_E"]) == len(d["truth_E"]) == len(d["region"]) == len(d["static"]) == q
    assert np.all(d["fitted_E"] > 0)
    names = list(d["region_names"])
    assert np.array_equal(d["truth_E"], np.array([REGION_TRUTH_E[names[r]] for r in d["region"]]))
