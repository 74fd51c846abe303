"""A fit that cannot learn says so: exit 2, one stderr line, nothing written.

Through the CLI on a tiny plant (800 Gaussians, 32 px, 4 frames): the camera looking away,
the object outside the image, every mask black, masks that leave out the moving part, a
still video, no iterations at all, every particle pinned, and (with the checks before the fit turned off, so the
fit runs) a loss that never moves. The same plant's video, with and without masks around
the object, is fitted: the checks do not refuse a fit that can learn.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

ARGS = ["fit", "plant.ply", "video", "-o", "fit.pdmat", "--static-below", "0.2", "--quality", "draft",
        "--velocity-iters", "1", "--material-iters", "2", "--working-size", "32", "--device", "cpu", "--no-preview"]


@pytest.fixture(scope="module")
def plant(tmp_path_factory) -> Path:
    from _plant import tiny_plant_video

    d = tmp_path_factory.mktemp("plant")
    tiny_plant_video(d, 800, seed=0, size=32)
    return d


def _run(plant: Path, tmp_path: Path, monkeypatch, edit=None, args=ARGS):
    """Copy the plant into a fresh folder, edit it, run `pdtool fit` there; returns the
    result and the files the run left besides its inputs."""
    from click.testing import CliRunner
    from tqdm import tqdm

    import cli

    w = tmp_path / "work"
    shutil.copytree(plant, w)
    if edit is not None:
        edit(w)
    before = {p.relative_to(w).as_posix() for p in w.rglob("*")}
    monkeypatch.chdir(w)
    # the progress bar's lines are the CLI's to clear; here only the error line counts
    monkeypatch.setattr(cli, "_tqdm", lambda *a, **k: tqdm(disable=True), raising=False)
    res = CliRunner().invoke(cli.main, args)
    after = {p.relative_to(w).as_posix() for p in w.rglob("*")}
    return res, sorted(after - before)


def _camera(w: Path, edit) -> None:
    path = w / "video" / "camera.json"
    cam = json.loads(path.read_text())
    cam["world_to_camera"] = edit(np.array(cam["world_to_camera"])).tolist()
    path.write_text(json.dumps(cam))


def _turn_away(w: Path) -> None:
    _camera(w, lambda m: np.diag([-1.0, 1.0, -1.0, 1.0]) @ m)  # half a turn about the camera's y axis


def _look_aside(w: Path) -> None:
    def edit(m):
        m = m.copy()
        m[0, 3] += 5.0 * abs(m[2, 3]) + 5.0  # the object far to the side, in front of the camera
        return m

    _camera(w, edit)


def _masks(w: Path, make) -> None:
    import imageio.v3 as iio

    (w / "video" / "masks").mkdir()
    for i, frame in enumerate(sorted((w / "video").glob("frame_*.png"))):
        iio.imwrite(w / "video" / "masks" / frame.name, make(i))


def _black_masks(w: Path) -> None:
    _masks(w, lambda i: np.zeros((32, 32), np.uint8))


def _corner_masks(w: Path) -> None:
    """White only in a corner the plant never reaches (more than the SSIM window away)."""
    def make(i):
        m = np.zeros((32, 32), np.uint8)
        m[:2, :2] = 255
        return m

    _masks(w, make)


def _object_masks(w: Path) -> None:
    """White where any frame differs from the background: the plant and where it moves."""
    import imageio.v3 as iio

    frames = [iio.imread(p).astype(int) for p in sorted((w / "video").glob("frame_*.png"))]
    obj = np.zeros((32, 32), bool)
    for f in frames:
        obj |= (np.abs(f - 255).max(axis=-1) > 8)
    _masks(w, lambda i: (obj * 255).astype(np.uint8))


def _still(w: Path) -> None:
    frames = sorted((w / "video").glob("frame_*.png"))
    for f in frames[1:]:
        shutil.copy(frames[0], f)


def _pinned(args):
    return [a if a != "0.2" else "100" for a in args]


CASES = [
    ("camera looking away", _turn_away, ARGS, r"^Error: video: the moving part of the scene \(\d+ Gaussians\) is "
                                              r"behind the camera, so the fit cannot see it move; use the camera"),
    ("object outside the image", _look_aside, ARGS, r"^Error: video: the moving part .* lies outside the camera's "
                                                    r"32x32 image, so the fit cannot see it move"),
    ("every mask black", _black_masks, ARGS, r"^Error: video/masks: every mask of frames 1-3 is black .*; paint the "
                                             r"object white in the masks, or remove masks/ to fit on whole frames$"),
    ("masks leave out the object", _corner_masks, ARGS,
     r"^Error: video: no frame differs from frame 0 by more than 0\.0/255 inside the masks"),
    # the same masks, past the video's own check: the render at rest shows the moving part
    # nowhere inside them
    ("masks leave out the rendered object", _corner_masks, ARGS,
     r"^Error: video: the moving part .* changes no pixel of the rest frame inside the masks"),
    ("still video", _still, ARGS, r"^Error: video: no frame differs from frame 0 by more than 0\.0/255, so the video "
                                  r"shows no motion to fit; pass a video of the object moving"),
    ("no iterations", None, [*ARGS, "--velocity-iters", "0", "--material-iters", "0"],
     r"^Error: --velocity-iters 0 and --material-iters 0 leave nothing to fit"),
    ("every particle pinned", None, _pinned(ARGS), r"^Error: every particle is static \(--static-below 100\.0 pins "
                                                   r"all \d+\), so nothing can move; shrink the static region"),
]


@pytest.mark.parametrize("name,edit,args,message", CASES, ids=[c[0] for c in CASES])
def test_a_fit_that_cannot_learn_is_refused_before_fitting(plant: Path, tmp_path: Path, monkeypatch, name, edit,
                                                           args, message) -> None:
    import re

    from pd_tool.fit import run as fit_run

    def no_fit(*a, **k):
        raise AssertionError("the fit started")

    monkeypatch.setattr(fit_run, "fit_round", no_fit)  # refused before any simulation
    if name == "masks leave out the rendered object":
        monkeypatch.setattr(fit_run, "check_videos_can_teach", lambda videos: None)
    res, written = _run(plant, tmp_path, monkeypatch, edit, args)
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and re.search(message, lines[0]), lines
    assert written == []


def test_a_loss_that_does_not_move_is_refused_after_the_fit(plant: Path, tmp_path: Path, monkeypatch) -> None:
    """The checks before the fit off, a camera that sees nothing: the fit runs, its loss stays
    put, and the run refuses before the material file is written (its checkpoint goes too)."""
    from pd_tool.fit import run as fit_run

    monkeypatch.setattr(fit_run, "check_fit_can_learn", lambda pb: None)
    res, written = _run(plant, tmp_path, monkeypatch, _turn_away)
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: the fit learned nothing: its material loss stayed at "), lines
    assert "over 2 iterations" in lines[0] and "nothing was written" in lines[0]
    assert written == []


@pytest.mark.parametrize("masks", [False, True])
def test_a_fit_that_can_learn_is_not_refused(plant: Path, tmp_path: Path, monkeypatch, masks: bool) -> None:
    res, written = _run(plant, tmp_path, monkeypatch, _object_masks if masks else None)
    assert res.exit_code == 0, res.output
    assert "fit.pdmat" in written and "fit.pdmat.ckpt" not in written


def _encode_mp4(frames: list[np.ndarray], folder: Path, camera: Path) -> Path:
    import imageio

    folder.mkdir()
    shutil.copy(camera, folder / "camera.json")
    w = imageio.get_writer(str(folder / "v.mp4"), fps=30, codec="libx264", macro_block_size=1)
    for f in frames:
        w.append_data(f)
    w.close()
    return folder


def test_a_still_mp4_is_told_from_a_moving_one(plant: Path, tmp_path: Path) -> None:
    """A codec's noise on a still scene is no motion; the plant swaying in an mp4 is."""
    import imageio.v3 as iio

    from pd_tool.fit.refusals import FitLearnsNothing, check_videos_can_teach
    from pd_tool.video.folder import load_reference_video

    frames = [iio.imread(p) for p in sorted((plant / "video").glob("frame_*.png"))]
    camera = plant / "video" / "camera.json"
    moving = _encode_mp4(frames, tmp_path / "moving", camera)
    still = _encode_mp4([frames[0]] * len(frames), tmp_path / "still", camera)
    check_videos_can_teach([load_reference_video(moving, working_size=32)])
    with pytest.raises(FitLearnsNothing, match=r"still/v\.mp4: no frame differs from frame 0 by more than"):
        check_videos_can_teach([load_reference_video(still, working_size=32)])


@pytest.mark.parametrize("where", ["video", "video/masks"])
def test_a_frame_that_is_a_folder_is_refused(plant: Path, tmp_path: Path, monkeypatch, where: str) -> None:
    """Frames are timed by their order, so one that is a folder is refused, not skipped."""
    def edit(w: Path) -> None:
        if where == "video/masks":
            _object_masks(w)
        (w / where / "frame_0002.png").unlink()
        (w / where / "frame_0002.png").mkdir()

    res, written = _run(plant, tmp_path, monkeypatch, edit)
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert lines == [f"Error: {where}/frame_0002.png: has a frame's name but is a folder; every later frame would "
                     f"shift in time; remove or rename it"], lines
    assert written == []


@pytest.mark.parametrize("error,start", [
    (lambda: __import__("torch").OutOfMemoryError("CUDA out of memory. Tried to allocate 20.00 MiB"),
     "Error: out of GPU memory"),
    (lambda: RuntimeError("Failed to allocate 425256000 bytes on device 'cuda:0'"), "Error: out of GPU memory"),
    (lambda: RuntimeError("Graph creation error: Warp CUDA error 2: out of memory (in function "
                          "wp_cuda_graph_create_exec)"), "Error: out of GPU memory"),
    (lambda: RuntimeError("Failed to allocate 8000000 bytes on device 'cpu'"), "Error: out of memory; lower"),
    (lambda: RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory: you "
                          "tried to allocate 80000000000 bytes"), "Error: out of memory; lower"),
    (lambda: MemoryError(), "Error: out of memory; lower"),
], ids=["torch", "warp array", "warp graph", "warp cpu", "torch cpu", "host"])
def test_running_out_of_memory_is_one_line(plant: Path, tmp_path: Path, monkeypatch, error, start) -> None:
    """A fit that runs out of memory (a larger scene, or another process on the same GPU)
    ends with one line naming the ways out, not torch's or warp's traceback, and leaves
    nothing behind."""
    from pd_tool.fit import run as fit_run

    def oom(*a, **k):
        raise error()

    monkeypatch.setattr(fit_run, "fit_round", oom)
    res, written = _run(plant, tmp_path, monkeypatch)
    assert res.exit_code == 2, (res.output, res.exception)
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(start), lines
    assert "--quality" in lines[0] and "Traceback" not in res.output
    assert written == []


def test_an_error_that_is_not_about_memory_is_not_dressed_as_one(plant: Path, tmp_path: Path, monkeypatch) -> None:
    from pd_tool.fit import run as fit_run

    def bug(*a, **k):
        raise RuntimeError("an index out of range in a kernel")

    monkeypatch.setattr(fit_run, "fit_round", bug)
    res, _ = _run(plant, tmp_path, monkeypatch)
    assert res.exit_code == 1 and isinstance(res.exception, RuntimeError)
    assert "memory" not in res.stderr
