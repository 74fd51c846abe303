"""docs/blender_panel.png: the add-on's panel after a real bake, next to a render of the result.

A bpy from PyPI always runs in background mode: there is no window, so Blender cannot
screenshot its own UI. This script therefore
1. installs the add-on zip into a temporary Blender user folder, loads the synthetic
   plant's preview, adds the helpers and bakes with the panel's operator (no `wait`:
   the bake runs out of process and is driven by calling the add-on's timer callback,
   the function bpy.app.timers would call);
2. records the panel's own draw() calls (PDTOOL_PT_panel.draw with a recording layout)
   once while pdtool runs (progress bar) and once after the import;
3. renders the scene with Blender's Workbench engine (bpy.ops.render.render) at the
   last baked frame: baked points coloured by the splat, wire proxies for the static
   box, the force arrow and the region sphere (empties do not render);
4. draws the recorded layout with Pillow in Blender's dark-theme colours (Blender's own
   Inter font; icons left out) and puts it beside the render like a 3D view sidebar.

    python blender_addon/panel_screenshot.py --out docs/blender_panel.png
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make_plant(path: Path, n: int) -> None:
    # torch in its own process: bpy and torch/usd-core do not share one process here
    code = ("import sys; from pd_tool.io.synthetic import make_plant; from pd_tool.io import save_splats; "
            f"save_splats(make_plant({n}, seed=0, thin=False), sys.argv[1])")
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)


def zip_addon(path: Path) -> None:
    code = "import sys; from pd_tool.addon import zip_addon; zip_addon(sys.argv[1])"
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)


# ------------------------------------------------------------------ recording layout

class Rec:
    """Stands in for bpy.types.UILayout and records what draw() asks for."""

    def __init__(self, kind: str = "layout"):
        self.kind, self.items, self.alert, self.use_property_split, self.enabled = kind, [], False, False, True

    def _child(self, kind):
        r = Rec(kind)
        r.alert = self.alert
        self.items.append(r)
        return r

    def box(self):
        return self._child("box")

    def row(self, **_kw):
        return self._child("row")

    def column(self, **_kw):
        return self._child("column")

    def separator(self, **_kw):
        self.items.append({"type": "separator"})

    def label(self, text="", icon="NONE", **_kw):
        self.items.append({"type": "label", "text": text, "alert": self.alert})

    def progress(self, factor=0.0, type="BAR", text=""):
        self.items.append({"type": "progress", "factor": factor, "text": text})

    def operator(self, idname, text=None, icon="NONE", **_kw):
        import bpy

        mod, name = idname.split(".")
        label = text if text is not None else getattr(bpy.ops, mod).__getattr__(name).get_rna_type().name
        enabled = getattr(bpy.ops, mod).__getattr__(name).poll()
        self.items.append({"type": "operator", "text": label, "enabled": enabled})

    def prop(self, data, name, text=None, expand=False, **_kw):
        p = data.bl_rna.properties[name]
        label = p.name if text is None else text
        value = getattr(data, name)
        item = {"type": "prop", "label": label, "rna": p.type, "subtype": getattr(p, "subtype", "")}
        if p.type == "ENUM":
            items = [(e.identifier, e.name) for e in p.enum_items]
            item.update(choices=[n for _, n in items], value=dict(items)[value], expand=expand)
        elif p.type == "POINTER":
            item["value"] = value.name if value is not None else ""
        elif p.type == "FLOAT":
            item["value"] = f"{value:.2f}" + (" s" if p.unit == "TIME_ABSOLUTE" else "")
        else:
            item["value"] = str(value)
        self.items.append(item)

    def to_json(self):
        return {"type": self.kind, "items": [i.to_json() if isinstance(i, Rec) else i for i in self.items]}


def record_panel(panel_cls, context) -> dict:
    rec = Rec()

    class Self:
        layout = rec

    panel_cls.draw(Self(), context)
    return rec.to_json()


# ------------------------------------------------------------------ Blender part

def blender_session(splat: Path, zip_path: Path, out_dir: Path, render_png: Path) -> dict:
    import bpy
    from mathutils import Matrix, Vector

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default", enable_on_install=True)
    module = "bl_ext.user_default.pdtool_blender"
    addon = sys.modules[module]
    prefs = bpy.context.preferences.addons[module].preferences
    prefs.pdtool_path = str(Path(sys.executable).with_name("pdtool"))
    sc = bpy.context.scene
    s = sc.pdtool
    s.splat_path = str(splat)
    bpy.ops.pdtool.load_preview()
    bpy.ops.pdtool.add_helpers()
    s.force_strength = 8.0
    s.quality, s.seconds, s.fps = "draft", 0.5, 24
    s.output_dir = str(out_dir)
    bpy.ops.pdtool.bake()  # starts pdtool, registers the timer, returns at once
    running = None
    while True:  # what bpy.app.timers does in a GUI Blender
        next_s = addon._timer()
        if next_s is None:
            break
        if running is None and s.running and s.progress >= 0.5:
            running = record_panel(addon.PDTOOL_PT_panel, bpy.context)
        time.sleep(next_s)
    if s.last_error:
        raise SystemExit(f"bake failed: {s.last_error}")
    done = record_panel(addon.PDTOOL_PT_panel, bpy.context)

    # render the result at its last frame
    sc.frame_set(sc.frame_end)
    s.splat_object.hide_render = True  # the rest pose; show the baked points
    for name in ("Instancer", "StaticInstancer"):  # moving and pinned instances
        inst = bpy.data.objects.get(name)
        if inst is not None:
            inst.hide_render = True  # the unit-sphere instances hide the colours (they are on *SplatColors)
    point_sets = [bpy.data.objects[n] for n in ("SplatColors", "StaticSplatColors") if n in bpy.data.objects]
    for a in ("pdtool static box",):
        o = bpy.data.objects[a]
        o.modifiers.new("wire", "WIREFRAME").thickness = 0.006
    mat_helper = bpy.data.materials.new("helper")
    mat_helper.diffuse_color = (0.95, 0.55, 0.1, 1.0)
    if bpy.app.version < (5, 0, 0):
        mat_helper.use_nodes = True
    mat_helper.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (0.95, 0.45, 0.05, 1.0)
    arrow, sphere = s.force_empty, s.region_empty
    # wire proxies for the empties, drawn where the empties are
    bpy.ops.mesh.primitive_cylinder_add(radius=0.008, depth=arrow.empty_display_size * 0.85)
    shaft = bpy.context.object
    shaft.matrix_world = arrow.matrix_world @ Matrix.Translation(
        (0, 0, arrow.empty_display_size * 0.425))
    bpy.ops.mesh.primitive_cone_add(radius1=0.03, depth=arrow.empty_display_size * 0.15)
    head = bpy.context.object
    head.matrix_world = arrow.matrix_world @ Matrix.Translation(
        (0, 0, arrow.empty_display_size * 0.925))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=sphere.empty_display_size, location=sphere.location,
                                         segments=24, ring_count=12)
    ball = bpy.context.object
    ball.modifiers.new("wire", "WIREFRAME").thickness = 0.003
    for o in (shaft, head, ball, bpy.data.objects["pdtool static box"]):
        o.data.materials.append(mat_helper)
    # the baked points as small spheres coloured by displayColor (a geometry-nodes material)
    mat_pts = bpy.data.materials.new("splat colours")
    if bpy.app.version < (5, 0, 0):
        mat_pts.use_nodes = True
    attr = mat_pts.node_tree.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = "displayColor"
    mat_pts.node_tree.links.new(attr.outputs["Color"], mat_pts.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    for pts in point_sets:
        pts.data.materials.append(mat_pts)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.location = (1.55, -1.75, 1.05)
    direction = Vector((0.0, 0.0, 0.42)) - cam.location
    cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    cam.data.lens = 40
    sc.render.engine = "BLENDER_EEVEE"  # reads the colour attribute through the material nodes
    sc.eevee.taa_render_samples = 16
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (0.7, 0.2, 0.8)
    sc.collection.objects.link(sun)
    sc.world = bpy.data.worlds.new("w")
    sc.world.color = (0.2, 0.2, 0.2)
    sc.view_settings.view_transform = "Standard"
    sc.render.resolution_x, sc.render.resolution_y = 820, 1180
    sc.render.film_transparent = False
    sc.render.filepath = str(render_png)
    bpy.ops.render.render(write_still=True)
    return {"running": running, "done": done, "frames": [sc.frame_start, sc.frame_end], "usd": s.last_usd,
            "fps": sc.render.fps}


# ------------------------------------------------------------------ drawing

THEME = dict(bg=(48, 48, 48), header=(40, 40, 40), box=(38, 38, 38), box_edge=(58, 58, 58),
             text=(230, 230, 230), dim=(160, 160, 160), field=(29, 29, 29), button=(84, 84, 84),
             select=(71, 114, 179), alert=(230, 80, 70), progress=(71, 114, 179), tab=(56, 56, 56))


def draw_panel(tree: dict, width: int, font_path: Path, scale: float = 2.0):
    from PIL import Image, ImageDraw, ImageFont

    px = lambda v: int(round(v * scale))  # noqa: E731
    font = ImageFont.truetype(str(font_path), px(11))
    bold = ImageFont.truetype(str(font_path), px(11))
    row_h, gap, pad = px(20), px(2), px(6)
    img = Image.new("RGB", (width, px(900)), THEME["bg"])
    d = ImageDraw.Draw(img)

    def text(x, y, s, fill=THEME["text"], anchor="lm", f=font):
        d.text((x, y), s, fill=fill, font=f, anchor=anchor)

    def fit(s, w):
        while s and d.textlength(s, font=font) > w - px(8):
            s = s[:-2] + "…" if not s.endswith("…") else s[:-2] + "…"
        return s

    def widget(x, y, w, item):
        t = item["type"]
        mid = y + row_h // 2
        if t == "label":
            text(x + px(2), mid, fit(item["text"], w), THEME["alert"] if item.get("alert") else THEME["text"])
        elif t == "operator":
            d.rounded_rectangle([x, y, x + w, y + row_h], px(4), fill=THEME["button"])
            text(x + w // 2, mid, item["text"], THEME["text"] if item["enabled"] else THEME["dim"], "mm")
        elif t == "progress":
            d.rounded_rectangle([x, y, x + w, y + row_h], px(4), fill=THEME["field"])
            d.rounded_rectangle([x, y, x + max(px(8), int(w * item["factor"])), y + row_h], px(4),
                                fill=THEME["progress"])
            text(x + w // 2, mid, item["text"], anchor="mm")
        elif t == "prop":
            rna = item["rna"]
            if rna == "ENUM" and item["expand"]:
                n = len(item["choices"])
                for k, name in enumerate(item["choices"]):
                    x0, x1 = x + w * k // n, x + w * (k + 1) // n
                    d.rectangle([x0, y, x1 - 1, y + row_h], fill=THEME["select"] if name == item["value"]
                                else THEME["button"])
                    text((x0 + x1) // 2, mid, name, anchor="mm")
            elif rna in ("FLOAT", "INT"):
                d.rounded_rectangle([x, y, x + w, y + row_h], px(4), fill=THEME["button"])
                text(x + px(8), mid, item["label"])
                text(x + w - px(8), mid, item["value"], anchor="rm")
            else:
                split = x + int(w * 0.38)
                if item["label"]:
                    text(x + px(2), mid, fit(item["label"], split - x))
                else:
                    split = x
                fill = THEME["button"] if rna == "ENUM" else THEME["field"]
                d.rounded_rectangle([split, y, x + w, y + row_h], px(4), fill=fill)
                value = item["value"] or ""
                text(split + px(6), mid, fit(value, x + w - split - px(4)), THEME["text"] if value else THEME["dim"])
                if rna == "ENUM":
                    text(x + w - px(8), mid, "⌄", THEME["dim"], "rm")
        return row_h

    def layout(node, x, y, w):
        """Lays out a container; returns its height."""
        if node["type"] == "row":
            items = node["items"]
            n = max(1, len(items))
            h = 0
            for k, it in enumerate(items):
                x0 = x + (w + gap) * k // n
                x1 = x + (w + gap) * (k + 1) // n - gap
                h = max(h, block(it, x0, y, x1 - x0))
            return h
        h = 0
        inner = node["type"] == "box"
        if inner:
            x, w = x + pad, w - 2 * pad
            h += pad
        for it in node["items"]:
            h += block(it, x, y + h, w) + gap
        return h + (pad if inner else 0)

    def block(it, x, y, w):
        if it["type"] in ("row", "column", "box", "layout"):
            if it["type"] == "box":
                hh = layout(it, x, y, w)  # measure, then draw the box under and redraw on top
                d.rounded_rectangle([x, y, x + w, y + hh], px(5), fill=THEME["box"], outline=THEME["box_edge"])
                layout(it, x, y, w)
                return hh
            return layout(it, x, y, w)
        return widget(x, y, w, it)

    # panel header, like Blender's collapsible panel title
    d.rectangle([0, 0, width, px(26)], fill=THEME["header"])
    text(px(10), px(13), "⌄  pdtool", f=bold)
    h = layout(tree, px(8), px(32), width - px(16))
    return img.crop((0, 0, width, px(32) + h + px(8)))


def compose(render_png: Path, panels: list, out: Path, font_path: Path) -> None:
    from PIL import Image, ImageDraw, ImageFont

    view = Image.open(render_png).convert("RGB")
    side_w, tab_w, top = 620, 44, 60
    imgs = [draw_panel(t, side_w, font_path) for t in panels]
    H = max(view.height, max(i.height for i in imgs) + top)
    W = view.width + len(imgs) * side_w + tab_w
    canvas = Image.new("RGB", (W, H), THEME["bg"])
    canvas.paste(view, (0, (H - view.height) // 2))
    d = ImageDraw.Draw(canvas)
    font = ImageFont.truetype(str(font_path), 22)
    for k, (img, caption) in enumerate(zip(imgs, ["while baking", "after the bake"])):
        x = view.width + k * side_w
        d.text((x + 16, top // 2), caption, fill=THEME["dim"], font=font, anchor="lm")
        canvas.paste(img, (x, top))
        d.line([x, 0, x, H], fill=(30, 30, 30), width=2)
    # the sidebar's vertical category tab
    d.rectangle([W - tab_w, 0, W, H], fill=(35, 35, 35))
    tab = Image.new("RGB", (140, tab_w - 8), THEME["tab"])
    ImageDraw.Draw(tab).text((70, (tab_w - 8) // 2), "pdtool", fill=THEME["text"], font=font, anchor="mm")
    canvas.paste(tab.rotate(-90, expand=True), (W - tab_w + 4, top))
    canvas.save(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "blender_panel.png")
    ap.add_argument("--json", type=Path, help="Also write the recorded layouts here.")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="pdtool_panel_"))
    os.environ["BLENDER_USER_RESOURCES"] = str(work / "user")  # before bpy starts
    splat, zip_path = work / "plant.ply", work / "pdtool_blender.zip"
    make_plant(splat, 3000)
    zip_addon(zip_path)
    (work / "out").mkdir()
    rep = blender_session(splat, zip_path, work / "out", work / "render.png")
    import bpy

    if args.json:
        args.json.write_text(json.dumps(rep, indent=1))
    font = Path(bpy.utils.system_resource("DATAFILES")) / "fonts" / "Inter.woff2"
    compose(work / "render.png", [rep["running"], rep["done"]], args.out, font)
    print(f"wrote {args.out} (work files in {work}); frames {rep['frames']}, usd {rep['usd']}")


if __name__ == "__main__":
    main()
