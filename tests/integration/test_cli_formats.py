"""`pdtool bake --format` with the splat formats, through the command line: one pass writes
the USD and every splat output, and each frame of each holds the same Gaussians where the
USD has them; bad format lists and names are one-line refusals."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from cli import main


def _run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


@pytest.fixture(scope="module")
def baked(tmp_path_factory):
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    d = tmp_path_factory.mktemp("formats")
    plant = save_splats(make_plant(1200, seed=1), d / "plant.ply")
    # -y up, as a COLMAP capture: the USD file is turned to Z-up, the .ply frames are not
    res = _run(["bake", "--scene", plant, "--preset", "jelly", "--force", "3,0,0", "--frames", "6",
                "--quality", "draft", "--up", "-y", "--device", "cpu", "--format", "both,ply-seq,spz-seq,gltf",
                d / "out.usd"])
    assert res.exit_code == 0, res.output
    return d, res.stdout


def test_one_bake_writes_every_format(baked):
    d, out = baked
    for line in ("wrote " + str(d / "out.usd"), f"wrote {d / 'out_ply'}/: ply-seq", f"wrote {d / 'out_spz'}/: spz-seq",
                 f"wrote {d / 'out.glb'}: gltf"):
        assert line in out, out
    assert len(list((d / "out_ply").glob("frame_*.ply"))) == 6
    assert len(list((d / "out_spz").glob("frame_*.spz"))) == 6
    assert json.loads((d / "out_ply" / "sequence.json").read_text())["scene_up_axis"] == "-y"


def test_ply_frames_move_as_the_usd(baked):
    from pxr import Usd

    from pd_tool.bake.baker import usd_frame
    from pd_tool.io import load_ply
    from usd_export import instance_positions

    d, _ = baked
    stage = Usd.Stage.Open(str(d / "out.usd"))
    R_usd, _ = usd_frame("-y")
    moved = 0.0
    rest = load_ply(d / "out_ply" / "frame_000000.ply").positions.numpy()
    for f in range(6):
        ply = load_ply(d / "out_ply" / f"frame_{f:06d}.ply").positions.numpy()
        _, usd = instance_positions(stage, f)
        assert np.abs(ply @ R_usd.T - usd).max() < 1e-4, f
        moved = max(moved, float(np.abs(ply - rest).max()))
    assert moved > 1e-3  # the frames differ: a sequence of the rest pose would pass the rest


def test_spz_and_gltf_frames_match_the_ply_frames(baked):
    gsply = pytest.importorskip("gsply", reason="the independent SPZ reader (pip install gsply) is not installed")
    from pd_tool.bake.outputs import gltf_axes
    from pd_tool.io import load_ply
    from _glb import accessor as _accessor, read_glb as _read_glb

    d, _ = baked
    doc, blob = _read_glb(d / "out.glb")
    meshes = {m["name"]: m["primitives"][0]["attributes"]["POSITION"] for m in doc["meshes"]}
    static_n = doc["accessors"][meshes["static"]]["count"] if "static" in meshes else 0
    R = gltf_axes("-y")
    for f in (0, 5):
        ply = load_ply(d / "out_ply" / f"frame_{f:06d}.ply").positions.numpy().astype(np.float64)
        spz = gsply.read_spz(d / "out_spz" / f"frame_{f:06d}.spz").means
        assert np.abs(spz - ply * [1, -1, -1]).max() < 2.5e-4
        if f"frame_{f}" in meshes:
            pts = _accessor(doc, blob, meshes[f"frame_{f}"])
            assert len(pts) + static_n == len(ply)
            # every glTF point is a .ply point turned to +Y up
            turned = ply @ R.T
            nearest = np.min(np.linalg.norm(pts[:, None, :] - turned[None, :, :], axis=2), axis=1)
            assert nearest.max() < 1e-4


@pytest.mark.parametrize("fmt,out,msg", [
    ("both,ply-seq", "out.txt", "must end in .usd"),
    ("gltf", "out.usd", "asks for no USD"),
    ("gltf", "out", "ending in .glb"),
    ("usdz", "out.usd", "unknown format 'usdz'"),
    ("both,instancer", "out.usd", "one USD content at most"),
])
def test_bad_formats_are_one_line(baked, fmt, out, msg):
    d, _ = baked
    res = _run(["bake", "--scene", d / "plant.ply", "--preset", "jelly", "--force", "1,0,0", "--format", fmt,
                d / out])
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and msg in lines[0], res.stderr


def _splat_prims_at(stage, frame: int):
    """Every ParticleField3DGaussianSplat prim's splats at `frame`, as one GaussianScene in
    the USD file's axes: what a renderer of the schema reads."""
    import torch
    from pxr import UsdVol

    from pd_tool.core.scene import GaussianScene

    parts = {k: [] for k in ("pos", "q", "s", "o", "sh")}
    for prim in stage.Traverse():
        if not prim.IsA(UsdVol.ParticleField3DGaussianSplat):
            continue
        f = UsdVol.ParticleField3DGaussianSplat(prim)
        pos = np.asarray(f.GetPositionsAttr().Get(frame), np.float32)
        q = np.asarray(f.GetOrientationshAttr().Get(frame), np.float32)[:, [3, 0, 1, 2]]  # xyzw -> wxyz
        degree = f.GetRadianceSphericalHarmonicsDegreeAttr().Get()
        sh = np.asarray(f.GetRadianceSphericalHarmonicsCoefficientsAttr().Get(), np.float32)
        parts["pos"].append(pos)
        parts["q"].append(q / np.linalg.norm(q, axis=1, keepdims=True))
        parts["s"].append(np.asarray(f.GetScalesAttr().Get(frame), np.float32))
        parts["o"].append(np.asarray(f.GetOpacitiesAttr().Get(), np.float32))
        parts["sh"].append(sh.reshape(len(pos), (degree + 1) ** 2, 3))
    t = {k: torch.as_tensor(np.concatenate(v)) for k, v in parts.items()}
    return GaussianScene(positions=t["pos"], quats=t["q"], scales=t["s"], opacities=t["o"], sh=t["sh"])


def test_the_native_splat_prim_animates_and_validates(baked):
    # UsdValidation passes on the time samples, and a renderer of the schema (pdtool's own
    # rasteriser, reading only the USD prims) draws two frames differently, each as the
    # bake's .ply frame of that time looks
    import torch
    from pxr import Usd

    from pd_tool.bake.baker import usd_frame
    from pd_tool.core.quaternion import matrix_to_quat, quat_multiply
    from pd_tool.io import load_ply
    from pd_tool.render.views import render_image, scene_camera
    from usd_export import validate_usd

    d, _ = baked
    validate_usd(d / "out.usd", usd_validators=True)  # raises on any error, every time sample checked
    stage = Usd.Stage.Open(str(d / "out.usd"))
    R_usd, _ = usd_frame("-y")
    images = {}
    for f in (0, 5):
        usd_scene = _splat_prims_at(stage, f)
        cam = scene_camera(_splat_prims_at(stage, 0), width=160, height=120, up_axis="+z")
        images[f] = render_image(usd_scene, cam).astype(float)
        ply = load_ply(d / "out_ply" / f"frame_{f:06d}.ply")
        ply.positions = ply.positions @ torch.as_tensor(R_usd.T, dtype=torch.float32)
        ply.quats = quat_multiply(matrix_to_quat(torch.as_tensor(R_usd)).float().expand(ply.count, 4), ply.quats)
        assert np.abs(render_image(ply, cam).astype(float) - images[f]).mean() < 1.0  # 8-bit levels
    assert np.abs(images[5] - images[0]).mean() > 1.0, np.abs(images[5] - images[0]).mean()


def test_outputs_beside_out_replace_only_pdtools_own(baked, tmp_path):
    d, _ = baked
    (tmp_path / "b.glb").write_text("my own model")  # beside b.usd, not named by the user
    args = ["bake", "--scene", d / "plant.ply", "--preset", "jelly", "--force", "1,0,0", "--frames", "2",
            "--quality", "draft", "--device", "cpu", "--format", "instancer,gltf", tmp_path / "b.usd"]
    res = _run(args)
    assert res.exit_code == 2 and "was not written by pdtool" in res.stderr
    assert (tmp_path / "b.glb").read_text() == "my own model" and not (tmp_path / "b.usd").exists()
    (tmp_path / "b.glb").unlink()
    assert _run(args).exit_code == 0
    assert _run(args).exit_code == 0  # its own .glb: replaced


def test_a_bake_stopped_midway_leaves_no_output_and_no_temporary(tmp_path):
    from pd_tool.bake import BakeSettings, ForceSpec, bake
    from pd_tool.io.synthetic import make_plant
    from pd_tool.materials.presets import Material

    def stop(done: int, total: int) -> None:
        if done == 2:
            raise KeyboardInterrupt  # Ctrl-C in the middle of the frames

    with pytest.raises(KeyboardInterrupt):
        bake(make_plant(600, seed=0), tmp_path / "s.usd", force=ForceSpec(accel=(2.0, 0.0, 0.0)),
             material=Material.from_preset("jelly"), progress=stop,
             settings=BakeSettings(seconds=0.2, quality="draft", fmt="both",
                                   splat_formats=("ply-seq", "spz-seq", "gltf")))
    assert list(tmp_path.iterdir()) == []
