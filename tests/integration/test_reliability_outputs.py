"""pdtool replaces only its own outputs: folders it made carry a manifest, side outputs
nobody named carry a mark, and no run deletes an input or another of its outputs.

Library level first (pd_tool.core.atomic and each writer), then through the CLI
(click.testing.CliRunner on cli.main) on a 300-Gaussian plant at draft quality."""
from __future__ import annotations

import gc
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from _cli import invoke, refusal_line
from click.testing import CliRunner

from pd_tool.core.atomic import (MANIFEST, atomic_output, check_outputs, check_own_file, check_replaceable_folder,
                            is_own_file)
from pd_tool.core.errors import OutputError, PdToolError

POT_TOP = "0.2"  # the synthetic plant's pot (pd_tool.io.synthetic.POT_TOP)
BAKE = ["--preset", "flower", "--force", "0,0,1", "--frames", "3", "--quality", "draft", "--device", "cpu"]


# ----------------------------------------------------------------------------- helpers


def _leftovers(folder: Path) -> list[str]:
    """Temporaries of any pdtool writer under folder: .*.part*, .*.tmp-*, .*.old."""
    out = []
    for p in folder.rglob(".*"):
        n = p.name
        if ".part" in n or ".tmp-" in n or n.endswith(".old"):
            out.append(str(p.relative_to(folder)))
    return out


def _tree(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    return save_splats(make_plant(300, seed=0), tmp_path_factory.mktemp("plant") / "plant.ply")


def _pdtool_folder(path: Path, files: dict[str, str]) -> Path:
    with atomic_output(path, directory=True) as tmp:
        for name, text in files.items():
            (tmp / name).parent.mkdir(parents=True, exist_ok=True)
            (tmp / name).write_text(text)
    return path


# ----------------------------------------------------------------------------- folders: the manifest


def test_folder_carries_a_manifest_of_what_it_holds(tmp_path: Path) -> None:
    folder = _pdtool_folder(tmp_path / "out", {"a.png": "aa", "sub/b.txt": "bbb"})
    m = json.loads((folder / MANIFEST).read_text())
    assert m["written_by"] == "pdtool" and m["files"] == {"a.png": 2, "sub/b.txt": 3} and m["folders"] == ["sub"]
    check_replaceable_folder(folder)  # its own: passes
    _pdtool_folder(folder, {"c.png": "c"})  # and is replaced
    assert sorted(p.name for p in folder.iterdir()) == [MANIFEST, "c.png"]


@pytest.mark.parametrize("change", ["added file", "added folder", "grown file", "link", "no manifest",
                                    "forged manifest"])
def test_folder_with_anything_foreign_is_never_replaced(tmp_path: Path, change: str) -> None:
    folder = _pdtool_folder(tmp_path / "out", {"a.png": "aa"})
    if change == "added file":
        (folder / "precious.txt").write_text("mine")
    elif change == "added folder":
        (folder / "notes").mkdir()
    elif change == "grown file":
        (folder / "a.png").write_text("edited by hand")
    elif change == "link":
        (folder / "a.png").unlink()
        (folder / "a.png").symlink_to(tmp_path)
    elif change == "no manifest":
        (folder / MANIFEST).unlink()
    else:
        (folder / MANIFEST).write_text('{"written_by": "someone else", "files": {}, "folders": []}')
    before = _tree(folder)
    with pytest.raises(OutputError, match="pdtool did not write"):
        check_replaceable_folder(folder, "--frames-out")
    with pytest.raises(OutputError, match="--frames-out"):
        with atomic_output(folder, directory=True, what="--frames-out") as tmp:
            (tmp / "new.png").write_text("new")
    assert _tree(folder) == before and _leftovers(tmp_path) == []


def test_empty_and_missing_folders_are_fine_links_files_and_the_current_folder_are_not(tmp_path, monkeypatch):
    (tmp_path / "empty").mkdir()
    _pdtool_folder(tmp_path / "empty", {"f.png": "x"})
    _pdtool_folder(tmp_path / "new" / "deeper", {"f.png": "x"})
    assert (tmp_path / "new" / "deeper" / "f.png").is_file()
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        check_replaceable_folder(tmp_path / "file")
    (tmp_path / "link").symlink_to(tmp_path / "empty")
    with pytest.raises(OutputError, match="symbolic link"):
        check_replaceable_folder(tmp_path / "link")
    work = _pdtool_folder(tmp_path / "work", {"f.png": "x"})  # even one pdtool made
    monkeypatch.chdir(work)
    for p in (Path("."), work, tmp_path):
        with pytest.raises(OutputError, match="current folder"):
            check_replaceable_folder(p)


def test_a_folder_of_files_pdtool_marked_counts_as_pdtools(tmp_path: Path) -> None:
    """`render -o video/frame_0000.png --write-camera video/` leaves marked files, no manifest."""
    from pd_tool.core.cameras import auto_camera, save_camera_json
    from pd_tool.render.preview import save_png

    video = tmp_path / "video"
    save_png(video / "frame_0000.png", np.zeros((8, 8, 3), np.uint8))
    save_camera_json(video / "camera.json", auto_camera(_scene().positions.numpy(), 8, 8))
    check_replaceable_folder(video)
    (video / "frame_0001.png").write_bytes(b"\x89PNG\r\n\x1a\n drawn elsewhere")
    with pytest.raises(OutputError, match="frame_0001.png"):
        check_replaceable_folder(video)


def test_known_files_and_python_caches_count_as_pdtools(tmp_path: Path) -> None:
    old = tmp_path / "addon"
    (old / "__pycache__").mkdir(parents=True)
    (old / "__init__.py").write_text("x")
    (old / "__pycache__" / "__init__.cpython-311.pyc").write_bytes(b"x")
    check_replaceable_folder(old, known=["__init__.py"])
    (old / "__pycache__" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="notes.txt"):
        check_replaceable_folder(old, known=["__init__.py"])


# ----------------------------------------------------------------------------- outputs against each other


def test_outputs_that_destroy_inputs_or_each_other_arerefusal_line(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "res").mkdir()
    scene = tmp_path / "res" / "plant.ply"
    scene.write_text("ply")
    cases = [
        ({"OUT": "res/out.usd"}, {"--frames-out": "res"}, {}, "holds OUT"),
        ({"--preview": "res/sub/p.mp4"}, {"--frames-out": "res"}, {}, "holds --preview"),
        ({}, {"--frames-out": "."}, {}, "current folder"),
        ({}, {"--frames-out": ".."}, {}, "current folder"),
        ({}, {"--frames-out": "res"}, {"--scene": scene}, "holds the input --scene"),
        ({}, {"--frames-out": "res/../res/"}, {"--scene": scene}, "holds the input --scene"),
        ({"OUT": "res/plant.ply"}, {}, {"--scene": scene}, "is the input --scene"),
        ({"OUT": "a.usd", "--preview": "./a.usd"}, {}, {}, "name the same path"),
    ]
    for files, folders, inputs, words in cases:
        with pytest.raises(OutputError, match=words):
            check_outputs(files, folders, inputs)
    check_outputs({"OUT": "out.usd", "--preview": "p.mp4"}, {"--frames-out": "frames"}, {"--scene": scene})
    # a link into the input's folder is the same folder
    (tmp_path / "alias").symlink_to(tmp_path / "res")
    with pytest.raises(OutputError, match="holds the input"):
        check_outputs({}, {"--frames-out": "alias"}, {"--scene": scene})


# ----------------------------------------------------------------------------- marks on side outputs


def _scene():
    from pd_tool.io.synthetic import make_plant

    return make_plant(200, seed=1)


def _writers(tmp_path: Path) -> dict[str, Path]:
    """One file from every writer that marks its files."""
    from pd_tool.core.cameras import auto_camera, save_camera_json
    from pd_tool.fit.outputs import write_report
    from pd_tool.io import save_ply
    from pd_tool.materials.file import write_record
    from pd_tool.render.plots import line_plot
    from pd_tool.render.preview import save_png, write_preview

    frames = [np.full((16, 16, 3), 40 * i, np.uint8) for i in range(3)]
    scene = _scene()
    return {
        "png": save_png(tmp_path / "a.png", frames[1]),
        "plot": line_plot(tmp_path / "loss.png", {"s": ([1, 2], [1.0, 0.5])}, title="t", xlabel="x", ylabel="y"),
        "ply": save_ply(scene, tmp_path / "a.ply"),
        "mp4": write_preview(frames, tmp_path / "a.mp4", 10),
        "gif": write_preview(frames, tmp_path / "a.gif", 10),
        "report": write_report(tmp_path / "a.report.json", {"losses": {}}),
        "camera": (save_camera_json(tmp_path / "camera.json", auto_camera(scene.positions.numpy(), 16, 16)),
                   tmp_path / "camera.json")[1],
        "record": write_record(tmp_path / "a.ply", tmp_path / "a.pdmat", tmp_path),
    }


def test_every_writer_marks_its_files_and_foreign_files_are_not_marked(tmp_path: Path) -> None:
    from pd_tool.io import load_splats

    written = _writers(tmp_path)
    for kind, p in written.items():
        assert is_own_file(p), kind
    assert load_splats(written["ply"]).count == 200  # the PLY comment does not disturb readers
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    from PIL import Image

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(foreign / "a.png")
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(foreign / "a.gif")
    body = written["ply"].read_bytes().replace(b"comment written by pdtool\n", b"")
    (foreign / "a.ply").write_bytes(body)
    (foreign / "a.mp4").write_bytes(written["mp4"].read_bytes().replace(b"written by pdtool", b"written by ffmpeg!"))
    (foreign / "a.json").write_text('{"written_by": "blender", "scene": "x"}')
    (foreign / "b.json").write_text("[1, 2]")
    (foreign / "c.json").write_text("not json")
    (foreign / "a.txt").write_text("x")
    (foreign / "link.png").symlink_to(written["png"])
    for p in foreign.iterdir():
        assert not is_own_file(p), p.name
    # what pdtool wrote before files carried the mark: the record's and report's exact keys
    (foreign / "last-fit.json").write_text('{"scene": "a", "material": "b", "written": "t"}')
    assert is_own_file(foreign / "last-fit.json")


def test_side_outputs_replace_only_pdtools_files(tmp_path: Path) -> None:
    from pd_tool.render.preview import save_png

    img = np.zeros((8, 8, 3), np.uint8)
    save_png(tmp_path / "fit.E.png", img, own_only=True)  # new
    save_png(tmp_path / "fit.E.png", img + 1, own_only=True)  # its own: replaced
    (tmp_path / "user.png").write_bytes(b"\x89PNG\r\n\x1a\n mine")
    with pytest.raises(OutputError, match=r"user.png: exists and was not written by pdtool.*the fit's E"):
        save_png(tmp_path / "user.png", img, own_only=True, what="the fit's E field picture")
    assert (tmp_path / "user.png").read_bytes() == b"\x89PNG\r\n\x1a\n mine"
    save_png(tmp_path / "user.png", img)  # named by the user (render -o): replaced as asked
    assert is_own_file(tmp_path / "user.png") and _leftovers(tmp_path) == []
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        check_own_file(tmp_path / "dir.png", "a plot")


@pytest.mark.parametrize("kind", ["loss.png", "E.ply", "E.png", "report.json", "preview.mp4"])
def test_fit_side_outputs_refuse_a_foreign_file_before_writing_any(tmp_path: Path, kind: str) -> None:
    from pd_tool.fit.outputs import check_fit_outputs, fit_output_paths

    paths = fit_output_paths(tmp_path, "fit")
    assert sorted(p.name for p, _ in paths.values())[:5] == sorted(
        f"fit.{k}" for k in ("loss.png", "E.ply", "E.png", "report.json", "preview.mp4"))
    check_fit_outputs(tmp_path, "fit")  # nothing there yet
    (tmp_path / f"fit.{kind}").write_text("the user's own")
    with pytest.raises(OutputError, match=rf"fit\.{kind.replace('.', '[.]')}: exists and was not written by pdtool"):
        check_fit_outputs(tmp_path, "fit")
    # the scene itself can be a side output's name: refused even when pdtool wrote it
    from pd_tool.io import save_ply

    scene = save_ply(_scene(), tmp_path / "x.E.ply")
    with pytest.raises(OutputError, match="is the input SCENE"):
        check_fit_outputs(tmp_path, "x", inputs={"SCENE": scene})


def test_fit_record_replaces_only_a_pdtool_record(tmp_path: Path) -> None:
    from pd_tool.materials.file import RECORD_PATH, read_record, write_record

    (tmp_path / "s.ply").write_text("x")
    (tmp_path / "m.pdmat").write_text("x")
    write_record(tmp_path / "s.ply", tmp_path / "m.pdmat", tmp_path)
    write_record(tmp_path / "s.ply", tmp_path / "m.pdmat", tmp_path)  # its own: replaced
    assert read_record(tmp_path)[0] == (tmp_path / "s.ply").resolve()
    (tmp_path / RECORD_PATH).write_text('{"my": "notes"}')
    with pytest.raises(OutputError, match="last-fit.json: exists and was not written by pdtool"):
        write_record(tmp_path / "s.ply", tmp_path / "m.pdmat", tmp_path)
    assert (tmp_path / RECORD_PATH).read_text() == '{"my": "notes"}'
    other = tmp_path / "other"
    other.mkdir()
    (other / ".pdtool").write_text("a file")
    with pytest.raises(OutputError, match=r"\.pdtool is a file"):
        write_record(tmp_path / "s.ply", tmp_path / "m.pdmat", other)
    (other / ".pdtool").unlink()
    (other / ".pdtool").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    with pytest.raises(OutputError, match=r"\.pdtool is a symbolic link"):
        write_record(tmp_path / "s.ply", tmp_path / "m.pdmat", other)
    assert not (tmp_path / "elsewhere").exists()


def test_camera_json_in_a_named_folder_replaces_only_pdtools(tmp_path: Path) -> None:
    from pd_tool.core.cameras import auto_camera, load_cameras, save_camera_json

    cam = auto_camera(_scene().positions.numpy(), 32, 24)
    save_camera_json(tmp_path / "camera.json", cam)
    save_camera_json(tmp_path / "camera.json", cam)
    assert load_cameras(tmp_path / "camera.json")[0].width == 32
    (tmp_path / "camera.json").write_text('{"fx": 1, "width": 2, "height": 2, "world_to_camera": []}')
    with pytest.raises(OutputError, match="camera.json: exists and was not written by pdtool"):
        save_camera_json(tmp_path / "camera.json", cam)


# ----------------------------------------------------------------------------- writers


def test_video_folder_never_replaces_a_foreign_folder(tmp_path: Path) -> None:
    from pd_tool.core.cameras import auto_camera
    from pd_tool.video.folder import load_reference_video, write_video_folder

    frames = np.zeros((3, 16, 16, 3), np.uint8)
    cam = auto_camera(_scene().positions.numpy(), 16, 16)
    folder = write_video_folder(tmp_path / "v", frames, cam, 10.0)
    write_video_folder(folder, frames + 5, cam, 10.0, overwrite=True)  # its own
    assert load_reference_video(folder, working_size=None).num_frames == 3  # the manifest is ignored by fit
    (folder / "masks").mkdir()
    (folder / "masks" / "m0.png").write_text("drawn by hand")
    before = _tree(folder)
    with pytest.raises(OutputError, match="masks"):
        write_video_folder(folder, frames, cam, 10.0, overwrite=True, what="--frames-out")
    assert _tree(folder) == before and _leftovers(tmp_path) == []


def test_addon_install_replaces_only_its_own_folder(tmp_path: Path) -> None:
    from pd_tool.addon import ADDON_NAME, AddonPackageError, addon_source, install_addon, zip_addon

    dest = tmp_path / "addons"
    target = install_addon(dest)
    assert (target / MANIFEST).is_file()
    (target / "__pycache__").mkdir(exist_ok=True)
    (target / "__pycache__" / "command.cpython-311.pyc").write_bytes(b"cache")  # Blender imported it
    install_addon(dest)  # its own: replaced
    # a copy without a manifest (older pdtool, Blender's installer) holding only the add-on's files
    (target / MANIFEST).unlink()
    install_addon(dest)
    (target / "my_tweaks.py").write_text("mine")
    with pytest.raises(OutputError, match="my_tweaks.py"):
        install_addon(dest)
    assert (target / "my_tweaks.py").read_text() == "mine" and _leftovers(dest) == []
    with pytest.raises(AddonPackageError, match="own copy"):
        install_addon(addon_source().parent)
    with pytest.raises(AddonPackageError, match="inside the add-on"):
        zip_addon(addon_source() / "a.zip")
    assert not (addon_source() / "a.zip").exists() and ADDON_NAME == target.name


def test_generate_overwrites_only_folders_it_made(tmp_path: Path, monkeypatch) -> None:
    import errno

    import imageio.v3 as iio

    from pd_tool.video import generate as gen
    from pd_tool.video.camera_motion import CameraMotion
    from pd_tool.core.cameras import auto_camera

    scene = _scene()
    cam = auto_camera(scene.positions.numpy(), 16, 16)
    model = gen.ModelInfo(tmp_path / "model", "StableVideoDiffusionPipeline", 8)
    model.path.mkdir()
    frames = np.zeros((3, 16, 16, 3), np.uint8)
    monkeypatch.setattr(gen, "load_pipeline", lambda info, device: type("P", (), {
        "set_progress_bar_config": lambda self, **kw: None})())
    monkeypatch.setattr(gen, "animate", lambda pipe, image, settings, seed, kind=None: frames)
    monkeypatch.setattr("pd_tool.video.camera_motion.estimate_camera_motion",
                        lambda *a, **k: CameraMotion(np.zeros((3, 2)), np.ones(3), np.zeros(3), np.zeros(3), 16))
    settings = gen.GenerateSettings(frames=3)
    out = tmp_path / "video"
    gen.generate_reference_videos(scene, cam, out, model, settings, say=lambda s: None)
    gen.generate_reference_videos(scene, cam, out, model, settings, overwrite=True, say=lambda s: None)
    (out / "keep.txt").write_text("mine")
    with pytest.raises(PdToolError, match="keep.txt.*--overwrite replaces only"):
        gen.check_output(out, True)
    assert (out / "keep.txt").read_text() == "mine"
    with pytest.raises(PdToolError, match="holds the input --model"):
        gen.check_output(tmp_path, True, {"--model": model.path})
    monkeypatch.chdir(out)
    with pytest.raises(PdToolError, match="current folder"):
        gen.check_output(".", True)
    monkeypatch.chdir(tmp_path)
    # a write that fails inside the nested video folder names the user's path, not a temporary
    real = iio.imwrite

    def full(path, *a, **k):
        if Path(path).name == "frame_0001.png":
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(iio, "imwrite", full)
    with pytest.raises(OutputError) as e:
        gen.generate_reference_videos(scene, cam, tmp_path / "second", model, settings, say=lambda s: None)
    assert str(e.value) == (f"cannot write {tmp_path / 'second'}: No space left on device; free some space or "
                            f"choose a writable folder")
    assert not (tmp_path / "second").exists() and _leftovers(tmp_path) == []


def test_bake_refuses_before_preparing_or_writing_anything(plant: Path, tmp_path: Path, monkeypatch) -> None:
    import pd_tool.bake.baker as bake_mod
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.io import load_splats
    from pd_tool.materials.presets import Material

    def no_work(*a, **k):
        raise AssertionError("the scene was prepared before the outputs were checked")

    monkeypatch.setattr(bake_mod, "prepare_scene", no_work)
    scene = load_splats(plant)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("mine")
    (tmp_path / "fits").mkdir()
    (tmp_path / "fits" / "m.pdmat").write_text("x")
    run = dict(force=ForceSpec(accel=(0.0, 0.0, 1.0)), material=Material.from_preset("flower"),
               settings=BakeSettings(seconds=0.1, quality="draft"))
    cases = [
        (dict(frames_dir=tmp_path / "mine"), "notes.txt"),
        (dict(frames_dir=tmp_path / "fits", inputs={"--material": tmp_path / "fits" / "m.pdmat"}),
         "holds the input --material"),
        (dict(frames_dir=plant.parent), "holds the input --scene"),
        (dict(preview=tmp_path / "o.usd"), "must end in .mp4 or .gif"),
        (dict(frames_dir=tmp_path / "o.usd" / ".."), "holds OUT"),
    ]
    for extra, words in cases:
        with pytest.raises(PdToolError, match=words):
            bake(scene, tmp_path / "o.usd", **run, **extra)
    (tmp_path / "dir.usd").mkdir()
    with pytest.raises(PdToolError, match="OUT .*dir.usd: is a folder"):
        bake(scene, tmp_path / "dir.usd", **run)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.usd", "fits", "mine"] and _leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- names


def test_long_names(tmp_path: Path) -> None:
    from usd_export import UsdBakeWriter

    legal = "b" * 250 + ".usd"  # legal, but a temporary named after it in full would not be
    pts = np.zeros((3, 3), np.float32)
    with UsdBakeWriter(tmp_path / legal, n_points=3, fps=30) as w:
        w.write_frame(0, pts, np.tile([1, 0, 0, 0], (3, 1)), np.full((3, 3), 0.1))
    assert (tmp_path / legal).is_file()
    with atomic_output(tmp_path / ("c" * 250 + ".json")) as tmp:
        tmp.write_text("{}")
    unraisable = []
    old_hook = sys.unraisablehook
    sys.unraisablehook = unraisable.append
    try:
        with pytest.raises(OutputError, match="File name too long; choose a shorter name") as e:
            UsdBakeWriter(tmp_path / ("a" * 300 + ".usd"), n_points=3, fps=30)
        del e
        gc.collect()
        with pytest.raises(OutputError, match="File name too long"):
            with atomic_output(tmp_path / ("a" * 300 + ".png")) as tmp:
                tmp.write_text("x")
    finally:
        sys.unraisablehook = old_hook
    assert unraisable == []  # the writer's finalizer stays quiet
    assert _leftovers(tmp_path) == []


# ----------------------------------------------------------------------------- through the CLI


def test_cli_frames_out_onto_a_users_folder_refuses_before_any_work(plant: Path, tmp_path: Path) -> None:
    (tmp_path / "mydata").mkdir()
    (tmp_path / "mydata" / "precious.txt").write_text("mine")
    res = invoke(["bake", "--scene", plant, *BAKE, "--frames-out", "mydata", "out.usd"], tmp_path)
    refusal_line(res, "--frames-out mydata", "precious.txt", bar=True)
    assert (tmp_path / "mydata" / "precious.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mydata"]  # no out.usd: refused before writing


def test_cli_frames_out_holding_the_other_outputs_refuses(plant: Path, tmp_path: Path) -> None:
    (tmp_path / "res").mkdir()
    res = invoke(["bake", "--scene", plant, *BAKE, "--frames-out", "res", "--preview", "res/p.mp4", "res/out.usd"],
               tmp_path)
    refusal_line(res, "--frames-out res", "OUT res/out.usd", bar=True)
    assert list((tmp_path / "res").iterdir()) == []


@pytest.mark.parametrize("where", [".", ".."])
def test_cli_frames_out_current_folder_refuses(plant: Path, tmp_path: Path, where: str) -> None:
    work = tmp_path / "work"
    work.mkdir()
    res = invoke(["bake", "--scene", plant, *BAKE, "--frames-out", where, "out.usd"], work)
    refusal_line(res, f"--frames-out {where}", "current folder", bar=True)
    assert list(work.iterdir()) == []


def test_cli_frames_out_holding_the_scene_refuses(plant: Path, tmp_path: Path) -> None:
    import shutil

    shutil.copy(plant, tmp_path / "plant.ply")
    res = invoke(["bake", "--scene", "plant.ply", *BAKE, "--frames-out", ".", "out.usd"], tmp_path)
    refusal_line(res, "--frames-out", bar=True)
    sub = tmp_path / "sub"
    sub.mkdir()
    res = invoke(["bake", "--scene", "../plant.ply", *BAKE, "--frames-out", "..", "out.usd"], sub)
    refusal_line(res, "--frames-out ..", bar=True)
    assert (tmp_path / "plant.ply").read_bytes() == plant.read_bytes()


def test_cli_frames_out_replaces_its_own_folder(plant: Path, tmp_path: Path) -> None:
    (tmp_path / "frames").mkdir()  # empty: fine
    for _ in range(2):
        res = invoke(["bake", "--scene", plant, *BAKE, "--frames-out", "frames", "out.usd"], tmp_path)
        assert res.exit_code == 0, res.output
    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    assert names == [MANIFEST, "camera.json", "frame_0000.png", "frame_0001.png", "frame_0002.png"]
    assert _leftovers(tmp_path) == []


def test_cli_frames_out_replaces_the_render_it_started_from(plant: Path, tmp_path: Path) -> None:
    """docs/tutorial.md's stand-in for a video model: render I_0 and its camera into video/,
    then bake frames from that camera over the same folder."""
    res = invoke(["render", plant, "--width", "32", "--height", "32", "-o", "video/frame_0000.png",
                "--write-camera", "video/"], tmp_path)
    assert res.exit_code == 0, res.output
    res = invoke(["bake", "--scene", plant, *BAKE, "--camera", "video/camera.json", "--frames-out", "video/",
                "out.usd"], tmp_path)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "video" / "frame_0002.png").is_file() and (tmp_path / "video" / MANIFEST).is_file()


def test_cli_long_output_name_is_one_line(plant: Path, tmp_path: Path) -> None:
    unraisable = []
    old_hook = sys.unraisablehook
    sys.unraisablehook = unraisable.append
    try:
        res = invoke(["bake", "--scene", plant, *BAKE, "a" * 300 + ".usd"], tmp_path)
        gc.collect()
    finally:
        sys.unraisablehook = old_hook
    refusal_line(res, "the name is 304 bytes long", bar=True)
    assert unraisable == [] and list(tmp_path.iterdir()) == []


def test_cli_render_write_camera_keeps_a_users_camera_json(plant: Path, tmp_path: Path) -> None:
    (tmp_path / "video").mkdir()
    (tmp_path / "video" / "camera.json").write_text('{"mine": true}')
    res = invoke(["render", plant, "-o", "x.png", "--width", "32", "--height", "32", "--write-camera", "video"], tmp_path)
    refusal_line(res, "video/camera.json: exists and was not written by pdtool")
    assert (tmp_path / "video" / "camera.json").read_text() == '{"mine": true}'


def test_cli_blender_addon_install_keeps_a_foreign_folder(tmp_path: Path) -> None:
    (tmp_path / "pdtool_blender").mkdir()
    (tmp_path / "pdtool_blender" / "notes.txt").write_text("mine")
    res = invoke(["blender-addon", "--install-to", tmp_path], tmp_path)
    refusal_line(res, "notes.txt", "--install-to")
    assert sorted(p.name for p in (tmp_path / "pdtool_blender").iterdir()) == ["notes.txt"]


def _fake_model(folder: Path) -> Path:
    """A model folder that passes `inspect_model` (configs and weight names, no weights)."""
    index = {"_class_name": "StableVideoDiffusionPipeline"}
    for comp, cfg in (("unet", "config.json"), ("vae", "config.json"), ("image_encoder", "config.json"),
                      ("scheduler", "scheduler_config.json"), ("feature_extractor", "preprocessor_config.json")):
        index[comp] = ["x", "y"]
        (folder / comp).mkdir(parents=True)
        (folder / comp / cfg).write_text(json.dumps({"block_out_channels": [1, 2], "down_block_types": ["a", "b"]}))
        (folder / comp / "model.safetensors").write_bytes(b"")
    (folder / "model_index.json").write_text(json.dumps(index))
    return folder


def test_cli_generate_overwrite_keeps_a_foreign_folder(plant: Path, tmp_path: Path) -> None:
    pytest.importorskip("diffusers")
    pytest.importorskip("transformers")
    model = _fake_model(tmp_path / "model")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep.txt").write_text("mine")
    res = invoke(["generate", plant, "--model", model, "--width", "64", "--height", "48", "-o", "taken", "--overwrite"],
               tmp_path)
    refusal_line(res, "keep.txt", "--overwrite replaces only")
    assert (tmp_path / "taken" / "keep.txt").read_text() == "mine"
    res = invoke(["generate", plant, "--model", model, "--width", "64", "--height", "48", "-o", ".", "--overwrite"],
               tmp_path / "taken")
    refusal_line(res, "current folder")


FIT = ["--quality", "draft", "--velocity-iters", "1", "--material-iters", "1", "--working-size", "24",
       "--static-below", POT_TOP, "--device", "cpu"]


def test_cli_fit_replaces_its_own_side_outputs_and_no_one_elses(fit_dir: Path, tmp_path: Path) -> None:
    args = ["fit", fit_dir / "plant.ply", fit_dir / "video", "-o", "fit.pdmat", *FIT]
    for _ in range(2):  # the second run replaces the first one's files
        res = invoke(args, tmp_path)
        assert res.exit_code == 0, res.output
    for name in ("fit.loss.png", "fit.E.ply", "fit.E.png", "fit.report.json", "fit.preview.mp4",
                 ".pdtool/last-fit.json"):
        assert is_own_file(tmp_path / name), name
    material = (tmp_path / "fit.pdmat").stat().st_mtime_ns
    (tmp_path / "fit.E.ply").write_text("my own E field")
    res = invoke(args, tmp_path)
    refusal_line(res, "fit.E.ply: exists and was not written by pdtool")  # before the fit: no bar yet
    assert (tmp_path / "fit.E.ply").read_text() == "my own E field"
    (tmp_path / "fit.E.ply").unlink()
    (tmp_path / ".pdtool" / "last-fit.json").write_text("{}")
    res = invoke(args, tmp_path)
    refusal_line(res, "last-fit.json: exists and was not written by pdtool")
    assert (tmp_path / ".pdtool" / "last-fit.json").read_text() == "{}"
    assert (tmp_path / "fit.pdmat").stat().st_mtime_ns == material  # refused before the fit wrote anything
    assert _leftovers(tmp_path) == []


def test_cli_fit_default_material_name_replaces_only_a_material_file(fit_dir: Path, tmp_path: Path) -> None:
    """Without -o the material goes to SCENE.pdmat, a name nobody gave: a file there that
    is not a pdtool material file is the user's."""
    import shutil

    shutil.copy(fit_dir / "plant.ply", tmp_path / "p.ply")
    (tmp_path / "p.pdmat").write_text("my notes")
    res = invoke(["fit", tmp_path / "p.ply", fit_dir / "video", *FIT], tmp_path)
    refusal_line(res, "p.pdmat: exists and is not a pdtool material file")
    assert (tmp_path / "p.pdmat").read_text() == "my notes"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.pdmat", "p.ply"]
    res = invoke(["fit", tmp_path / "p.ply", fit_dir / "video", "-o", "p.pdmat", *FIT], tmp_path)
    assert res.exit_code == 0, res.output  # named with -o, it is replaced as asked
    from pd_tool.materials.file import is_material_file

    assert is_material_file(tmp_path / "p.pdmat")
    res = invoke(["fit", tmp_path / "p.ply", fit_dir / "video", *FIT], tmp_path)
    assert res.exit_code == 0, res.output  # and now it is pdtool's own
