"""The fit checkpoint: a file from disk is data, never code, and a resume continues only
from a checkpoint of this very fit.

The format's reader on its own (round trip, strictness), then crafted checkpoints given to
`run_fit(resume=True)` on a tiny plant: each is refused with one line that names the file,
what is wrong and the fix, before anything is fitted or written. Crafted files that
recompute the checksum are stopped by the fit's own checks (ranges, keys, shapes). A file
at the checkpoint's path that pdtool did not write is neither read nor replaced, with or
without --resume; a full or read-only destination ends the fit with one line and no
temporaries.
"""
from __future__ import annotations

import contextlib
import errno
import io
import os
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from pd_tool.fit.checkpoint import (CheckpointError, ForeignCheckpointFile, checkpoint_bytes, is_pdtool_checkpoint,
                                    read_checkpoint)

BIG = 1 << 30  # max_bytes for reads outside a fit
FIX = "; delete it, or fit without --resume"
FOREIGN_FIX = "pdtool neither reads nor replaces it: move it away, or fit to another --out"


# ---------------------------------------------------------------------- the format
def _tree() -> dict:
    return {"a": {0: torch.arange(6, dtype=torch.float32).reshape(2, 3), 7: (0.9, 0.999)},
            "scalar": torch.tensor(3.0), "rng": torch.arange(10, dtype=torch.uint8), "flags": [True, None, "x"],
            "n": 10, "lr": 0.05, "empty": {}, "ints": torch.tensor([1, 2], dtype=torch.int64)}


def _write(path: Path, tree: dict, problem: dict | None = None) -> Path:
    path.write_bytes(checkpoint_bytes(tree, problem or {"k": 1}))
    return path


def _members(path: Path) -> dict[str, bytes]:
    with zipfile.ZipFile(path) as zf:
        return {i.filename: zf.read(i) for i in zf.infolist()}


def _rezip(path: Path, members: dict[str, bytes], compress: int = zipfile.ZIP_STORED) -> None:
    """Write `members` as a zip; `compress` applies to all but the first (which says what the file is)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for i, (name, data) in enumerate(members.items()):
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), data,
                        compress_type=compress if i else zipfile.ZIP_STORED)
    path.write_bytes(buf.getvalue())


def test_round_trip_keeps_types_shapes_and_bits(tmp_path: Path) -> None:
    tree = _tree()
    path = _write(tmp_path / "c.ckpt", tree, {"scene": "abc", "frames": [4]})
    assert is_pdtool_checkpoint(path) == (True, "a pdtool fit checkpoint")
    problem, back = read_checkpoint(path, max_bytes=BIG)
    assert problem == {"scene": "abc", "frames": [4]}
    assert set(back["a"]) == {0, 7} and back["a"][7] == (0.9, 0.999) and isinstance(back["a"][7], tuple)
    assert back["scalar"].shape == () and back["scalar"].dtype == torch.float32
    for k in ("rng", "ints"):
        assert back[k].dtype == tree[k].dtype and torch.equal(back[k], tree[k])
    assert back["a"][0].numpy().tobytes() == tree["a"][0].numpy().tobytes()
    assert back["flags"] == [True, None, "x"] and back["n"] == 10 and back["lr"] == 0.05 and back["empty"] == {}
    # the same state gives the same bytes (no timestamps)
    assert checkpoint_bytes(tree, {"scene": "abc", "frames": [4]}) == path.read_bytes()


def _stale_checksum(path: Path, edit) -> None:
    m = _members(path)
    edited = edit(m["header.json"])
    assert edited != m["header.json"]
    m["header.json"] = edited
    _rezip(path, m)


@pytest.mark.parametrize("name,craft,why", [
    ("checksum", lambda p: _stale_checksum(p, lambda h: h.replace(b'["n", 10]', b'["n", 11]')),
     "sha256 checksum does not match"),
    ("truncated", lambda p: p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2]), "truncated or corrupt"),
    ("compressed", lambda p: _rezip(p, _members(p), zipfile.ZIP_DEFLATED), "compressed or encrypted"),
    ("extra member", lambda p: _rezip(p, {**_members(p), "data.pkl": b"x"}), "not those of a fit checkpoint"),
    ("nan in header", lambda p: _stale_checksum(p, lambda h: h.replace(b'["lr", 0.05]', b'["lr", NaN]')), "checksum"),
])
def test_damaged_files_are_refused(tmp_path: Path, name: str, craft, why: str) -> None:
    path = _write(tmp_path / "c.ckpt", _tree())
    craft(path)
    with pytest.raises(CheckpointError, match=why):
        read_checkpoint(path, max_bytes=BIG)


def _resigned(path: Path, header_edit=None, arrays: dict[str, bytes] | None = None) -> None:
    """Rewrite members and recompute the checksum the way a crafted file would."""
    from pd_tool.fit.checkpoint import _digest

    m = _members(path)
    if header_edit is not None:
        edited = header_edit(m["header.json"])
        assert edited != m["header.json"]
        m["header.json"] = edited
    m.update(arrays or {})
    m.pop("sha256")
    m["sha256"] = _digest(list(m.items())).encode()
    _rezip(path, m)


def _npy(a: np.ndarray, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a, allow_pickle=allow_pickle)
    return buf.getvalue()


def _raw_npy(header: str, data: bytes) -> bytes:
    """A .npy member with any header text (version 1.0), padded as numpy pads it."""
    text = header.encode("latin1")
    pad = 64 - (10 + len(text) + 1) % 64
    text += b" " * pad + b"\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text + data


@pytest.mark.parametrize("name,header_edit,arrays,why", [
    ("nan constant", lambda h: h.replace(b'["lr", 0.05]', b'["lr", NaN]'), None, "holds NaN"),
    ("overflow", lambda h: h.replace(b'["lr", 0.05]', b'["lr", 1e999]'), None, "beyond a float"),
    ("non-finite tag", lambda h: h.replace(b'["lr", 0.05]', b'["lr", {"float": "inf"}]'), None, r"state\.lr holds inf"),
    ("unknown tag", lambda h: h.replace(b'["lr", 0.05]', b'["lr", {"object": "os.system"}]'), None,
     "not a value a checkpoint holds"),
    ("deep", lambda h: h.replace(b'["lr", 0.05]', b'["lr", ' + b"[" * 100 + b"]" * 100 + b"]" ), None, "nested more than"),
    ("very deep", lambda h: h.replace(b'["lr", 0.05]', b'["lr", ' + b"[" * 100000 + b"]" * 100000 + b"]" ), None,
     "(nested more than|not JSON)"),
    ("huge integer", lambda h: h.replace(b'["n", 10]', b'["n", ' + b"9" * 5000 + b"]"), None, "not JSON"),
    ("repeated key", lambda h: h.replace(b'"format":', b'"version": 1, "format":'), None, "repeats a key"),
    ("nan array", None, {"arrays/0.npy": _npy(np.full((2, 3), np.nan, np.float32))}, r"state\.a\.0 holds NaN"),
    ("object array", None, {"arrays/0.npy": _npy(np.array([None, 1], dtype=object), True)}, "holds |O"),
    ("trailing bytes", None, {"arrays/0.npy": _npy(np.zeros((2, 3), np.float32)) + b"\0" * 8}, "holds 32 bytes"),
    ("short data", None, {"arrays/0.npy": _npy(np.zeros((2, 3), np.float32))[:-4]}, "holds 20 bytes"),
    ("other shape", None, {"arrays/0.npy": _npy(np.zeros((3, 2), np.float32))}, "not the array its header lists"),
    ("negative shape", None, {"arrays/0.npy": _raw_npy("{'descr': '<f4', 'fortran_order': False, 'shape': (-2, -3)}",
                                                       b"\0" * 24)}, r"declares the shape \(-2, -3\)"),
    ("code in the header", None, {"arrays/0.npy": _raw_npy("{'descr': __import__('os').getcwd()}", b"")},
     "no readable .npy header"),
])
def test_crafted_files_with_a_good_checksum_are_refused(tmp_path: Path, name, header_edit, arrays, why) -> None:
    path = _write(tmp_path / "c.ckpt", _tree())
    _resigned(path, header_edit, arrays)
    with pytest.raises(CheckpointError, match=why):
        read_checkpoint(path, max_bytes=BIG)


def test_a_file_larger_than_the_fit_writes_is_refused_unread(tmp_path: Path) -> None:
    path = _write(tmp_path / "c.ckpt", _tree())
    with pytest.raises(CheckpointError, match="where this fit writes at most 100"):
        read_checkpoint(path, max_bytes=100)


@pytest.mark.parametrize("what,make", [
    ("a folder", lambda p: p.mkdir()),
    ("a symbolic link", lambda p: p.symlink_to(p.with_name("target"))),
    ("a torch pickle, which pdtool never loads", lambda p: torch.save({"x": 1}, p)),
    ("a zip archive of another kind", lambda p: _rezip(p, {"a.npy": _npy(np.zeros(2))})),
    ("an empty file", lambda p: p.write_bytes(b"")),
    ("not a pdtool file", lambda p: p.write_text("my notes\n")),
])
def test_foreign_files_are_told_apart(tmp_path: Path, what: str, make) -> None:
    path = tmp_path / "c.ckpt"
    make(path)
    assert is_pdtool_checkpoint(path) == (False, what)
    with pytest.raises(ForeignCheckpointFile):
        read_checkpoint(path, max_bytes=BIG)


# ---------------------------------------------------------------------- resume checks
class Interrupt(Exception):
    pass


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """A tiny plant, its video, and two genuine checkpoints written in stage 2 (iteration 1):
    one of the fit the tests resume, one of the same fit with another seed."""
    from _plant import tiny_plant_inputs

    inputs = tiny_plant_inputs(tmp_path_factory.mktemp("ckpt"))
    d = inputs[0]
    genuine = {}
    for seed in (0, 1):
        out = d / f"seed{seed}.pdmat"
        with pytest.raises(Interrupt):
            _fit(inputs, out, stop_at=("material", 2), seed=seed)
        genuine[seed] = out.with_name(out.name + ".ckpt").read_bytes()
    return inputs, genuine


def _fit(inputs, out: Path, stop_at=None, resume: bool = False, seed: int = 0, **kw):
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    d, scene, refs = inputs

    def progress(stage: str, it: int, total: int, loss: float) -> None:
        if (stage, it) == stop_at:
            raise Interrupt

    settings = FitSettings(quality="draft", velocity_iters=2, material_iters=2, working_long_side=24,
                           checkpoint_every=1, seed=seed, stage1_level=False, **kw)
    return run_fit(scene, d / "plant.ply", refs, out, prepare_options=PrepareOptions(static_below=POT_TOP),
                   settings=settings, progress=progress, resume=resume)


def _read_bytes(data: bytes) -> tuple[dict, dict]:
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "c.ckpt"
        path.write_bytes(data)
        return read_checkpoint(path, max_bytes=BIG)


def _craft(data: bytes, edit=None, problem_edit=None) -> bytes:
    """A genuine checkpoint edited and written again with a fresh checksum."""
    problem, state = _read_bytes(data)
    if edit is not None:
        edit(state)
    if problem_edit is not None:
        problem = problem_edit(problem)
    return checkpoint_bytes(state, problem)


def _stale(data: bytes, old: bytes, new: bytes) -> bytes:
    """A genuine checkpoint with its header edited and its checksum left as it was (the zip's
    own CRC is made right, so only the checksum can tell)."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        m = {i.filename: zf.read(i) for i in zf.infolist()}
    assert old in m["header.json"]
    m["header.json"] = m["header.json"].replace(old, new)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for name, body in m.items():
            zf.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), body)
    return buf.getvalue()


def _pop(key):
    return lambda st: st.pop(key)


def _set(key, value):
    return lambda st: st.__setitem__(key, value)


def _nan_residual(st):
    st["residual"] = st["residual"].clone()
    st["residual"][0] = float("nan")


class Boom:
    """Unpickling this creates the marker file: the code a crafted pickle runs."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def _pickle(marker: Path) -> bytes:
    buf = io.BytesIO()
    torch.save({"version": 1, "stage": "material", "boom": Boom(marker)}, buf)
    return buf.getvalue()


RESUME_CASES = [
    # name, bytes from (genuine, marker), what the message says after the path (a regex)
    ("pickle", lambda g, m: _pickle(m),
     r": is not a pdtool fit checkpoint \(a torch pickle, which pdtool never loads\)"),
    ("truncated", lambda g, m: g[0][: len(g[0]) * 2 // 3], r": damaged fit checkpoint: truncated or corrupt .*"),
    ("checksum", lambda g, m: _stale(g[0], b'["iteration", 1]', b'["iteration", 0]'),
     ": damaged fit checkpoint: its sha256 checksum does not match its contents"),
    ("missing keys", lambda g, m: _craft(g[0], _pop("optimizer_r")), ": it lacks optimizer_r"),
    ("nan", lambda g, m: _craft(g[0], _nan_residual), r": damaged fit checkpoint: state\.residual holds NaN/inf"),
    ("key removed", lambda g, m: _craft(g[1], problem_edit=lambda p: {}),
     r": the checkpoint does not say which fit it belongs to \(no problem key\)"),
    ("another fit", lambda g, m: g[1], r": the checkpoint belongs to another fit \(settings differs\)"),
    ("huge iteration", lambda g, m: _craft(g[0], _set("iteration", 10 ** 9)),
     ": iteration 1000000000 is outside this fit's range 0-1"),
    ("negative round", lambda g, m: _craft(g[0], _set("round", -1)), ": round -1 is outside this fit's range 0-0"),
    ("float iteration", lambda g, m: _craft(g[0], _set("iteration", 1.0)), ": iteration 1.0 is outside"),
    ("unknown stage", lambda g, m: _craft(g[0], _set("stage", "polish")),
     ": stage 'polish' is not 'velocity' or 'material'"),
    ("unknown entry", lambda g, m: _craft(g[0], _set("hook", "os.system")), ": it holds unknown entries hook"),
    ("optimizer entry", lambda g, m: _craft(g[0], lambda st: st["optimizer"].__setitem__("hook", 1)),
     ": optimizer is not an optimiser state"),
    ("residual shape", lambda g, m: _craft(g[0], _set("residual", torch.zeros(7))),
     r": residual is torch.float32 \[7\], where this fit has torch.float32 \[\d+\]"),
    ("residual dtype", lambda g, m: _craft(g[0], lambda st: st.__setitem__("residual", st["residual"].double())),
     r": residual is torch.float64 \[\d+\], where this fit has torch.float32"),
    ("field shape", lambda g, m: _craft(g[0], lambda st: st["material"].__setitem__(
        "net.mlp.4.bias", torch.zeros(2))), r": material.net.mlp.4.bias is torch.float32 \[2\]"),
    ("learning rate", lambda g, m: _craft(g[0], lambda st: st["optimizer"]["param_groups"][0].__setitem__("lr", 1e6)),
     r": optimizer's lr is 1000000.0, where this fit has"),
    ("scheduler attribute", lambda g, m: _craft(g[0], lambda st: st["scheduler"].__setitem__("optimizer", None)),
     ": scheduler is not this fit's learning-rate schedule"),
    ("step count", lambda g, m: _craft(g[0], lambda st: st["optimizer"]["state"][0].__setitem__(
        "step", torch.tensor(1e9))), ": optimizer has a step count outside 1-1"),
    ("kept state", lambda g, m: _craft(g[0], _pop("kept_residual")), ": it lacks kept_residual"),
    ("kept iteration", lambda g, m: _craft(g[0], _set("kept_at", torch.tensor([0.01, 7.0], dtype=torch.float64))),
     r": kept_at names iteration 7, where by iteration 1 this fit has measured at \[0\]"),
    ("kept loss", lambda g, m: _craft(g[0], _set("kept_at", torch.tensor([0.01, 0.0], dtype=torch.float64))),
     r": kept_at names iteration 0 at the whole-clip loss 0\.01, where this round's measures rank iteration 0 "
     r"first, at [0-9.e-]+;"),
    ("loss history", lambda g, m: _craft(g[0], lambda st: st["losses"].__setitem__(
        "material", torch.zeros(5, dtype=torch.float64))), r": losses\.material is torch\.float64 \[5\]"),
]


@pytest.mark.parametrize("name,make,message", RESUME_CASES, ids=[c[0] for c in RESUME_CASES])
def test_resume_refuses_a_crafted_or_foreign_checkpoint(plant, tmp_path: Path, name, make, message) -> None:
    from pd_tool.core.errors import PdToolError

    inputs, genuine = plant
    marker = tmp_path / "marker"
    out = tmp_path / "fit.pdmat"
    ckpt = out.with_name(out.name + ".ckpt")
    data = make(genuine, marker)
    ckpt.write_bytes(data)
    with pytest.raises(PdToolError) as err:
        _fit(inputs, out, resume=True)
    text = str(err.value)
    assert "\n" not in text
    import re

    assert re.match(re.escape(str(ckpt)) + message, text), text
    assert text.endswith(FOREIGN_FIX if name == "pickle" else FIX), text
    assert not marker.exists()  # no code ran
    assert ckpt.read_bytes() == data  # left as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == [ckpt.name]  # nothing written, no temporaries


def test_the_genuine_checkpoint_resumes(plant, tmp_path: Path) -> None:
    """The crafts above start from this file: unedited, it resumes and is removed at the end."""
    inputs, genuine = plant
    out = tmp_path / "fit.pdmat"
    ckpt = out.with_name(out.name + ".ckpt")
    ckpt.write_bytes(genuine[0])
    res = _fit(inputs, out, resume=True)
    assert out.is_file() and not ckpt.exists()
    assert len(res.losses["material"]) == 2


def test_a_checkpoint_at_a_borrowed_measure_point_resumes_to_the_same_fit(plant, tmp_path: Path) -> None:
    """With keep_best_every 1, the state after stage 2's first step is measured by the second
    iteration's own loss (borrowed_points), which a checkpoint taken after that step has not
    run: resumed there, the fit measures it and ends as the uninterrupted fit does."""
    inputs, _ = plant
    whole = _fit(inputs, tmp_path / "whole.pdmat", keep_best_every=1)
    out = tmp_path / "cut.pdmat"
    with pytest.raises(Interrupt):
        _fit(inputs, out, stop_at=("material", 2), keep_best_every=1)
    ckpt = out.with_name(out.name + ".ckpt")
    _, state = read_checkpoint(ckpt, max_bytes=BIG)
    assert state["stage"] == "material" and state["iteration"] == 1
    assert len(state["losses"]["whole_clip"]) == 1  # the start only: point 1 is the next iteration's to measure
    res = _fit(inputs, out, resume=True, keep_best_every=1)
    assert not ckpt.exists()
    assert len(res.losses["whole_clip"]) == 3 and res.losses["whole_clip"][1] == res.losses["material"][1]
    np.testing.assert_allclose(res.losses["whole_clip"], whole.losses["whole_clip"], rtol=1e-6)
    assert res.losses["kept"] == whole.losses["kept"]
    np.testing.assert_allclose(res.driver_E, whole.driver_E, rtol=1e-6)


@pytest.mark.parametrize("horizon", [None, 1])
def test_a_checkpoint_at_stage_2s_start_resumes_to_the_same_fit(plant, tmp_path: Path, horizon) -> None:
    """Where stage 2's first iteration back-propagates through every frame its own loss is
    the start's measure (FitSettings.borrows_start): the checkpoint taken as the stage begins
    holds no measure or kept state yet, and resumed there the fit measures its start and ends
    as the uninterrupted fit does. With a one-frame horizon the start is simulated on its own
    first, and the checkpoint carries it."""
    inputs, _ = plant
    kw = dict(keep_best_every=1, material_horizon=horizon)
    whole = _fit(inputs, tmp_path / "whole.pdmat", **kw)
    out = tmp_path / "cut.pdmat"
    with pytest.raises(Interrupt):
        _fit(inputs, out, stop_at=("material", 1), **kw)
    ckpt = out.with_name(out.name + ".ckpt")
    _, state = read_checkpoint(ckpt, max_bytes=BIG)
    assert state["stage"] == "material" and state["iteration"] == 0
    assert ("kept_at" in state) == ("start" in state["losses"]) == ("whole_clip" in state["losses"]) == (horizon == 1)
    res = _fit(inputs, out, resume=True, **kw)
    assert not ckpt.exists()
    for k in ("start", "whole_clip", "kept", "final"):
        np.testing.assert_allclose(res.losses[k], whole.losses[k], rtol=1e-6)
    np.testing.assert_allclose(res.driver_E, whole.driver_E, rtol=1e-6)
    if horizon is None:
        assert res.losses["start"] == res.losses["material"][:1]


def _nan_measure(st):
    st["losses"]["whole_clip"] = torch.full_like(st["losses"]["whole_clip"], float("nan"))
    st["kept_at"] = torch.tensor([float("nan"), 0.0], dtype=torch.float64)


def test_a_checkpoint_whose_whole_clip_measure_is_nan_resumes(plant, tmp_path: Path) -> None:
    """A whole-clip measure of a diverged state is NaN, and so is the kept state's loss
    until a measure beats it: such a checkpoint is the fit's own record, and resumes. NaN
    where a state is kept (the kept iteration, the weights) is still damage."""
    from pd_tool.core.errors import PdToolError

    inputs, genuine = plant
    out = tmp_path / "fit.pdmat"
    ckpt = out.with_name(out.name + ".ckpt")
    assert genuine[0] != _craft(genuine[0], _nan_measure)
    ckpt.write_bytes(_craft(genuine[0], _nan_measure))
    res = _fit(inputs, out, resume=True)
    assert out.is_file() and not ckpt.exists()
    assert np.isnan(res.losses["whole_clip"][0]) and np.isfinite(res.losses["whole_clip"][-1])
    for edit, message in ((_set("kept_at", torch.tensor([0.01, float("nan")], dtype=torch.float64)),
                           "kept_at names iteration nan"),
                          (_nan_residual, r"state\.residual holds NaN/inf")):
        out.unlink(missing_ok=True)
        ckpt.write_bytes(_craft(genuine[0], edit))
        with pytest.raises(PdToolError, match=message):
            _fit(inputs, out, resume=True)


@pytest.mark.parametrize("resume", [False, True])
@pytest.mark.parametrize("kind", ["user file", "folder", "pickle"])
def test_a_foreign_file_at_the_checkpoint_path_is_kept(plant, tmp_path: Path, kind: str, resume: bool) -> None:
    """A file pdtool did not write, where the fit keeps its checkpoint: refused before any work,
    neither overwritten nor deleted, with or without --resume."""
    from pd_tool.core.errors import PdToolError

    inputs, _ = plant
    out = tmp_path / "fit.pdmat"
    ckpt = out.with_name(out.name + ".ckpt")
    marker = tmp_path / "marker"
    if kind == "folder":
        ckpt.mkdir()
        (ckpt / "precious.txt").write_text("mine")
    else:
        ckpt.write_bytes(b"my precious notes\n" if kind == "user file" else _pickle(marker))
    before = ckpt.read_bytes() if ckpt.is_file() else None
    with pytest.raises(PdToolError, match="is not a pdtool fit checkpoint.*pdtool neither reads nor replaces it"):
        _fit(inputs, out, resume=resume)
    if kind == "folder":
        assert (ckpt / "precious.txt").read_text() == "mine"
    else:
        assert ckpt.read_bytes() == before
    assert not out.exists() and not marker.exists()


def test_an_own_stale_checkpoint_is_replaced_without_resume(plant, tmp_path: Path) -> None:
    inputs, genuine = plant
    out = tmp_path / "fit.pdmat"
    ckpt = out.with_name(out.name + ".ckpt")
    ckpt.write_bytes(genuine[1])  # another fit's: pdtool's own file, so a fresh fit may replace it
    _fit(inputs, out)
    assert out.is_file() and not ckpt.exists()


# ---------------------------------------------------------------------- through the CLI
FIT_ARGS = ["fit", "plant.ply", "video", "-o", "fit.pdmat", "--static-below", "0.2", "--quality", "draft",
            "--velocity-iters", "1", "--material-iters", "2", "--working-size", "24", "--device", "cpu",
            "--no-preview"]


def _cli(args: list[str], cwd: Path, monkeypatch):
    from click.testing import CliRunner

    from cli import main

    import cli
    from tqdm import tqdm

    monkeypatch.chdir(cwd)
    # the progress bar's lines are the CLI's to clear; here only the error line counts
    monkeypatch.setattr(cli, "_tqdm", lambda *a, **k: tqdm(disable=True), raising=False)
    return CliRunner().invoke(main, args)


def _workdir(plant, tmp_path: Path, name: str = "work") -> Path:
    import shutil

    (d, _, _), _ = plant
    w = tmp_path / name
    w.mkdir()
    shutil.copy(d / "plant.ply", w / "plant.ply")
    shutil.copytree(d / "video", w / "video")
    return w


def _left(w: Path) -> list[str]:
    return sorted(p.relative_to(w).as_posix() for p in w.rglob("*") if not p.relative_to(w).as_posix().startswith("video"))


@pytest.mark.parametrize("resume", [[], ["--resume"]])
def test_cli_refuses_a_pickle_checkpoint_in_one_line_and_runs_nothing(plant, tmp_path: Path, monkeypatch,
                                                                      resume) -> None:
    w = _workdir(plant, tmp_path)
    marker = tmp_path / "marker"
    data = _pickle(marker)
    (w / "fit.pdmat.ckpt").write_bytes(data)
    res = _cli(FIT_ARGS + resume, w, monkeypatch)
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: fit.pdmat.ckpt: is not a pdtool fit checkpoint"), lines
    assert not marker.exists()
    assert (w / "fit.pdmat.ckpt").read_bytes() == data
    assert _left(w) == ["fit.pdmat.ckpt", "plant.ply"]


@contextlib.contextmanager
def _small_mount(path: Path, options: str):
    """A tmpfs at `path` (root only); yields False when one cannot be mounted here."""
    path.mkdir()
    if os.geteuid() != 0:
        yield False
        return
    ok = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True).returncode == 0
    try:
        yield ok
    finally:
        if ok:
            subprocess.run(["umount", str(path)], check=True)


@contextlib.contextmanager
def _no_mount(path: Path):
    path.mkdir()
    yield False


@pytest.mark.parametrize("how", ["tmpfs", "injected"])
@pytest.mark.parametrize("kind", ["full", "read-only"])
def test_cli_full_or_read_only_destination_ends_in_one_line(plant, tmp_path: Path, monkeypatch, kind: str,
                                                            how: str) -> None:
    """A real tmpfs where this runs as root (else, and always for "injected", the OSError a
    full or read-only file system raises)."""
    w = _workdir(plant, tmp_path)
    dest = w / "dest"
    options = "size=64k" if kind == "full" else "ro"
    with (_small_mount(dest, options) if how == "tmpfs" else _no_mount(dest)) as mounted:
        if not mounted:  # inject what the file system would say
            code = errno.ENOSPC if kind == "full" else errno.EROFS
            if kind == "full":
                real = Path.write_bytes

                def write_bytes(self, data):
                    if ".ckpt." in self.name:
                        raise OSError(code, os.strerror(code), str(self))
                    return real(self, data)

                monkeypatch.setattr(Path, "write_bytes", write_bytes)
            else:
                import tempfile

                def mkstemp(*a, dir=None, **k):
                    if dir is not None and Path(dir).resolve() == dest.resolve():
                        raise OSError(code, os.strerror(code), str(dir))
                    return real_mkstemp(*a, dir=dir, **k)

                real_mkstemp = tempfile.mkstemp
                monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
        args = [a if a != "fit.pdmat" else "dest/fit.pdmat" for a in FIT_ARGS]
        res = _cli(args, w, monkeypatch)
        left = sorted(p.name for p in dest.iterdir())
    assert res.exit_code == 2, res.output
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), lines
    expect = "No space left on device" if kind == "full" else "Read-only file system"
    assert "dest" in lines[0] and expect in lines[0] and "writable folder" in lines[0], lines
    assert left == [], left  # no temporaries, no partial checkpoint


def test_mutated_files_end_in_one_line_error(tmp_path: Path) -> None:
    """Seeded random edits (bytes flipped, cut or inserted; JSON tokens spliced into the
    header and the checksum recomputed): every read either succeeds or raises one
    CheckpointError line, never another exception."""
    import random

    from pd_tool.fit.checkpoint import _digest

    rnd = random.Random(35)
    good = checkpoint_bytes(_tree(), {"k": 1})
    path = tmp_path / "c.ckpt"
    _write(path, _tree())
    members = _members(path)
    tokens = [b"{", b"}", b"[", b"]", b'"dict"', b'"tensor"', b'"tuple"', b'"float"', b"-1", b"1e999", b"NaN",
              b",", b":", b"null", b"true", b"99999999999", b"'", b"("]
    refused = 0
    for i in range(400):
        if i % 2:  # the file's bytes
            b = bytearray(good)
            j = rnd.randrange(len(b))
            b[j:j + rnd.randint(0, 2)] = bytes(rnd.randrange(256) for _ in range(rnd.randint(0, 3)))
            data = bytes(b[: len(b) if rnd.random() < 0.8 else rnd.randrange(len(b))])
            path.write_bytes(data)
        else:  # one member, then signed again
            m = dict(members)
            name = rnd.choice([n for n in m if n.startswith("arrays/") or n == "header.json"])
            b = bytearray(m[name])
            for _ in range(rnd.randint(1, 3)):
                j = rnd.randrange(len(b) + 1)
                b[j:j + rnd.randint(0, 3)] = rnd.choice(tokens) if rnd.random() < 0.7 else bytes([rnd.randrange(256)])
            m[name] = bytes(b)
            m.pop("sha256")
            m["sha256"] = _digest(list(m.items())).encode()
            _rezip(path, m)
        try:
            read_checkpoint(path, max_bytes=BIG)
        except CheckpointError as e:
            assert "\n" not in str(e) and str(e).startswith(str(path)), str(e)
            refused += 1
    assert refused > 300  # most edits break the file (edits of array data bytes may not)
