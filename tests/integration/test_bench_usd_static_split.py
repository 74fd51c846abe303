"""bench/usd_static_split.py at CI scale: the poses it reads back from a bake are the bake's
(every frame, every Gaussian, static ones unmoved), and writing the pot once makes the file
smaller than one time-sampled prim."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("usd_static_split", REPO / "bench" / "usd_static_split.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_read_poses_returns_what_was_written(tmp_path: Path) -> None:
    from usd_export import UsdBakeWriter

    rng = np.random.default_rng(0)
    n, frames = 50, 4
    static = np.zeros(n, bool)
    static[::5] = True
    pos = rng.normal(size=(frames, n, 3)).astype(np.float32)
    pos[:, static] = pos[0, static]
    q = rng.normal(size=(frames, n, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q[:, static] = q[0, static]
    sig = rng.uniform(0.01, 0.05, size=(frames, n, 3)).astype(np.float32)
    sig[:, static] = sig[0, static]
    path = tmp_path / "a.usd"
    with UsdBakeWriter(path, n_points=n, fps=30, fmt="both", static=static) as w:
        for f in range(frames):
            w.write_frame(f, pos[f], q[f], sig[f])
    got_static, got_pos, got_q, got_sig, ids = _bench().read_poses(path)
    assert np.array_equal(ids, np.arange(n))
    assert np.array_equal(got_static, static)
    np.testing.assert_allclose(got_pos, pos, atol=1e-6)
    # quath keeps about 3 decimal digits; q and -q are one rotation
    assert np.abs(np.abs((got_q * q).sum(-1)) - 1).max() < 2e-3
    np.testing.assert_allclose(got_sig, sig, rtol=2e-3)


@pytest.mark.slow
def test_quick_run_reports_a_smaller_split_file(tmp_path: Path) -> None:
    out = tmp_path / "split.json"
    p = subprocess.run([sys.executable, str(REPO / "bench" / "usd_static_split.py"), "--quick", "--json", str(out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-3000:]
    rep = json.loads(out.read_text())
    assert 0.1 < rep["static_share"] < 0.5  # the pot
    assert rep["rewrite_split_mib"] < rep["rewrite_one_prim_mib"]
