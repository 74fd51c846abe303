"""The speed benchmarks' own parts at CI scale: usd_write's usd-core floor writes the frames
it times (every sample reads back) and leaves nothing behind; bake_speed's setup parts
account for the setup; sim_speed's frame cost splits frames that differ in their substeps."""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _bench(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_usd_core_floor_writes_every_frame(tmp_path: Path, monkeypatch) -> None:
    from pxr import Sdf

    mod = _bench("usd_write")
    kept = {}
    real_save = Sdf.Layer.Save

    def unlink_later(self, *a):  # read the file back before the floor deletes it
        ok = real_save(self, *a)
        kept["times"] = self.ListAllTimeSamples()
        kept["n"] = len(self.QueryTimeSample("/Instancer.positions", 2))
        return ok

    monkeypatch.setattr(Sdf.Layer, "Save", unlink_later)
    res = mod.usd_core_floor(1000, 3, str(tmp_path))
    assert kept["times"] == [0.0, 1.0, 2.0] and kept["n"] == 1000
    # at least every frame's positions (the crate file stores a repeated array once)
    assert res["mb_per_s"] > 0 and res["file_mb"] >= 3 * 1000 * 12 / 2**20
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_bake_speed_setup_parts_add_up(tmp_path: Path) -> None:
    out = tmp_path / "b.json"
    subprocess.run([sys.executable, str(REPO / "bench" / "bake_speed.py"), "--quick", "--json", str(out),
                    "--profile", str(tmp_path / "p.txt")], check=True, capture_output=True, cwd=REPO)
    d = json.loads(out.read_text())
    parts, setup = d["setup_parts_s"], d["timings_s"]["setup"]
    assert set(parts) >= {"prepare", "grid", "drivers", "solver", "outputs"}
    # the parts cover the setup but for the output checks before them
    assert 0.8 * setup <= sum(parts.values()) <= setup * 1.001
    text = (tmp_path / "p.txt").read_text()
    assert "prepare_scene" in text
    assert text.index("Ordered by: cumulative time") < text.index("Ordered by: internal time")


def test_bake_speed_bakes_a_capture(tmp_path: Path, shared_data: Path) -> None:
    """--scene bakes the capture itself (every one of udon's Gaussians, its lowest tenth
    pinned), not the plant."""
    out = tmp_path / "b.json"
    subprocess.run([sys.executable, str(REPO / "bench" / "bake_speed.py"), "--device", "cpu", "--scene", "udon",
                    "--data", str(shared_data), "--gaussians", "300000", "--quality", "draft", "--seconds", "0.1",
                    "--json", str(out)], check=True, capture_output=True, cwd=REPO)
    d = json.loads(out.read_text())
    from pd_tool.io import load_splats

    assert d["scene"] == "udon" and d["gaussians"] == load_splats(shared_data / "udon.ply").count
    assert d["drivers"] > 0 and any(" static" in line for line in d["report"])


def test_sim_speed_frame_cost_splits_a_frame(tmp_path: Path) -> None:
    """--frame-cost times the forward at S and 4S substeps a frame: the longer frame takes
    longer, and the split gives back both frame times."""
    out = tmp_path / "s.json"
    subprocess.run([sys.executable, str(REPO / "bench" / "sim_speed.py"), "--quick",
                    "--no-backward", "--frame-cost", "--json", str(out)], check=True, cwd=REPO,
                   capture_output=True, timeout=600)
    fc = json.loads(out.read_text())["rows"][0]["frame_cost"]
    t1, t4 = fc["frame_us"]["4"], fc["frame_us"]["16"]
    assert t4 > t1 > 0 and fc["substep_us"] > 0
    assert fc["frame_fixed_us"] + 16 * fc["substep_us"] == pytest.approx(t4)
