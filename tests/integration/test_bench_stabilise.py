"""bench/stabilise_accuracy.py at a CI scale: a real capture before a textured room, shaken
by a known similarity, comes back within a small share of the frame."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests._bench import BENCH


def test_a_shaken_capture_is_stabilised_close_to_the_true_shake(tmp_path: Path, shared_data) -> None:
    out = tmp_path / "s.json"
    run = subprocess.run([sys.executable, str(BENCH / "stabilise_accuracy.py"), "--scenes", "udon", "--cases", "1",
                          "--frames", "3", "--size", "128", "--gaussians", "2000", "--data", str(shared_data),
                          "--json", str(out)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-3000:]
    (row,) = json.loads(out.read_text())["rows"]
    (case,) = row["cases"]
    assert case["warped"] and len(case["corner_error_pct"]) == 2
    # the shake was several times what is left of it, and the frames came back closer
    assert max(case["corner_error_pct"]) < 0.5 < min(case["shake_pct"]), case
    assert row["grey_error_after"] < 0.5 * row["grey_error_shaken"], row
