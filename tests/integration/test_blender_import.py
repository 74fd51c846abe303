"""A real client: Blender (bpy 5.0.1) imports a baked file with bpy.ops.wm.usd_import.

Blender runs in a subprocess: bpy carries its own OpenUSD build, and loading it
into the pytest process next to usd-core (and torch/warp) is asking for symbol
clashes. The skip check therefore looks bpy up without importing it.
"""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.blender

if importlib.util.find_spec("bpy") is None:  # pytest.importorskip without the import
    pytest.skip("bpy (Blender as a Python module) is not installed: pip install bpy==5.0.1",
                allow_module_level=True)
pytest.importorskip("pxr")

from usd_export import UsdBakeWriter, instance_positions  # noqa: E402
from usd_export._geom import normalize_quats, srgb_to_linear  # noqa: E402

N = 240
START, FRAMES, HOLD_TO = 1, 8, 12
PROBE_FRAMES = (2, 7)  # two different frames with motion between them
POS_TOL = 1e-4  # scene units; the bar for positions after the round trip through Blender
QUAT_TOL = 3e-3  # quath storage (11-bit mantissa) plus Blender's float matrices

PROBE = textwrap.dedent('''
    import json, sys
    import bpy
    path, frames = sys.argv[1], [int(f) for f in sys.argv[2].split(",")]
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=path)
    sc = bpy.context.scene
    out = {"frame_range": [sc.frame_start, sc.frame_end], "objects": {}, "frames": {}}
    for o in bpy.data.objects:
        out["objects"][o.name] = {"type": o.type, "modifiers": [m.type for m in o.modifiers]}
    for f in frames:
        sc.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        by_prim = {"Instancer": {}, "StaticInstancer": {}}
        for oi in dg.object_instances:
            if oi.is_instance and oi.parent is not None and oi.parent.name in by_prim:
                m = oi.matrix_world
                by_prim[oi.parent.name][oi.persistent_id[1]] = (
                    list(m.translation), list(m.to_quaternion()), list(m.to_scale()))
        inst = by_prim["Instancer"]
        idx = sorted(inst)
        rec = {"instance_ids": idx,
               "positions": [inst[i][0] for i in idx],
               "quats_wxyz": [inst[i][1] for i in idx],
               "scales": [inst[i][2] for i in idx]}
        st = by_prim["StaticInstancer"]
        rec["static_instance_ids"] = sorted(st)
        rec["static_positions"] = [st[i][0] for i in sorted(st)]
        pts = bpy.data.objects["SplatColors"].evaluated_get(dg).data
        rec["points"] = [list(p.vector) for p in pts.attributes["position"].data]
        rec["point_attributes"] = sorted(a.name for a in pts.attributes)
        if "displayColor" in pts.attributes:
            rec["colors"] = [list(c.color)[:3] for c in pts.attributes["displayColor"].data]
        out["frames"][str(f)] = rec
    print("PROBE_JSON" + json.dumps(out))
''')


def _trajectories():
    """Points on circles about the z axis, each with its own radius, phase and spin."""
    rng = np.random.default_rng(3)
    centre = rng.uniform(-1, 1, (N, 3)).astype(np.float32)
    radius = rng.uniform(0.1, 0.5, N)
    phase = rng.uniform(0, 2 * np.pi, N)
    q0 = normalize_quats(rng.normal(size=(N, 4)).astype(np.float32))
    sig = rng.uniform(0.005, 0.02, (N, 3)).astype(np.float32)
    frames = []
    for f in range(FRAMES):
        a = phase + 0.4 * f
        pos = centre + np.stack([radius * np.cos(a), radius * np.sin(a), 0.05 * f * np.ones(N)],
                                1).astype(np.float32)
        frames.append((pos, q0, sig))
    colors = rng.uniform(0, 1, (N, 3)).astype(np.float32)
    return frames, colors


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    frames, colors = _trajectories()
    path = tmp_path_factory.mktemp("blender") / "bake.usd"
    # flush_bytes=1: an incremental crate save after every frame, the way a large
    # bake streams, so Blender reads a file that was appended to many times.
    with UsdBakeWriter(path, n_points=N, fps=30, start_frame=START, fmt="both",
                       colors=colors, opacities=np.full(N, 0.8, np.float32), flush_bytes=1) as w:
        for f, (pos, q, s) in enumerate(frames):
            w.write_frame(START + f, pos, q, s)
        w.hold_frames(HOLD_TO)
    return run_probe(path, PROBE_FRAMES), frames, colors


def run_probe(path: Path, frames) -> dict:
    """Import `path` into a fresh Blender (subprocess) and report what arrived."""
    proc = subprocess.run([sys.executable, "-c", PROBE, str(path), ",".join(map(str, frames))],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    line = next(l for l in proc.stdout.splitlines() if l.startswith("PROBE_JSON"))
    return json.loads(line[len("PROBE_JSON"):])


def test_frame_range(imported):
    out, _, _ = imported
    assert out["frame_range"] == [START, HOLD_TO]


def test_instancer_imported_as_instances(imported):
    out, _, _ = imported
    assert out["objects"]["Instancer"]["type"] == "POINTCLOUD"
    assert "NODES" in out["objects"]["Instancer"]["modifiers"]  # instance-on-points
    for f in PROBE_FRAMES:
        assert out["frames"][str(f)]["instance_ids"] == list(range(N))


@pytest.mark.parametrize("frame", PROBE_FRAMES)
def test_instance_transforms_equal_written_samples(imported, frame):
    out, frames, _ = imported
    pos, q, sig = frames[frame - START]
    rec = out["frames"][str(frame)]
    np.testing.assert_allclose(np.array(rec["positions"]), pos, rtol=0, atol=POS_TOL)
    got_q = np.array(rec["quats_wxyz"])
    dots = np.abs((got_q * q).sum(1))  # q and -q are the same rotation
    assert (dots > 1 - QUAT_TOL).all(), dots.min()
    np.testing.assert_allclose(np.array(rec["scales"]), 2.0 * sig, rtol=QUAT_TOL)
    # the companion point cloud follows the same trajectory
    np.testing.assert_allclose(np.array(rec["points"]), pos, rtol=0, atol=POS_TOL)


def test_frames_differ(imported):
    out, _, _ = imported
    a, b = (np.array(out["frames"][str(f)]["positions"]) for f in PROBE_FRAMES)
    assert np.abs(a - b).max() > 0.1


def test_per_splat_colours_reach_blender(imported):
    out, _, colors = imported
    rec = out["frames"][str(PROBE_FRAMES[0])]
    assert "displayColor" in rec["point_attributes"]
    # displayColor is linear: Blender's FLOAT_COLOR attribute holds the linearised sRGB
    np.testing.assert_allclose(np.array(rec["colors"]), srgb_to_linear(colors), rtol=0, atol=1e-6)


def test_pdtool_bake_output_imports(tmp_path):
    """End to end: a real `pd_tool.bake.baker` of the synthetic plant, imported into Blender."""
    from pxr import Usd, UsdGeom

    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material
    from pd_tool.io.synthetic import POT_TOP, make_plant

    scene = make_plant(1500, seed=0)
    out = tmp_path / "plant.usd"
    res = bake(scene, out, force=ForceSpec(accel=(0.0, 0.0, 1.0)),
               material=Material.from_preset("flower"),
               prepare_options=PrepareOptions(static_below=POT_TOP),
               settings=BakeSettings(seconds=0.2, fps=30, quality="draft", fmt="both",
                                     stop_at_rest=False))
    frames = tuple(range(res.frames))
    probe = run_probe(out, frames)
    assert probe["frame_range"] == [0, res.frames - 1]
    stage = Usd.Stage.Open(str(out))
    # the pinned pot is written once, in its own prim; the rest is sampled per frame
    moving = np.asarray(UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer")).GetIdsAttr().Get())
    static = np.asarray(UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/StaticInstancer")).GetIdsAttr().Get())
    assert len(static) > 0.1 * scene.count and len(moving) + len(static) == scene.count
    assert not stage.GetPrimAtPath("/Root/StaticInstancer").GetAttribute("positions").GetNumTimeSamples()
    written = {f: instance_positions(stage, f)[1] for f in frames}
    assert np.abs(written[frames[2]] - written[frames[-1]]).max() > 1e-4  # it moved
    # Blender converts to metres on import (apply_unit_conversion_scale): the bake's
    # metersPerUnit is the scene's scale, so world positions are samples * mpu.
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    assert mpu != 1.0  # the conversion is exercised, not trivially 1
    for f in frames:  # every frame, every instance, moving or pinned, by id
        rec = probe["frames"][str(f)]
        assert rec["instance_ids"] == list(range(len(moving)))
        assert rec["static_instance_ids"] == list(range(len(static)))
        got = np.zeros((scene.count, 3))
        got[moving] = rec["positions"]
        got[static] = rec["static_positions"]
        np.testing.assert_allclose(got, written[f] * mpu, rtol=0, atol=POS_TOL)
    colors = np.asarray(UsdGeom.Points(stage.GetPrimAtPath("/Root/SplatColors"))
                        .GetDisplayColorPrimvar().Get())
    np.testing.assert_allclose(np.array(probe["frames"][str(frames[0])]["colors"]), colors,
                               rtol=0, atol=1e-6)


# ---------------------------------------------------------------- colour, as Blender renders it

RENDER = textwrap.dedent('''
    import json, sys
    import bpy
    from mathutils import Matrix
    usd, cam_json, png = sys.argv[1:4]
    cam = json.loads(open(cam_json).read())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(filepath=usd)
    sc = bpy.context.scene
    sc.frame_set(sc.frame_start)
    # an emission material that shows the imported colour attribute as it is: no lights,
    # no shading, so the pixel is the attribute's (linear) value, display encoded
    mat = bpy.data.materials.new("displayColor")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_type, attr.attribute_name = "GEOMETRY", "displayColor"
    emit = nt.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(attr.outputs["Color"], emit.inputs["Color"])
    nt.links.new(emit.outputs["Emission"], out.inputs["Surface"])
    shown = []
    for o in bpy.data.objects:
        if o.name.endswith("SplatColors"):
            o.data.materials.clear()
            o.data.materials.append(mat)
            shown.append(o.name)
        else:  # the unit-sphere instances and their prototype carry no colour in Blender
            o.hide_render = True
    # pdtool's camera (OpenCV axes: x right, y down, z forward) as a Blender camera
    # (looking down -z, y up), same pinhole intrinsics
    cd = bpy.data.cameras.new("cam")
    w, h = cam["width"], cam["height"]
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.lens = cam["fx"] * 36.0 / w
    cd.shift_x = (w / 2 - cam["cx"]) / w
    cd.shift_y = (cam["cy"] - h / 2) / w
    cd.clip_start, cd.clip_end = 1e-3, 1e4
    co = bpy.data.objects.new("cam", cd)
    sc.collection.objects.link(co)
    flip = Matrix(((1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0), (0, 0, 0, 1)))
    co.matrix_world = Matrix(cam["camera_to_world"]) @ flip
    sc.camera = co
    r = sc.render
    r.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.cycles.samples = 8
    sc.cycles.use_denoising = False
    sc.cycles.filter_width = 0.01  # no pixel filter: interior pixels are one sphere's colour
    r.resolution_x, r.resolution_y, r.resolution_percentage = w, h, 100
    r.film_transparent = True
    r.dither_intensity = 0.0
    r.image_settings.file_format = "PNG"
    r.image_settings.color_mode = "RGBA"
    vs = sc.view_settings
    vs.view_transform, vs.look, vs.exposure, vs.gamma = "Standard", "None", 0.0, 1.0
    sc.display_settings.display_device = "sRGB"
    r.filepath = png
    bpy.ops.render.render(write_still=True)
    print("RENDER_JSON" + json.dumps({"shown": shown}))
''')

# Why 0.02 (5/255): both renders show the same per-splat sRGB colours, so their object
# means differ only through coverage (pdtool blends Gaussians, Blender shows the nearest
# 2-sigma sphere, so each pixel samples a slightly different mix of the +-0.04 colour
# jitter: under 0.01 on the mean), 8-bit/16-bit quantisation (0.002) and Cycles'
# sampling of the few pixels left at the alpha threshold. The bug this guards against,
# sRGB values read as linear, brightens these channels by 0.15 to 0.29.
COLOUR_TOL = 0.02
BASE_SRGB = np.array([0.7, 0.45, 0.25])


def test_blender_render_matches_pdtool_colours(tmp_path):
    """Blender renders the imported splats (Cycles, emission of displayColor, view
    transform Standard) with the colour pdtool's own renderer gives frame 0."""
    import torch
    from PIL import Image

    from pd_tool.core.cameras import auto_camera
    from pd_tool.render import render
    from usd_export._geom import rgb_to_sh_dc

    rng = np.random.default_rng(5)
    n = 600
    pos = (rng.normal(size=(n, 3)) * [0.5, 0.5, 0.15]).astype(np.float32)
    q = normalize_quats(rng.normal(size=(n, 4)).astype(np.float32))
    sig = rng.uniform(0.04, 0.07, (n, 3)).astype(np.float32)
    srgb = np.clip(BASE_SRGB + rng.uniform(-0.04, 0.04, (n, 3)), 0, 1).astype(np.float32)
    sh = rgb_to_sh_dc(srgb)[:, None, :]
    opac = np.ones(n, np.float32)
    path = tmp_path / "colour.usd"
    with UsdBakeWriter(path, n_points=n, fps=30, fmt="instancer", sh=sh, opacities=opac) as w:
        w.write_frame(0, pos, q, sig)
    cam = auto_camera(pos, 96, 72, up_axis="z", elevation_deg=60.0)

    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    with torch.no_grad():
        ours = render(t(pos), t(q), t(sig), t(opac), t(sh), cam, background=(1.0, 1.0, 1.0))
    ours_rgb = ours.rgb.clamp(0, 1).numpy()
    ours_mask = ours.alpha[..., 0].numpy() > 0.98

    cam_json = tmp_path / "cam.json"
    cam_json.write_text(json.dumps({"width": cam.width, "height": cam.height, "fx": cam.fx, "fy": cam.fy,
                                    "cx": cam.cx, "cy": cam.cy,
                                    "camera_to_world": cam.camera_to_world.tolist()}))
    png = tmp_path / "blender.png"
    proc = subprocess.run([sys.executable, "-c", RENDER, str(path), str(cam_json), str(png)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    shown = json.loads(next(l for l in proc.stdout.splitlines() if l.startswith("RENDER_JSON"))[11:])["shown"]
    assert shown, "no SplatColors point cloud arrived"
    img = np.asarray(Image.open(png))
    img = img.astype(np.float64) / np.iinfo(img.dtype).max
    assert img.shape == (cam.height, cam.width, 4)
    theirs_mask = img[..., 3] > 0.98
    # The same camera frames the same object: pdtool's opaque core (Gaussians) lies
    # inside Blender's silhouette (2-sigma spheres, larger), and the object pixels
    # compared are those both call opaque.
    both = ours_mask & theirs_mask
    assert both.sum() > 0.9 * ours_mask.sum() > 200, (ours_mask.sum(), theirs_mask.sum(), both.sum())
    ours_mean = ours_rgb[both].mean(0)
    theirs_mean = img[..., :3][both].mean(0)
    np.testing.assert_allclose(ours_mean, srgb.mean(0), atol=COLOUR_TOL)  # pdtool shows the sRGB colours
    np.testing.assert_allclose(theirs_mean, ours_mean, atol=COLOUR_TOL)
