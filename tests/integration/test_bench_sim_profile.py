"""bench/sim_profile.py --scene at CI scale: it profiles the solver a bake builds (the same
particles, grid and substeps as the bake reports), poked, and leaves no output behind."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_scene_profile_is_the_bakes_solver(tmp_path: Path) -> None:
    out = tmp_path / "prof.json"
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "sim_profile.py"), "--device", "cpu", "--scene",
                           "thin", "--gaussians", "3000", "--quality", "draft", "--frames", "1", "--json", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    row = json.loads(out.read_text())["rows"][0]

    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.io.synthetic import POT_TOP, make_plant
    from pd_tool.materials.presets import Material
    from pd_tool.prepare.preparation import PrepareOptions

    res = bake(make_plant(3000, seed=0, thin=True), tmp_path / "b.usd",
               force=ForceSpec.from_interaction("poke", (20.0, 0.0, 0.0)), material=Material.from_preset("flower"),
               prepare_options=PrepareOptions(static_below=POT_TOP),
               settings=BakeSettings(seconds=2 / 30, quality="draft", device="cpu", stop_at_rest=False))
    assert row["particles"] == res.drivers
    assert row["substeps_per_frame"] >= 1 and len(row["grid"]) == 3
    assert row["active_blocks"] is None  # the CPU has no binned P2G to tag blocks
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.usd", "prof.json"]
