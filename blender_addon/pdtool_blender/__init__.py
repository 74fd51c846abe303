"""pdtool for Blender: pick a splat, place a static box and a force arrow, bake, import.

The add-on holds no physics: it spells a `pdtool bake` command line from the objects in
the scene (command.py), runs it in a separate process so that Blender stays responsive,
polls it from a bpy.app.timers callback (progress from pdtool's tqdm bar on stderr) and
imports the USD it writes with bpy.ops.wm.usd_import, or, where a Blender 3DGS add-on
that plays .ply sequences is installed (the 4DGS Viewer/Editor extension,
`bpy.ops.b4d.import_sequence`), also bakes a .ply sequence and loads it through that
add-on, so that the animation shows as splats rather than as coloured points.

Coordinates: pdtool works in the splat file's own units and axes ("scene units"). The
"Load preview" object shows the splat in those coordinates; the helpers (box, arrow,
sphere) are read in the preview object's local frame, so moving or scaling the preview
keeps everything consistent, and the baked result is placed with the preview's transform.
"""
from __future__ import annotations

import json
import os
import subprocess
import tempfile
import time
from pathlib import Path

import bpy
from mathutils import Matrix, Vector

from . import command, ply_points

bl_info = {
    "name": "pdtool",
    "author": "pdtool developers",
    "version": (0, 1, 0),
    "blender": (4, 2, 0),
    "location": "3D Viewport > Sidebar (N) > pdtool",
    "description": "Make a Gaussian splat move under a force (pdtool bake) and import the animated USD",
    "category": "Animation",
}

PRESETS = [("flower", "Flower", ""), ("leafy-plant", "Leafy plant", ""), ("fabric-hat", "Fabric hat", ""),
           ("rubber-cord", "Rubber cord", ""), ("jelly", "Jelly", "")]
QUALITIES = [("draft", "Draft", "Coarse grid, fastest"), ("default", "Default", ""),
             ("final", "Final", "Finest grid, slowest")]
POLL_S = 0.25  # timer interval while pdtool runs, seconds

_job: "BakeJob | None" = None  # one bake at a time


# ---------------------------------------------------------------- preferences, properties

class PDTOOL_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    pdtool_path: bpy.props.StringProperty(
        name="pdtool", subtype="FILE_PATH",
        description="The `pdtool` executable, or the Python interpreter of an environment with pdtool "
                    "installed (it runs `python -c \"from cli import main; main()\"`). Empty: `pdtool` on PATH")
    launcher_kind: bpy.props.EnumProperty(
        name="Kind", default="AUTO",
        items=[("AUTO", "Auto", "A file named python* is an interpreter, anything else the pdtool program"),
               ("PDTOOL", "pdtool executable", ""), ("PYTHON", "Python interpreter", "")])

    def draw(self, context):
        self.layout.prop(self, "pdtool_path")
        self.layout.prop(self, "launcher_kind")


def _prefs(context):
    addon = context.preferences.addons.get(__package__)
    return addon.preferences if addon is not None else None


def _is_empty(_self, obj):
    return obj.type == "EMPTY"


def _is_mesh(_self, obj):
    return obj.type == "MESH"


class PDTOOL_Settings(bpy.types.PropertyGroup):
    splat_path: bpy.props.StringProperty(name="Splat", subtype="FILE_PATH",
                                         description="3D Gaussian splat (.ply or .splat) to animate")
    splat_object: bpy.props.PointerProperty(
        name="Preview", type=bpy.types.Object,
        description="The splat preview; helpers are read in its local frame (the splat's scene units)")
    static_box: bpy.props.PointerProperty(name="Box", type=bpy.types.Object, poll=_is_mesh,
                                          description="Gaussians inside this object's bounds stay fixed")
    force_empty: bpy.props.PointerProperty(
        name="Arrow", type=bpy.types.Object, poll=_is_empty,
        description="Single-arrow Empty: its local +Z is the force direction, its drawn length the size")
    force_strength: bpy.props.FloatProperty(
        name="Strength", default=10.0, min=0.0, soft_max=1000.0,
        description="Acceleration (scene units/s^2) per scene unit of arrow length")
    region_empty: bpy.props.PointerProperty(
        name="Apply region", type=bpy.types.Object, poll=_is_empty,
        description="Sphere Empty: only Gaussians inside it are pushed. Empty: the whole free object")
    material_mode: bpy.props.EnumProperty(
        name="Material", items=[("PRESET", "Preset", "A shipped material preset"),
                                ("FILE", "Fitted", "A .pdmat written by `pdtool fit`")])
    preset: bpy.props.EnumProperty(name="Preset", items=PRESETS, default="flower")
    material_file: bpy.props.StringProperty(name="Material file", subtype="FILE_PATH")
    quality: bpy.props.EnumProperty(name="Quality", items=QUALITIES, default="default")
    seconds: bpy.props.FloatProperty(name="Seconds", default=2.0, min=0.01, soft_max=20.0, unit="TIME_ABSOLUTE")
    fps: bpy.props.IntProperty(name="FPS", default=30, min=1, max=240)
    import_as: bpy.props.EnumProperty(
        name="Import", default="AUTO",
        items=[("AUTO", "Auto", "Splats when a 3DGS sequence add-on is installed, else USD"),
               ("USD", "USD", "The animated USD through Blender's USD importer (coloured points)"),
               ("SPLATS", "Splats", "A .ply sequence through the 3DGS add-on (bpy.ops.b4d.import_sequence)")])
    output_dir: bpy.props.StringProperty(
        name="Output", subtype="DIR_PATH",
        description="Folder for the baked .usd. Empty: pdtool_bakes/ beside the .blend, or a temp folder")
    # state shown by the panel
    progress: bpy.props.FloatProperty(min=0.0, max=1.0, options={"SKIP_SAVE"})
    running: bpy.props.BoolProperty(options={"SKIP_SAVE"})
    status: bpy.props.StringProperty(options={"SKIP_SAVE"})
    last_error: bpy.props.StringProperty(options={"SKIP_SAVE"})
    last_usd: bpy.props.StringProperty(options={"SKIP_SAVE"})


# ---------------------------------------------------------------- scene objects -> numbers

def _to_scene(settings) -> Matrix:
    """World -> splat scene coordinates (the preview object's inverse transform)."""
    obj = settings.splat_object
    return obj.matrix_world.inverted() if obj is not None else Matrix.Identity(4)


def static_box(settings) -> tuple[float, ...] | None:
    """(x0, y0, z0, x1, y1, z1) of the box object's world bounds, in scene units."""
    obj = settings.static_box
    if obj is None:
        return None
    m = _to_scene(settings) @ obj.matrix_world
    pts = [m @ Vector(c) for c in obj.bound_box]
    return (*(min(p[i] for p in pts) for i in range(3)), *(max(p[i] for p in pts) for i in range(3)))


def force_vector(settings) -> tuple[float, float, float]:
    """The arrow's drawn vector (local +Z times display size) times strength, scene units/s^2."""
    obj = settings.force_empty
    if obj is None:
        raise ValueError("no force arrow: pick a single-arrow Empty under Force (or press Add helpers)")
    m = (_to_scene(settings) @ obj.matrix_world).to_3x3()
    v = m @ Vector((0.0, 0.0, obj.empty_display_size)) * settings.force_strength
    return (v.x, v.y, v.z)


def force_region(settings) -> tuple[tuple[float, float, float] | None, float | None]:
    """Centre and radius of the sphere Empty in scene units, or (None, None)."""
    obj = settings.region_empty
    if obj is None:
        return None, None
    m = _to_scene(settings) @ obj.matrix_world
    centre = m.translation
    radius = obj.empty_display_size * max(abs(s) for s in m.to_scale())
    return (centre.x, centre.y, centre.z), radius


def _output_path(settings, scene_path: Path) -> Path:
    if settings.output_dir:
        folder = Path(bpy.path.abspath(settings.output_dir))
    elif bpy.data.filepath:
        folder = Path(bpy.data.filepath).parent / "pdtool_bakes"
    else:
        folder = Path(tempfile.gettempdir()) / "pdtool_blender"
    folder.mkdir(parents=True, exist_ok=True)
    stem = f"{scene_path.stem}_{time.strftime('%Y%m%d-%H%M%S')}"
    out, i = folder / f"{stem}.usd", 1
    while out.exists():
        out, i = folder / f"{stem}_{i}.usd", i + 1
    return out


def sequence_importer_installed() -> bool:
    """Whether a 3DGS add-on that imports .ply sequences is enabled."""
    try:
        return "import_sequence" in dir(bpy.ops.b4d)
    except (AttributeError, KeyError, RuntimeError):
        return False


def wants_splats(settings) -> bool:
    """Whether the bake also writes a .ply sequence to load through the 3DGS add-on.
    Raises ValueError when the panel asks for splats and no such add-on is installed."""
    if settings.import_as == "USD":
        return False
    if sequence_importer_installed():
        return True
    if settings.import_as == "SPLATS":
        raise ValueError("no 3DGS sequence add-on is enabled (bpy.ops.b4d.import_sequence); install the 4DGS "
                         "Viewer/Editor extension, or set Import to USD")
    return False


def build_command(context) -> tuple[list[str], Path]:
    """argv of `pdtool bake` for the panel's settings, and the .usd it will write (with a
    .ply sequence beside it, command.sequence_folder, when wants_splats).

    Raises ValueError (command.LauncherError included) with one line the user can act on.
    """
    s = context.scene.pdtool
    if not s.splat_path:
        raise ValueError("no splat: pick a .ply or .splat file under Scene")
    scene_path = Path(bpy.path.abspath(s.splat_path))
    prefs = _prefs(context)
    prefix = command.launcher(prefs.pdtool_path if prefs else "", prefs.launcher_kind if prefs else "AUTO")
    at, radius = force_region(s)
    if s.material_mode == "FILE":
        if not s.material_file:
            raise ValueError("no material file: pick a .pdmat from `pdtool fit`, or use a preset")
        mat = dict(material=bpy.path.abspath(s.material_file))
    else:
        mat = dict(preset=s.preset)
    out = _output_path(s, scene_path)
    argv = command.bake_command(prefix, scene=scene_path, out=out, force=force_vector(s),
                                static_box=static_box(s), at=at, radius=radius, quality=s.quality,
                                seconds=s.seconds, fps=s.fps, formats="both,ply-seq" if wants_splats(s) else None,
                                **mat)
    return argv, out


# ---------------------------------------------------------------- the bake job

class BakeJob:
    """A running `pdtool bake`: stdout/stderr go to temp files (no pipe to fill and block)."""

    def __init__(self, argv: list[str], out: Path, scene_name: str, fps: int):
        self.argv, self.out, self.scene_name, self.fps = argv, out, scene_name, fps
        self._err = tempfile.TemporaryFile()
        self._out = tempfile.TemporaryFile()
        env = dict(os.environ)
        env.pop("PYTHONHOME", None)  # Blender's bundled Python must not leak into pdtool's
        env["PYTHONUNBUFFERED"] = "1"
        env["PDTOOL_PROGRESS"] = "1"  # pdtool draws its bar on a terminal only; the panel reads it from the file
        self.proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=self._out, stderr=self._err,
                                     cwd=str(out.parent), env=env)

    def stderr(self) -> str:
        self._err.seek(0)
        return self._err.read().decode("utf-8", "replace")

    def stdout(self) -> str:
        self._out.seek(0)
        return self._out.read().decode("utf-8", "replace")

    def poll(self) -> bool:
        """Update the scene's progress; True while pdtool still runs."""
        scene = bpy.data.scenes.get(self.scene_name)
        p = command.progress(self.stderr())
        if scene is not None and p is not None and p[1] > 0:
            scene.pdtool.progress = p[0] / p[1]
            scene.pdtool.status = f"baking: frame {p[0]} of {p[1]}"
        return self.proc.poll() is None

    def cancel(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def finish(self) -> tuple[str, str]:
        """Import on success. Returns (level, message): ('INFO', ...) or ('ERROR', pdtool's line)."""
        scene = bpy.data.scenes.get(self.scene_name)
        settings = scene.pdtool if scene is not None else None
        if settings is not None:
            settings.running = False
        rc = self.proc.returncode
        if rc != 0:
            line = command.error_line(self.stderr(), rc)
            if settings is not None:
                settings.last_error, settings.status, settings.progress = line, "bake failed", 0.0
            return "ERROR", line
        if scene is None:
            return "ERROR", "the scene that started the bake is gone; nothing imported"
        folder = command.sequence_folder(self.out)
        if folder.is_dir() and sequence_importer_installed():
            objs = import_sequence(scene, folder, self.fps)
        else:
            objs = import_bake(scene, self.out, self.fps)
        settings.progress, settings.last_error, settings.last_usd = 1.0, "", str(self.out)
        settings.status = f"imported frames {scene.frame_start}-{scene.frame_end} from {self.out.name}"
        return "INFO", f"pdtool: {settings.status} ({len(objs)} objects)"


def import_bake(scene, path: Path, fps: int) -> list:
    """Import a baked USD into `scene` at the preview's place; set fps and frame range."""
    before = set(bpy.data.objects)
    wm = bpy.context.window_manager
    window = next((w for w in wm.windows if w.scene == scene), None) if wm is not None else None
    override = dict(window=window, screen=window.screen) if window is not None else {}
    with bpy.context.temp_override(**override):
        # Scene units, not metres: the result lands on the preview and the helpers.
        bpy.ops.wm.usd_import(filepath=str(path), set_frame_range=True, apply_unit_conversion_scale=False,
                              create_collection=True)
    return _place(scene, [o for o in bpy.data.objects if o not in before], fps)


def import_sequence(scene, folder: Path, fps: int) -> list:
    """Load a baked .ply sequence through the 3DGS add-on, frames from 1, at the
    preview's place; set fps and frame range. The add-on converts the frames in the
    background and fills the object when it is done."""
    manifest = json.loads((folder / "sequence.json").read_text())
    up = command.UP_AXIS_4DGS.get(manifest.get("scene_up_axis"), "POS_Z")
    before = set(bpy.data.objects)
    bpy.ops.b4d.import_sequence(filepath=str(folder / manifest["files"][0]), fps=fps, start_frame=1, up_axis=up,
                                full_quality=True, setup_scene=False)
    scene.frame_start, scene.frame_end = 1, int(manifest["frames"])
    return _place(scene, [o for o in bpy.data.objects if o not in before], fps)


def _place(scene, new: list, fps: int) -> list:
    """Put newly imported objects where the preview is, set the fps and go to the first frame."""
    frame = scene.pdtool.splat_object
    if frame is not None:
        for o in new:
            if o.parent is None:
                o.matrix_world = frame.matrix_world @ o.matrix_world
    scene.render.fps, scene.render.fps_base = fps, 1.0
    scene.frame_set(scene.frame_start)
    return new


def _redraw() -> None:
    wm = bpy.context.window_manager
    for window in (wm.windows if wm is not None else []):
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _timer():
    """bpy.app.timers callback: poll pdtool, import when it ends. Returns the next interval."""
    global _job
    job = _job
    if job is None:
        return None
    if job.poll():
        _redraw()
        return POLL_S
    _job = None
    level, msg = job.finish()
    print(f"pdtool: {msg}")
    if level == "ERROR":
        wm = bpy.context.window_manager
        if wm is not None and wm.windows and not bpy.app.background:  # no UI to pop up in (crashes)
            wm.popup_menu(lambda menu, _c: menu.layout.label(text=msg), title="pdtool bake failed", icon="ERROR")
    _redraw()
    return None


# ---------------------------------------------------------------- operators

class PDTOOL_OT_load_preview(bpy.types.Operator):
    """Import the splat's Gaussian centres as a mesh of points coloured by the splat"""

    bl_idname = "pdtool.load_preview"
    bl_label = "Load preview"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        s = context.scene.pdtool
        path = Path(bpy.path.abspath(s.splat_path))
        try:
            pos, col = ply_points.read_points(path)
        except (OSError, ValueError) as e:
            self.report({"ERROR"}, str(e) if isinstance(e, ValueError) else f"{path}: {e.strerror}")
            return {"CANCELLED"}
        obj = make_preview(context, path.stem, pos, col)
        s.splat_object = obj
        self.report({"INFO"}, f"pdtool: {len(pos):,} points from {path.name}")
        return {"FINISHED"}


def _points_material() -> bpy.types.Material:
    mat = bpy.data.materials.get("pdtool preview")
    if mat is None:
        mat = bpy.data.materials.new("pdtool preview")
        if bpy.app.version < (5, 0, 0):  # 5.0+ always has nodes (use_nodes is deprecated)
            mat.use_nodes = True
        nodes = mat.node_tree.nodes
        attr = nodes.new("ShaderNodeAttribute")
        attr.attribute_name = "Col"
        bsdf = nodes.get("Principled BSDF")
        mat.node_tree.links.new(attr.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def _points_nodes(radius: float) -> bpy.types.NodeTree:
    """Geometry nodes: mesh vertices -> points with a radius and the preview material."""
    ng = bpy.data.node_groups.new("pdtool points", "GeometryNodeTree")
    ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    gin, gout = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    to_pts = ng.nodes.new("GeometryNodeMeshToPoints")
    to_pts.inputs["Radius"].default_value = radius
    set_mat = ng.nodes.new("GeometryNodeSetMaterial")
    set_mat.inputs["Material"].default_value = _points_material()
    ng.links.new(gin.outputs[0], to_pts.inputs["Mesh"])
    ng.links.new(to_pts.outputs["Points"], set_mat.inputs["Geometry"])
    ng.links.new(set_mat.outputs["Geometry"], gout.inputs[0])
    return ng


def make_preview(context, name: str, pos, col) -> bpy.types.Object:
    """A mesh of vertices [N,3] with a 'Col' point colour [N,4], shown as small points."""
    mesh = bpy.data.meshes.new(f"{name} preview")
    mesh.vertices.add(len(pos))
    mesh.vertices.foreach_set("co", pos.reshape(-1))
    attr = mesh.color_attributes.new("Col", "FLOAT_COLOR", "POINT")
    attr.data.foreach_set("color", col.reshape(-1))
    mesh.color_attributes.active_color = attr
    mesh.update()
    obj = bpy.data.objects.new(f"{name} preview", mesh)
    context.collection.objects.link(obj)
    size = float((pos.max(0) - pos.min(0)).max()) if len(pos) else 1.0
    mod = obj.modifiers.new("pdtool points", "NODES")
    mod.node_group = _points_nodes(0.004 * size)
    return obj


def _new_empty(context, name: str, kind: str, size: float, loc) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, None)
    obj.empty_display_type, obj.empty_display_size, obj.location = kind, size, loc
    context.collection.objects.link(obj)
    return obj


class PDTOOL_OT_add_helpers(bpy.types.Operator):
    """Add a static box under the preview, a force arrow and a sphere region at its top"""

    bl_idname = "pdtool.add_helpers"
    bl_label = "Add helpers"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        s = context.scene.pdtool
        if s.splat_object is not None:
            corners = [s.splat_object.matrix_world @ Vector(c) for c in s.splat_object.bound_box]
            lo = Vector([min(c[i] for c in corners) for i in range(3)])
            hi = Vector([max(c[i] for c in corners) for i in range(3)])
        else:
            lo, hi = Vector((-0.5, -0.5, 0.0)), Vector((0.5, 0.5, 1.0))
        size = max(hi - lo)
        pad = 0.05 * size
        z_top = lo.z + 0.2 * (hi.z - lo.z)  # the bottom fifth (a pot, a base) stays fixed
        verts = [(x, y, z) for x in (lo.x - pad, hi.x + pad) for y in (lo.y - pad, hi.y + pad)
                 for z in (lo.z - pad, z_top)]
        faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        mesh = bpy.data.meshes.new("pdtool static box")
        mesh.from_pydata(verts, [], faces)
        box = bpy.data.objects.new("pdtool static box", mesh)
        box.display_type = "WIRE"
        context.collection.objects.link(box)
        top = Vector(((lo.x + hi.x) / 2, (lo.y + hi.y) / 2, hi.z - 0.15 * (hi.z - lo.z)))
        arrow = _new_empty(context, "pdtool force", "SINGLE_ARROW", 0.5 * size, top)
        arrow.rotation_euler = (0.0, 1.5707963, 0.0)  # local +Z -> world +X: a sideways push
        sphere = _new_empty(context, "pdtool region", "SPHERE", 0.25 * size, top)
        s.static_box, s.force_empty, s.region_empty = box, arrow, sphere
        return {"FINISHED"}


class PDTOOL_OT_bake(bpy.types.Operator):
    """Run `pdtool bake` in the background and import the animated USD when it ends"""

    bl_idname = "pdtool.bake"
    bl_label = "Bake"
    bl_options = {"REGISTER"}

    wait: bpy.props.BoolProperty(
        name="Wait", default=False, options={"SKIP_SAVE", "HIDDEN"},
        description="Block until pdtool ends (scripts and tests); the panel's button does not wait")

    @classmethod
    def poll(cls, context):
        return _job is None

    def execute(self, context):
        global _job
        s = context.scene.pdtool
        try:
            argv, out = build_command(context)
        except ValueError as e:
            s.last_error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        try:
            job = BakeJob(argv, out, context.scene.name, s.fps)
        except OSError as e:
            s.last_error = f"cannot start pdtool ({argv[0]}): {e.strerror}; check Preferences > Add-ons > pdtool"
            self.report({"ERROR"}, s.last_error)
            return {"CANCELLED"}
        s.running, s.progress, s.last_error, s.status = True, 0.0, "", "starting pdtool"
        print("pdtool: " + subprocess.list2cmdline(argv))
        if not self.wait:
            _job = job
            bpy.app.timers.register(_timer, first_interval=POLL_S)
            return {"FINISHED"}
        while job.poll():  # the same polling the timer does, in a loop
            time.sleep(0.1)
        level, msg = job.finish()
        self.report({level}, msg)
        return {"FINISHED"} if level == "INFO" else {"CANCELLED"}


class PDTOOL_OT_cancel(bpy.types.Operator):
    """Stop the running bake; nothing is imported"""

    bl_idname = "pdtool.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        global _job
        if _job is not None:
            _job.cancel()
            _job = None
        s = context.scene.pdtool
        s.running, s.progress, s.status = False, 0.0, "cancelled"
        return {"FINISHED"}


# ---------------------------------------------------------------- panel

class PDTOOL_PT_panel(bpy.types.Panel):
    bl_label = "pdtool"
    bl_idname = "PDTOOL_PT_panel"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "pdtool"

    def draw(self, context):
        s = context.scene.pdtool
        layout = self.layout

        box = layout.box()
        box.label(text="Scene", icon="POINTCLOUD_DATA")
        box.prop(s, "splat_path")
        row = box.row()
        row.operator("pdtool.load_preview", icon="IMPORT")
        row.prop(s, "splat_object", text="")

        box = layout.box()
        box.label(text="Static region", icon="MESH_CUBE")
        box.prop(s, "static_box")
        bounds = static_box(s)
        if bounds is not None:
            box.label(text="fixed: " + " ".join(f"{v:.2f}" for v in bounds))

        box = layout.box()
        box.label(text="Force", icon="EMPTY_SINGLE_ARROW")
        box.prop(s, "force_empty")
        if s.force_empty is not None and s.force_empty.empty_display_type != "SINGLE_ARROW":
            box.label(text="show it as a Single Arrow to see the direction", icon="INFO")
        box.prop(s, "force_strength")
        if s.force_empty is not None:
            box.label(text="force: " + ", ".join(f"{v:.2f}" for v in force_vector(s)) + " units/s²")
        box.prop(s, "region_empty")
        box.operator("pdtool.add_helpers", icon="ADD")

        box = layout.box()
        box.label(text="Settings", icon="PREFERENCES")
        box.row().prop(s, "material_mode", expand=True)
        box.prop(s, "preset" if s.material_mode == "PRESET" else "material_file")
        box.prop(s, "quality")
        row = box.row()
        row.prop(s, "seconds")
        row.prop(s, "fps")
        box.prop(s, "output_dir")
        row = box.row()
        row.prop(s, "import_as", expand=True)
        if s.import_as != "USD" and not sequence_importer_installed():
            box.label(text="no 3DGS sequence add-on: importing USD" if s.import_as == "AUTO" else
                      "install a 3DGS sequence add-on, or import USD", icon="INFO")

        box = layout.box()
        box.label(text="Bake", icon="RENDER_ANIMATION")
        if s.running:
            box.progress(factor=s.progress, type="BAR", text=s.status or "baking")
            box.operator("pdtool.cancel", icon="CANCEL")
        else:
            box.operator("pdtool.bake", icon="PLAY")
            if s.status:
                box.label(text=s.status)
        if s.last_error:
            col = box.column()
            col.alert = True
            col.label(text=s.last_error, icon="ERROR")


CLASSES = (PDTOOL_AddonPreferences, PDTOOL_Settings, PDTOOL_OT_load_preview, PDTOOL_OT_add_helpers,
           PDTOOL_OT_bake, PDTOOL_OT_cancel, PDTOOL_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.pdtool = bpy.props.PointerProperty(type=PDTOOL_Settings)


def unregister():
    global _job
    if _job is not None:
        _job.cancel()
        _job = None
    if bpy.app.timers.is_registered(_timer):
        bpy.app.timers.unregister(_timer)
    del bpy.types.Scene.pdtool
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
