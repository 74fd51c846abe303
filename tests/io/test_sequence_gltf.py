"""Splat sequences (.ply and .spz frames) and the glTF flipbook: what is written reads back
as the frames given, in the axes each format promises, atomically and only over pdtool's
own outputs; the .glb passes the Khronos glTF validator where it is installed."""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from pd_tool.core.errors import OutputError
from pd_tool.core.quaternion import quat_to_matrix_np
from pd_tool.io import load_ply
from pd_tool.io.formats import output_paths, parse_formats
from pd_tool.io.gltf import Z_UP_TO_Y_UP, GltfSplatWriter
from pd_tool.io.sequence import MANIFEST_NAME, SplatSequenceWriter
from pd_tool.io.synthetic import make_plant
from _glb import accessor as _accessor, read_glb as _read_glb

ROOT = Path(__file__).resolve().parents[2]
VALIDATOR = ROOT / ".ci" / "node" / "node_modules" / "gltf-validator"


@pytest.fixture(scope="module")
def scene():
    return make_plant(400, seed=2)


def _frames(scene, count: int, seed: int = 0):
    """count frames of positions [N, 3] and unit (w, x, y, z) rotations [N, 4]."""
    rng = np.random.default_rng(seed)
    pos0 = scene.positions.numpy().astype(np.float64)
    out = []
    for f in range(count):
        q = rng.normal(size=(scene.count, 4))
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        out.append((pos0 + 0.01 * f * rng.normal(size=pos0.shape), q))
    return out


def test_ply_frames_read_back_as_written(tmp_path, scene):
    frames = _frames(scene, 3)
    with SplatSequenceWriter(tmp_path / "seq", scene, fmt="ply", fps=24, up_axis="+z") as w:
        for f, (p, q) in enumerate(frames):
            w.write_frame(f, p, q)
        w.hold_frames(4)
    names = sorted(p.name for p in (tmp_path / "seq").glob("frame_*.ply"))
    assert names == [f"frame_{f:06d}.ply" for f in range(5)]
    for f in range(5):
        got = load_ply(tmp_path / "seq" / names[f])
        p, q = frames[min(f, 2)]
        assert np.allclose(got.positions.numpy(), p, atol=1e-5)
        assert np.allclose(np.abs((got.quats.numpy() * q).sum(1)), 1, atol=1e-5)
        # what a bake does not change stays as the scene has it
        for a, b in ((got.scales, scene.scales), (got.opacities, scene.opacities), (got.sh, scene.sh)):
            assert torch.allclose(a, b, atol=1e-6)
        assert np.array_equal(got.labels, scene.labels)  # extra properties too
    manifest = json.loads((tmp_path / "seq" / MANIFEST_NAME).read_text())
    assert manifest["frames"] == 5 and manifest["fps"] == 24 and manifest["files"] == names
    assert manifest["written_by"] == "pdtool"


def test_spz_frames_are_the_scene_turned_half_about_x(tmp_path, scene):
    gsply = pytest.importorskip("gsply", reason="the independent SPZ reader (pip install gsply) is not installed")
    frames = _frames(scene, 2, seed=1)
    with SplatSequenceWriter(tmp_path / "seq", scene, fmt="spz", fps=30, up_axis="+z") as w:
        for f, (p, q) in enumerate(frames):
            w.write_frame(f, p, q)
    half = np.diag([1.0, -1.0, -1.0])
    for f, (p, q) in enumerate(frames):
        got = gsply.read_spz(tmp_path / "seq" / f"frame_{f:06d}.spz")
        assert np.abs(got.means - p @ half.T).max() < 2.5e-4
        R_got = quat_to_matrix_np(np.asarray(got.quats, np.float64))
        assert np.abs(R_got - half @ quat_to_matrix_np(q) @ half.T).max() < 0.01


def test_sequences_are_atomic_and_replace_only_their_own(tmp_path, scene):
    (p, q), = _frames(scene, 1)
    w = SplatSequenceWriter(tmp_path / "seq", scene, fmt="ply", fps=30, up_axis="+z")
    w.write_frame(0, p, q)
    w.abort()  # an error or Ctrl-C during the bake
    assert list(tmp_path.iterdir()) == []
    with SplatSequenceWriter(tmp_path / "seq", scene, fmt="ply", fps=30, up_axis="+z") as w:
        w.write_frame(0, p, q)
    with SplatSequenceWriter(tmp_path / "seq", scene, fmt="ply", fps=30, up_axis="+z") as w:  # its own: replaced
        w.write_frame(0, p, q)
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(OutputError, match="pdtool did not write"):
        SplatSequenceWriter(mine, scene, fmt="ply", fps=30, up_axis="+z")
    assert (mine / "notes.txt").read_text() == "keep me"


def test_spz_refuses_positions_it_cannot_hold(tmp_path, scene):
    far = make_plant(100, seed=0)
    far.positions = far.positions + 5000.0
    with pytest.raises(OutputError, match="use --format ply-seq"):
        SplatSequenceWriter(tmp_path / "seq", far, fmt="spz", fps=30, up_axis="+z")


def test_gltf_flipbook_holds_every_frame_in_gltf_axes(tmp_path, scene):
    frames = _frames(scene, 3, seed=4)
    static = np.zeros(scene.count, bool)
    static[:100] = True
    R = Z_UP_TO_Y_UP  # a +z-up scene
    with GltfSplatWriter(tmp_path / "a.glb", scene, static=static, to_gltf=R, fps=10) as w:
        for f, (p, q) in enumerate(frames):
            p[static] = scene.positions.numpy()[static]  # the static ones never move
            w.write_frame(f, p, q)
        w.hold_frames(5)
    doc, blob = _read_glb(tmp_path / "a.glb")
    assert doc["extensionsUsed"] == ["KHR_gaussian_splatting"]
    meshes = {m["name"]: m["primitives"][0] for m in doc["meshes"]}
    assert set(meshes) == {"static", "frame_0", "frame_1", "frame_2"}
    for f, (p, q) in enumerate(frames):
        prim = meshes[f"frame_{f}"]
        assert prim["mode"] == 0 and prim["extensions"]["KHR_gaussian_splatting"]["kernel"] == "ellipse"
        attrs = prim["attributes"]
        assert np.allclose(_accessor(doc, blob, attrs["POSITION"]), p[~static] @ R.T, atol=1e-5)
        q_got = _accessor(doc, blob, attrs["KHR_gaussian_splatting:ROTATION"])[:, [3, 0, 1, 2]]
        assert np.allclose(quat_to_matrix_np(q_got), R @ quat_to_matrix_np(q[~static]), atol=1e-5)
        scale = _accessor(doc, blob, attrs["KHR_gaussian_splatting:SCALE"])
        assert np.allclose(scale, scene.scales.numpy()[~static])  # linear, shared by every frame
        assert attrs["KHR_gaussian_splatting:SCALE"] == meshes["frame_0"]["attributes"]["KHR_gaussian_splatting:SCALE"]
    assert np.allclose(_accessor(doc, blob, meshes["static"]["attributes"]["POSITION"]),
                       scene.positions.numpy()[static] @ R.T, atol=1e-5)
    # the animation shows frame k's node from k / fps on; the last stays through the held frames
    anim = doc["animations"][0]
    nodes = {n["name"]: i for i, n in enumerate(doc["nodes"])}
    times = _accessor(doc, blob, anim["samplers"][0]["input"])
    assert np.allclose(times, np.arange(6) / 10)
    for ch in anim["channels"]:
        shown = _accessor(doc, blob, anim["samplers"][ch["sampler"]]["output"])[:, 0]
        k = int(doc["nodes"][ch["target"]["node"]]["name"].split("_")[1])
        assert np.array_equal(shown, [1.0 if min(t, 2) == k else 0.0 for t in range(6)])
    assert "scale" not in doc["nodes"][nodes["frame_0"]] and doc["nodes"][nodes["frame_1"]]["scale"] == [0, 0, 0]


@pytest.mark.skipif(shutil.which("node") is None or not VALIDATOR.is_dir(),
                    reason="the Khronos glTF validator is not installed (.ci/run installs it with npm)")
def test_khronos_validator_finds_no_error(tmp_path, scene):
    frames = _frames(scene, 2)
    with GltfSplatWriter(tmp_path / "a.glb", scene, static=np.zeros(scene.count, bool), to_gltf=np.eye(3),
                         fps=30) as w:
        for f, (p, q) in enumerate(frames):
            w.write_frame(f, p, q)
    # The validator (2.0.0-dev.3.10) predates KHR_gaussian_splatting and reports its
    # attributes as invalid semantics; that one code is ignored, every other check stands.
    script = """
const v = require(process.argv[1]); const fs = require('fs');
v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[2])),
  {ignoredIssues: ['MESH_PRIMITIVE_INVALID_ATTRIBUTE', 'UNSUPPORTED_EXTENSION']})
 .then(r => console.log(JSON.stringify(r.issues)));"""
    out = subprocess.run(["node", "-e", script, str(VALIDATOR), str(tmp_path / "a.glb")], capture_output=True,
                         text=True, timeout=120, check=True)
    issues = json.loads(out.stdout)
    assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def test_format_lists_and_output_names(tmp_path):
    assert parse_formats("both,ply-seq") == ("both", ("ply-seq",))
    assert parse_formats("gltf") == (None, ("gltf",))
    for bad in ("", "usdz", "both,splat"):
        with pytest.raises(ValueError):
            parse_formats(bad)
    out = tmp_path / "a.usd"
    assert output_paths(out, "both", ("ply-seq", "spz-seq", "gltf")) == {
        "usd": out, "ply-seq": tmp_path / "a_ply", "spz-seq": tmp_path / "a_spz", "gltf": tmp_path / "a.glb"}
    assert output_paths(tmp_path / "f", None, ("ply-seq",)) == {"ply-seq": tmp_path / "f"}
    assert output_paths(tmp_path / "g.glb", None, ("gltf",)) == {"gltf": tmp_path / "g.glb"}
    for args in ((tmp_path / "a.txt", "both", ()), (tmp_path / "a.usd", None, ("gltf",)),
                 (tmp_path / "g", None, ("gltf",)), (tmp_path / "f.ply", None, ("ply-seq",))):
        with pytest.raises(OutputError):
            output_paths(*args)
