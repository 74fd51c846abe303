"""The Blender add-on (blender_addon/pdtool_blender) in a real, headless Blender.

bpy 5.0.1 runs in a subprocess (as in test_blender_import.py: bpy's own OpenUSD next to
usd-core in one process is asking for symbol clashes). The add-on is installed the way a
user does it: `pd_tool.addon.zip_addon` -> Blender's extension install (4.2+), and
`install_addon` -> a legacy scripts/addons folder. The bake runs the real `pdtool`
program on the synthetic plant; the operator's `wait` option runs the same polling the
timer does, in a loop, because a headless bpy has no event loop to fire timers.
"""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from pd_tool.addon import ADDON_NAME, addon_source, install_addon, zip_addon

ROOT = Path(__file__).resolve().parents[2]
HAVE_BPY = importlib.util.find_spec("bpy") is not None  # looked up, not imported
needs_bpy = pytest.mark.skipif(not HAVE_BPY, reason="bpy (Blender as a Python module) not installed: "
                                                    "pip install bpy==5.0.1")
N_SPLATS = 600
FORCE_SIZE, FORCE_STRENGTH = 0.5, 8.0  # arrow display size (scene units) x strength -> 4 units/s^2 along +x
BOX = dict(location=(0.0, 0.0, 0.1), scale=(0.3, 0.3, 0.1))  # a +-1 cube -> bounds below
BOX_BOUNDS = (-0.3, -0.3, 0.0, 0.3, 0.3, 0.2)  # covers the pot (POT_TOP = 0.2)
SPHERE = dict(location=(0.0, 0.0, 0.7), size=0.1, scale=2.0)  # radius 0.2 about the top


def _load(name: str):
    """A bpy-free module of the add-on, loaded from its file (the package imports bpy)."""
    spec = importlib.util.spec_from_file_location(f"_addon_{name}", addon_source() / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


command = _load("command")
ply_points = _load("ply_points")

# Runs inside Blender. argv: zip, good splat, missing splat, corrupt splat, out dir.
SESSION = textwrap.dedent('''
    import json, math, os, sys, time
    import bpy, addon_utils
    zip_path, good, missing, corrupt, out_dir = sys.argv[1:6]
    pdtool_exe = os.path.join(os.path.dirname(sys.executable), "pdtool")
    rep = {}
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    module = "bl_ext.user_default.pdtool_blender"
    rep["enabled"] = [a.module for a in bpy.context.preferences.addons if "pdtool" in a.module]
    rep["registered"] = dict(scene_prop=hasattr(bpy.types.Scene, "pdtool"),
                             panel=hasattr(bpy.types, "PDTOOL_PT_panel"),
                             panel_space=getattr(getattr(bpy.types, "PDTOOL_PT_panel", None), "bl_space_type", None),
                             panel_region=getattr(getattr(bpy.types, "PDTOOL_PT_panel", None), "bl_region_type", None),
                             ops=[op for op in ("load_preview", "add_helpers", "bake", "cancel")
                                  if hasattr(bpy.ops.pdtool, op) and bpy.ops.pdtool.__getattr__(op).poll() is not None])
    prefs = bpy.context.preferences.addons[module].preferences
    sc = bpy.context.scene
    s = sc.pdtool
    s.output_dir = out_dir
    s.quality, s.seconds, s.fps = "draft", 0.3, 10

    def bake(timer=False):
        before = sorted(o.name for o in bpy.data.objects)
        try:
            res, err = sorted(bpy.ops.pdtool.bake(wait=not timer)), None
        except RuntimeError as e:  # an operator's ERROR report becomes this in scripts
            res, err = None, str(e)
        if timer:  # headless: no event loop, so call the timer callback the way Blender would
            mod = sys.modules[module]
            while (next_s := mod._timer()) is not None:
                time.sleep(next_s)
        new = sorted(set(o.name for o in bpy.data.objects) - set(before))
        return dict(result=res, exception=err, last_error=s.last_error, new_objects=new,
                    files=sorted(os.listdir(out_dir)))

    # 1. errors, before anything is in the scene: a Python interpreter as the launcher
    prefs.pdtool_path, prefs.launcher_kind = sys.executable, "AUTO"
    bpy.ops.pdtool.add_helpers()  # a force is needed before pdtool even starts
    s.splat_path = missing
    rep["missing"] = bake()
    prefs.pdtool_path = pdtool_exe  # the pdtool executable
    s.splat_path = corrupt
    rep["corrupt"] = bake(timer=True)  # started, then polled by the timer callback

    # 2. preview, helpers placed by hand
    s.splat_path = good
    bpy.ops.pdtool.load_preview()
    prev = s.splat_object
    me = prev.evaluated_get(bpy.context.evaluated_depsgraph_get()).original.data
    rep["preview"] = dict(name=prev.name, n=len(me.vertices),
                          co=[list(v.co) for v in me.vertices],
                          col=[list(c.color) for c in me.color_attributes["Col"].data],
                          modifiers=[m.type for m in prev.modifiers])
    mesh = bpy.data.meshes.new("box")
    mesh.from_pydata([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], [],
                     [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)])
    box = bpy.data.objects.new("my box", mesh)
    sc.collection.objects.link(box)
    box.location, box.scale = BOX["location"], BOX["scale"]
    s.static_box = box
    s.force_empty.empty_display_type = "SINGLE_ARROW"
    s.force_empty.empty_display_size = FORCE_SIZE
    s.force_empty.rotation_euler = (0.0, math.pi / 2, 0.0)  # local +z -> world +x
    s.force_strength = FORCE_STRENGTH
    s.region_empty.location = SPHERE["location"]
    s.region_empty.empty_display_size = SPHERE["size"]
    s.region_empty.scale = (SPHERE["scale"],) * 3
    bpy.context.view_layer.update()
    s.material_mode, s.preset = "PRESET", "flower"
    mod = sys.modules[module]
    rep["argv"] = mod.build_command(bpy.context)[0]

    # 3. the bake
    rep["good"] = bake()
    rep["usd"] = s.last_usd
    rep["frame_range"] = [sc.frame_start, sc.frame_end]
    rep["fps"] = sc.render.fps / sc.render.fps_base
    rep["objects"] = {o.name: dict(type=o.type, modifiers=[m.type for m in o.modifiers]) for o in bpy.data.objects}
    rep["frames"] = {}
    for f in (sc.frame_start, sc.frame_end):
        sc.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        per_prim = {}
        for name in ("Instancer", "StaticInstancer"):  # moving and pinned instances
            inst = {oi.persistent_id[1]: list(oi.matrix_world.translation) for oi in dg.object_instances
                    if oi.is_instance and oi.parent is not None and oi.parent.name == name}
            per_prim[name] = [inst[i] for i in sorted(inst)]
        rep["frames"][str(f)] = per_prim
    print("REPORT_JSON" + json.dumps(rep))
''')


def _blender(script: str, args: list[str], env_extra: dict[str, str], consts: dict | None = None) -> dict:
    consts_src = "".join(f"{k} = {v!r}\n" for k, v in (consts or {}).items())
    env = {**os.environ, **env_extra}
    proc = subprocess.run([sys.executable, "-c", consts_src + script, *args], capture_output=True, text=True,
                          timeout=600, env=env)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    line = next(l for l in proc.stdout.splitlines() if l.startswith("REPORT_JSON"))
    return json.loads(line[len("REPORT_JSON"):])


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    d = tmp_path_factory.mktemp("addon")
    scene = make_plant(N_SPLATS, seed=0)
    return save_splats(scene, d / "plant.ply"), scene


@pytest.fixture(scope="module")
def session(plant, tmp_path_factory):
    """One Blender session: install, two failing bakes, preview, a real bake, probes."""
    d = tmp_path_factory.mktemp("blender_session")
    ply, _ = plant
    corrupt = d / "corrupt.ply"
    corrupt.write_bytes(b"not a splat\n")
    zip_path = zip_addon(d / "pdtool_blender.zip")
    (d / "out").mkdir()
    rep = _blender(SESSION, [str(zip_path), str(ply), str(d / "missing.ply"), str(corrupt), str(d / "out")],
                   {"BLENDER_USER_RESOURCES": str(d / "user")},  # the install stays in tmp
                   dict(FORCE_SIZE=FORCE_SIZE, FORCE_STRENGTH=FORCE_STRENGTH, BOX=BOX, SPHERE=SPHERE))
    return rep, d


# ------------------------------------------------------------- in Blender

@needs_bpy
def test_extension_installs_and_registers(session):
    rep, _ = session
    assert rep["enabled"] == ["bl_ext.user_default.pdtool_blender"]
    reg = rep["registered"]
    assert reg["scene_prop"] and reg["panel"]
    assert (reg["panel_space"], reg["panel_region"]) == ("VIEW_3D", "UI")  # the 3D view sidebar
    assert reg["ops"] == ["load_preview", "add_helpers", "bake", "cancel"]


@needs_bpy
def test_command_line_from_scene_objects(session, plant):
    rep, _ = session
    argv = rep["argv"]
    assert argv[1:3] == ["bake", "--scene"] and argv[3] == str(plant[0])

    def vec(flag):
        return np.array([float(v) for v in argv[argv.index(flag) + 1].split(",")])

    np.testing.assert_allclose(vec("--force"), [FORCE_SIZE * FORCE_STRENGTH, 0, 0], atol=1e-5)
    np.testing.assert_allclose(vec("--static-box"), BOX_BOUNDS, atol=1e-5)
    np.testing.assert_allclose(vec("--at"), SPHERE["location"], atol=1e-5)
    assert float(argv[argv.index("--radius") + 1]) == pytest.approx(SPHERE["size"] * SPHERE["scale"])
    for flag, val in (("--preset", "flower"), ("--quality", "draft"), ("--seconds", "0.3"), ("--fps", "10")):
        assert argv[argv.index(flag) + 1] == val
    assert argv[-1].endswith(".usd")


def _by_id(usd: str, per_prim: dict) -> np.ndarray:
    """Blender's instance positions of each instancer prim, put back in the bake's Gaussian
    order through the prims' USD ids (Blender numbers each prim's instances from 0)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(usd)
    out = np.full((N_SPLATS, 3), np.nan)
    for name, pos in per_prim.items():
        prim = stage.GetPrimAtPath(f"/Root/{name}")
        if not prim.IsValid():
            assert not pos, name
            continue
        out[np.asarray(UsdGeom.PointInstancer(prim).GetIdsAttr().Get())] = np.asarray(pos).reshape(-1, 3)
    return out


@needs_bpy
def test_bake_imports_animated_instancer(session, plant):
    rep, _ = session
    _, scene = plant
    good = rep["good"]
    assert good["result"] == ["FINISHED"] and good["exception"] is None and good["last_error"] == ""
    assert Path(rep["usd"]).is_file()
    objs = rep["objects"]
    assert objs["Instancer"]["type"] == "POINTCLOUD" and "NODES" in objs["Instancer"]["modifiers"]
    assert {"Instancer", "SplatColors"} <= set(good["new_objects"])
    # 0.3 s at 10 fps: frames 0..3, and the scene's frame rate follows the bake
    assert rep["frame_range"] == [0, 3] and rep["fps"] == 10
    f0, f1 = (_by_id(rep["usd"], rep["frames"][str(f)]) for f in rep["frame_range"])
    assert f0.shape == f1.shape == (N_SPLATS, 3)
    # imported in scene units on the preview: frame 0 is the splat at rest
    np.testing.assert_allclose(f0, scene.positions.numpy(), atol=1e-4)
    moved = np.linalg.norm(f1 - f0, axis=1)
    assert moved.max() > 1e-3  # it moves between two frames
    lo, hi = np.array(BOX_BOUNDS[:3]), np.array(BOX_BOUNDS[3:])
    in_box = ((f0 >= lo) & (f0 <= hi)).all(1)
    # the static box holds; Gaussians near its top follow free driver particles a little
    deep = in_box & (f0[:, 2] < BOX_BOUNDS[5] - 0.1)
    assert deep.sum() > 20 and moved[deep].max() < 1e-5
    assert moved[in_box].max() < 0.05 * moved[~in_box].max()
    push = f1[~in_box, 0] - f0[~in_box, 0]
    assert push.mean() > 0  # the arrow points along +x


@needs_bpy
@pytest.mark.parametrize("case", ["missing", "corrupt"])
def test_bad_splat_reports_pdtool_error_and_imports_nothing(session, case):
    rep, d = session
    r = rep[case]
    expected = {
        "missing": f"Error: Invalid value for '--scene': File '{d / 'missing.ply'}' does not exist.",
        "corrupt": f"Error: {d / 'corrupt.ply'}: not a PLY file (it does not start with 'ply'); "
                   "pass a 3DGS .ply or .splat file",
    }[case]
    assert r["last_error"] == expected  # pdtool's own line, as printed
    if case == "missing":  # waited for: the operator itself reports ERROR with pdtool's line
        assert r["result"] is None and expected in r["exception"]
    else:  # started, polled by the timer callback: the line lands in the panel (and a popup in a GUI)
        assert r["result"] == ["FINISHED"] and r["exception"] is None
    assert r["new_objects"] == []
    assert r["files"] == []  # and no half-written output


@needs_bpy
def test_preview_points_match_the_splat(session, plant):
    rep, _ = session
    _, scene = plant
    prev = rep["preview"]
    assert prev["n"] == N_SPLATS and prev["modifiers"] == ["NODES"]
    np.testing.assert_allclose(np.array(prev["co"]), scene.positions.numpy(), atol=1e-6)
    rgb = np.clip(0.5 + 0.28209479 * scene.sh[:, 0].numpy(), 0, 1)
    np.testing.assert_allclose(np.array(prev["col"])[:, :3], rgb, atol=1e-5)
    np.testing.assert_allclose(np.array(prev["col"])[:, 3], scene.opacities.numpy(), atol=1e-5)


LEGACY = textwrap.dedent('''
    import json, bpy, addon_utils
    bpy.ops.wm.read_factory_settings(use_empty=True)
    mod = addon_utils.enable("pdtool_blender", default_set=True)
    rep = dict(file=mod.__file__, version=list(mod.bl_info["version"]),
               on=hasattr(bpy.types.Scene, "pdtool") and hasattr(bpy.types, "PDTOOL_PT_panel"),
               prefs=bpy.context.preferences.addons["pdtool_blender"].preferences.bl_rna.identifier)
    addon_utils.disable("pdtool_blender", default_set=True)
    rep["off"] = not hasattr(bpy.types.Scene, "pdtool") and not hasattr(bpy.types, "PDTOOL_PT_panel")
    print("REPORT_JSON" + json.dumps(rep))
''')


@needs_bpy
def test_legacy_install_enables_and_disables(tmp_path):
    """`pdtool blender-addon --install-to` into a scripts/addons folder (bl_info add-on)."""
    target = install_addon(tmp_path / "scripts" / "addons")
    rep = _blender(LEGACY, [], {"BLENDER_USER_SCRIPTS": str(tmp_path / "scripts"),
                                "BLENDER_USER_RESOURCES": str(tmp_path / "user")})
    assert Path(rep["file"]) == target / "__init__.py"
    assert rep["on"] and rep["off"] and rep["prefs"] == "PDTOOL_AddonPreferences"


# ------------------------------------------------------------- without Blender

def test_cli_packages_addon(tmp_path):
    """`pdtool blender-addon`, run through the add-on's own python -c shim."""
    out = tmp_path / "a.zip"
    argv = command.launcher(sys.executable, "AUTO") + ["blender-addon", "--zip", str(out),
                                                         "--install-to", str(tmp_path / "addons")]
    proc = subprocess.run(argv, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert proc.returncode == 0, proc.stderr
    import zipfile

    names = zipfile.ZipFile(out).namelist()
    assert f"{ADDON_NAME}/blender_manifest.toml" in names and f"{ADDON_NAME}/__init__.py" in names
    assert not any("__pycache__" in n for n in names)
    assert (tmp_path / "addons" / ADDON_NAME / "command.py").is_file()
    bad = subprocess.run(argv[:-4] + ["--zip", str(tmp_path / "a.tar")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert command.error_line(bad.stderr, 2) == f"Error: --zip {tmp_path / 'a.tar'}: the file name must end in .zip"


def test_launcher_kinds(tmp_path):
    exe = tmp_path / "pdtool"
    exe.write_text("#!/bin/sh\n")
    py = tmp_path / "python3.11"
    py.write_text("")
    assert command.launcher(str(exe)) == [str(exe)]
    assert command.launcher(str(py)) == [str(py), "-c", command.PYTHON_SHIM]
    assert command.launcher(str(exe), "PYTHON")[1:] == ["-c", command.PYTHON_SHIM]
    with pytest.raises(command.LauncherError, match="is not a file"):
        command.launcher(str(tmp_path / "nope"))


def test_error_line_and_progress_parsing():
    click_usage = ("Usage: pdtool bake [OPTIONS] OUT\nTry 'pdtool bake --help' for help.\n\n"
                   "Error: Invalid value for '--scene': File 'x.ply' does not exist.\n")
    assert command.error_line(click_usage, 2) == "Error: Invalid value for '--scene': File 'x.ply' does not exist."
    tqdm = ("bake:   0%|          | 0/4 [00:00<?, ?frame/s]\rbake:  50%|█████     | 2/4 [00:03<00:02,  1.4s/frame]"
            "\rbake:  50%|█████     | 2/4 [00:03<00:02,  1.4s/frame]\nError: simulation unstable at frame 2; lower --force\n")
    assert command.progress(tqdm) == (2, 4)
    assert command.error_line(tqdm, 2) == "Error: simulation unstable at frame 2; lower --force"
    assert command.progress("") is None
    assert command.error_line("", 1) == "pdtool exited with code 1 and printed nothing"
    assert command.error_line("Traceback ...\nKeyError: 'x'\n", 1) == "KeyError: 'x'"


def test_point_reader_matches_pdtool_loader(shared_data):
    """The add-on's minimal .ply reader against pdtool's loader on a real SH3 capture."""
    from pd_tool.io import load_splats

    s = load_splats(shared_data / "udon.ply")
    pos, col = ply_points.read_points(shared_data / "udon.ply")
    np.testing.assert_array_equal(pos, s.positions.numpy())
    np.testing.assert_allclose(col[:, :3], np.clip(0.5 + 0.28209479 * s.sh[:, 0].numpy(), 0, 1), atol=1e-5)
    np.testing.assert_allclose(col[:, 3], s.opacities.numpy(), atol=1e-5)


def test_point_reader_ascii_and_errors(tmp_path):
    p = tmp_path / "a.ply"
    p.write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                 "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 0\n"
                 "property list uchar int vertex_indices\nend_header\n0 1 2 255 0 0\n3 4 5 0 255 0\n")
    pos, col = ply_points.read_points(p)
    np.testing.assert_array_equal(pos, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(col, [[1, 0, 0, 1], [0, 1, 0, 1]])
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
                  b"property float z\nend_header\n" + b"\0" * 20)
    with pytest.raises(ValueError, match="truncated"):
        ply_points.read_points(p)
    p.write_bytes(b"PK\x03\x04")
    with pytest.raises(ValueError, match="not a PLY file"):
        ply_points.read_points(p)
