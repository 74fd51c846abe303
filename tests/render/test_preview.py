"""pd_tool.render.preview: mp4 / gif / png writers (read back with imageio) and animation previews."""
from __future__ import annotations

import os

import imageio.v2 as iio
import numpy as np
import pytest
import torch

from pd_tool.core.cameras import auto_camera
from pd_tool.render.preview import PreviewError, render_animation_preview, save_png, write_preview


def frames(n=6, h=33, w=47):
    # A bright square moving right over a dark background: easy to see after lossy coding.
    out = []
    for i in range(n):
        a = np.full((h, w, 3), 20, np.uint8)
        a[10:22, 4 + 5 * i : 16 + 5 * i] = (230, 200, 40)
        out.append(a)
    return out


def test_mp4_roundtrip(tmp_path):
    path = write_preview(iter(frames()), tmp_path / "p.mp4", fps=12)
    assert sorted(os.listdir(tmp_path)) == ["p.mp4"]  # the temp file was renamed away
    r = iio.get_reader(path)
    assert r.get_meta_data()["fps"] == pytest.approx(12.0)
    got = [f for f in r]
    r.close()
    assert len(got) == 6
    assert got[0].shape == (34, 48, 3)  # padded to even sizes for H.264
    for src, dec in zip(frames(), got):
        assert np.abs(dec[:33, :47].astype(int) - src.astype(int)).mean() < 8  # lossy, close


def test_gif_roundtrip(tmp_path):
    path = write_preview(frames(), tmp_path / "p.gif", fps=10)
    got = iio.mimread(path)
    assert len(got) == 6 and got[0].shape[:2] == (33, 47)
    assert np.abs(got[3][..., :3].astype(int) - frames()[3].astype(int)).max() <= 16  # palette


def test_png_roundtrip(tmp_path):
    img = frames()[2]
    save_png(tmp_path / "x.png", img)
    assert np.array_equal(iio.imread(tmp_path / "x.png"), img)


def test_bad_inputs_leave_nothing(tmp_path):
    with pytest.raises(PreviewError, match=r"must end in \.mp4 or \.gif"):
        write_preview(frames(), tmp_path / "p.avi", fps=10)
    with pytest.raises(PreviewError, match="differs from frame 0"):
        write_preview([frames()[0], frames(h=20)[0]], tmp_path / "p.mp4", fps=10)
    with pytest.raises(PreviewError, match="expected uint8"):
        write_preview([np.zeros((8, 8, 3), np.float32)], tmp_path / "p.gif", fps=10)
    with pytest.raises(PreviewError, match="no frames"):
        write_preview([], tmp_path / "p.gif", fps=10)
    assert os.listdir(tmp_path) == []


def test_render_animation_preview(shared_data, tmp_path):
    from pd_tool.io import load_splats

    scene = load_splats(shared_data / "udon.ply")
    cam = auto_camera(scene.positions.numpy(), 64, 48, up_axis="-y")
    shift = torch.tensor([0.05, 0.0, 0.0])
    anim = [(scene.positions + k * shift, scene.quats) for k in range(4)]
    path = render_animation_preview(anim, scene.scales, scene.opacities, scene.sh, cam, tmp_path / "a.gif", fps=8)
    got = iio.mimread(path)
    assert len(got) == 4 and got[0].shape[:2] == (48, 64)
    # The object is there (not a blank white frame) and it moves between frames.
    assert (got[0][..., :3] < 200).any(axis=-1).mean() > 0.02
    assert np.abs(got[0].astype(int) - got[3].astype(int)).max() > 50


def test_missing_mp4_encoder_is_named_and_a_fit_preview_falls_back_to_gif(tmp_path, monkeypatch):
    """imageio without imageio-ffmpeg (seen on a machine with a partial install): an .mp4
    preview fails with one clear line naming the package and leaves no file; the fit's
    preview (write_preview_any) writes a .gif beside it instead of failing the fit."""
    from pd_tool.render.preview import PreviewEncoderMissing, write_preview_any

    def no_ffmpeg(*args, **kwargs):
        raise ImportError("The `FFMPEG` plugin is not installed.")

    monkeypatch.setattr("pd_tool.render.preview.ffmpeg_exe", no_ffmpeg)
    with pytest.raises(PreviewEncoderMissing, match="imageio-ffmpeg"):
        write_preview(frames(), tmp_path / "a.mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    got = write_preview_any(frames(), tmp_path / "fit.preview.mp4", fps=10)
    assert got == tmp_path / "fit.preview.gif"
    assert len(iio.mimread(got)) == 6
    assert not (tmp_path / "fit.preview.mp4").exists()


def held_frames(n=61, moving=20):
    # an object that moves for `moving` frames, then rests: the rest are identical frames
    out = []
    for i in range(n):
        a = np.full((32, 48, 3), 20, np.uint8)
        k = min(i, moving)
        a[8:20, k:k + 10] = (230, 200, 40)
        out.append(a)
    return out


def gif_durations_ms(path):
    from PIL import Image

    with Image.open(path) as im:
        out = []
        for i in range(im.n_frames):
            im.seek(i)
            out.append(im.info["duration"])
    return out


@pytest.mark.parametrize("n,fps", [(61, 30), (61, 24), (31, 15), (7, 30), (151, 60), (100, 120), (13, 7)])
def test_gif_plays_as_long_as_the_bake(tmp_path, n, fps):
    """A bake's GIF plays n / fps seconds, exact to GIF's 10 ms unit, although 1000 / fps
    ms is no whole number of centiseconds and Pillow merges the identical frames of a
    held pose into one; no delay is under the 20 ms viewers honour."""
    path = write_preview(held_frames(n, moving=min(20, n - 1)), tmp_path / "p.gif", fps=fps)
    d = gif_durations_ms(path)
    assert abs(sum(d) - 1000.0 * n / fps) <= 5.0, (sum(d), 1000.0 * n / fps)
    assert min(d) >= 20


def test_gif_of_moving_frames_keeps_every_frame(tmp_path):
    path = write_preview(held_frames(31, moving=40), tmp_path / "p.gif", fps=30)
    d = gif_durations_ms(path)
    assert len(d) == 31 and sum(d) == 1030 and set(d) == {30, 40}  # 1.0333 s: 10 ms rounding spread


def test_mp4_plays_as_long_as_the_bake(tmp_path):
    import imageio_ffmpeg

    path = write_preview(held_frames(61), tmp_path / "p.mp4", fps=30)
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(path))
    assert n == 61 and abs(secs - 61 / 30) <= 0.01  # ffmpeg reports centiseconds
