"""UsdBakeWriter: what lands in the file, atomic output, streaming, validation."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")
from pxr import Sdf, Usd, UsdGeom  # noqa: E402

from pd_tool.core.errors import OutputError, UsdExportError  # noqa: E402
from usd_export import UsdBakeWriter, validate_usd  # noqa: E402
from usd_export._geom import normalize_quats  # noqa: E402

N = 300
FRAMES = 6
HALF_QUAT_TOL = 1e-3  # quath: 11-bit mantissa, |q_i| <= 1


def synthetic_bake(n: int = N, frames: int = FRAMES, seed: int = 0, sh_k: int = 16):
    """Known trajectories: each point moves on its own circle and its sigma breathes."""
    rng = np.random.default_rng(seed)
    x0 = rng.normal(size=(n, 3)).astype(np.float32)
    phase = rng.uniform(0, 2 * np.pi, n)
    q0 = normalize_quats(rng.normal(size=(n, 4)).astype(np.float32))
    s0 = rng.uniform(0.01, 0.05, (n, 3)).astype(np.float32)
    pos, quats, sig = [], [], []
    for f in range(frames):
        a = 0.3 * f + phase
        pos.append(x0 + 0.2 * np.stack([np.cos(a), np.sin(a), 0.1 * f * np.ones(n)], 1).astype(np.float32))
        half = 0.05 * f  # rotation about z by 0.1 f rad, composed with q0
        rz = np.array([np.cos(half), 0, 0, np.sin(half)], np.float32)
        w1, x1, y1, z1 = rz
        w2, x2, y2, z2 = q0.T
        quats.append(np.stack([w1 * w2 - z1 * z2, w1 * x2 - z1 * y2, w1 * y2 + z1 * x2,
                               w1 * z2 + z1 * w2], 1).astype(np.float32))
        sig.append(s0 * (1 + 0.05 * f))
    sh = (rng.normal(size=(n, sh_k, 3)) * 0.3).astype(np.float32)
    opac = rng.uniform(0.05, 1, n).astype(np.float32)
    return np.stack(pos), np.stack(quats), np.stack(sig), sh, opac


def write(path: Path, data, *, fmt="both", start=1, hold_to=None, **kw) -> Path:
    pos, quats, sig, sh, opac = data
    with UsdBakeWriter(path, n_points=pos.shape[1], fps=30, start_frame=start, fmt=fmt,
                       sh=sh, opacities=opac, **kw) as w:
        for f in range(pos.shape[0]):
            w.write_frame(start + f, pos[f], quats[f], sig[f])
        if hold_to is not None:
            w.hold_frames(hold_to)
    return path


def assert_box_bounds(ext: np.ndarray, p: np.ndarray, radii: np.ndarray) -> None:
    """An ellipsoid's box half size lies between its smallest and largest radius."""
    r_min, r_max = radii.min(1, keepdims=True), radii.max(1, keepdims=True)
    assert (ext[0] <= (p - r_min).min(0)).all() and (ext[1] >= (p + r_min).max(0)).all()
    assert (ext[0] >= (p - r_max).min(0) - 1e-6).all() and (ext[1] <= (p + r_max).max(0) + 1e-6).all()


@pytest.fixture(scope="module")
def data():
    return synthetic_bake()


@pytest.fixture(scope="module")
def both_file(tmp_path_factory, data):
    return write(tmp_path_factory.mktemp("usd") / "bake.usd", data, hold_to=FRAMES + 10)


def test_stage_metadata(both_file):
    stage = Usd.Stage.Open(str(both_file))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30 and stage.GetFramesPerSecond() == 30
    assert stage.GetStartTimeCode() == 1
    assert stage.GetEndTimeCode() == FRAMES + 10  # the hold is covered
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Root")
    # a single self-contained file: no sidecars, no temporaries left
    assert sorted(p.name for p in both_file.parent.iterdir()) == ["bake.usd"]


def test_instancer_samples_equal_written(both_file, data):
    pos, quats, sig, sh, opac = data
    stage = Usd.Stage.Open(str(both_file))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    assert inst.GetPositionsAttr().GetTimeSamples() == list(range(1, FRAMES + 1))
    for f in (0, FRAMES - 1):
        t = 1 + f
        np.testing.assert_array_equal(np.asarray(inst.GetPositionsAttr().Get(t)), pos[f])
        q = np.asarray(inst.GetOrientationsAttr().Get(t)).astype(np.float32)  # x, y, z, w
        np.testing.assert_allclose(q[:, [3, 0, 1, 2]], quats[f], atol=HALF_QUAT_TOL)
        np.testing.assert_allclose(np.asarray(inst.GetScalesAttr().Get(t)), 2.0 * sig[f], rtol=1e-6)
        assert_box_bounds(np.asarray(inst.GetExtentAttr().Get(t)), pos[f], 2 * sig[f])
    assert inst.GetOrientationsAttr().GetTypeName() == Sdf.ValueTypeNames.QuathArray
    assert not inst.GetPrim().GetAttribute("orientationsf").HasAuthoredValue()
    # written once, not per frame
    for attr in (inst.GetProtoIndicesAttr(), inst.GetIdsAttr()):
        assert attr.GetNumTimeSamples() == 0 and len(attr.Get()) == N
    np.testing.assert_array_equal(np.asarray(inst.GetIdsAttr().Get()), np.arange(N))
    proto = inst.GetPrototypesRel().GetTargets()
    assert proto == [Sdf.Path("/Root/Instancer/Prototypes/Sphere")]
    assert UsdGeom.Sphere(stage.GetPrimAtPath(proto[0])).GetRadiusAttr().Get() == 1.0
    pv = UsdGeom.PrimvarsAPI(inst)
    assert pv.GetPrimvar("displayColor").GetInterpolation() == UsdGeom.Tokens.vertex
    assert len(pv.GetPrimvar("displayColor").Get()) == N
    np.testing.assert_allclose(np.asarray(pv.GetPrimvar("displayOpacity").Get()), opac)


@pytest.mark.parametrize("threaded", [False, True])
def test_float64_and_strided_frames(tmp_path, data, threaded):
    """A simulation hands float64 or strided arrays; the writer converts them to float32
    with or without its thread (numpy 2 refuses a conversion asked to avoid copies)."""
    pos, quats, sig, _, _ = data
    path = tmp_path / "f64.usd"
    with UsdBakeWriter(path, n_points=N, fps=30, fmt="instancer", threaded=threaded) as w:
        for f in range(2):
            wide = np.concatenate([pos[f], pos[f]], axis=1).astype(np.float64)  # [N, 6]
            w.write_frame(f, wide[:, :3], quats[f].astype(np.float64), sig[f].astype(np.float64))
    stage = Usd.Stage.Open(str(path))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    for f in range(2):
        np.testing.assert_array_equal(np.asarray(inst.GetPositionsAttr().Get(f)), pos[f])
        np.testing.assert_allclose(np.asarray(inst.GetScalesAttr().Get(f)), 2.0 * sig[f], rtol=1e-6)


def test_held_frames_keep_last_pose(both_file, data):
    pos = data[0]
    stage = Usd.Stage.Open(str(both_file))
    attr = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer")).GetPositionsAttr()
    np.testing.assert_array_equal(np.asarray(attr.Get(FRAMES + 10)), pos[-1])


def test_write_after_hold_does_not_blend_into_the_hold(tmp_path, data):
    pos, quats, sig, sh, opac = data
    path = tmp_path / "h.usd"
    with UsdBakeWriter(path, n_points=N, fps=30, start_frame=0, sh=sh) as w:
        w.write_frame(0, pos[0], quats[0], sig[0])
        w.hold_frames(5)
        w.write_frame(6, pos[1], quats[1], sig[1])
    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/Root/Instancer").GetAttribute("positions")
    # between the pose and its re-authored copy at 5, interpolation is the pose (to 1 ulp)
    np.testing.assert_allclose(np.asarray(attr.Get(4.5)), pos[0], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(attr.Get(5)), pos[0])
    np.testing.assert_array_equal(np.asarray(attr.Get(6)), pos[1])


def test_points_companion_carries_colour(both_file, data):
    pos = data[0]
    stage = Usd.Stage.Open(str(both_file))
    pts = UsdGeom.Points(stage.GetPrimAtPath("/Root/SplatColors"))
    np.testing.assert_array_equal(np.asarray(pts.GetPointsAttr().Get(3)), pos[2])
    inst_col = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Root/Instancer")).GetPrimvar("displayColor").Get()
    np.testing.assert_array_equal(np.asarray(pts.GetDisplayColorPrimvar().Get()), np.asarray(inst_col))
    assert len(pts.GetWidthsAttr().Get()) == N


def test_display_color_is_linear(tmp_path, data):
    """3DGS colours are sRGB encoded; USD's displayColor is linear, so every prim that
    carries it gets the sRGB EOTF of the colour (Blender showed them washed out)."""
    from usd_export._geom import sh_dc_to_rgb, srgb_to_linear
    pos, quats, sig, sh, opac = data
    path = write(tmp_path / "c.usd", data)
    stage = Usd.Stage.Open(str(path))
    want = srgb_to_linear(sh_dc_to_rgb(sh[:, 0]))
    for prim in ("/Root/Instancer", "/Root/SplatColors", "/Root/Splats"):
        got = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath(prim)).GetPrimvar("displayColor").Get()
        np.testing.assert_allclose(np.asarray(got), want, rtol=0, atol=1e-7)
    assert not np.allclose(want, sh_dc_to_rgb(sh[:, 0]), atol=0.05)  # the test can tell them apart


def test_splat_schema_layout(both_file, data):
    from pxr import UsdVol
    pos, quats, sig, sh, opac = data
    stage = Usd.Stage.Open(str(both_file))
    field = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/Root/Splats"))
    assert field
    assert field.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 3
    coeffs = np.asarray(field.GetRadianceSphericalHarmonicsCoefficientsAttr().Get())
    # per splat its 16 RGB coefficients contiguously, DC first
    np.testing.assert_array_equal(coeffs.reshape(N, 16, 3), sh)
    np.testing.assert_array_equal(np.asarray(field.GetOpacitiesAttr().Get()), opac)
    assert field.GetOpacitiesAttr().GetNumTimeSamples() == 0
    for f in (1, 4):
        t = 1 + f
        np.testing.assert_array_equal(np.asarray(field.GetPositionsAttr().Get(t)), pos[f])
        np.testing.assert_array_equal(np.asarray(field.GetScalesAttr().Get(t)), sig[f])  # sigma, unscaled
        assert not field.GetOrientationsAttr().HasAuthoredValue()  # quath: orientationsh
        q = np.asarray(field.GetOrientationshAttr().Get(t)).astype(np.float32)
        np.testing.assert_allclose(q[:, [3, 0, 1, 2]], quats[f], atol=HALF_QUAT_TOL)
        # box of the 3-sigma ellipsoids
        assert_box_bounds(np.asarray(field.GetExtentAttr().Get(t)), pos[f], 3 * sig[f])


def test_validate_clean_file_has_no_errors(both_file):
    assert isinstance(validate_usd(both_file), list)


@pytest.mark.parametrize("fmt,prims", [("instancer", {"Instancer", "SplatColors"}),
                                       ("splat", {"Splats"})])
def test_formats(tmp_path, data, fmt, prims):
    path = write(tmp_path / f"{fmt}.usdc", data, fmt=fmt)
    stage = Usd.Stage.Open(str(path))
    assert {p.GetName() for p in stage.GetDefaultPrim().GetChildren()} == prims


def test_usda_output_and_torch_inputs(tmp_path, data):
    torch = pytest.importorskip("torch")
    pos, quats, sig, sh, opac = data
    path = tmp_path / "t.usda"
    with UsdBakeWriter(path, n_points=N, fps=24, fmt="both", sh=torch.from_numpy(sh),
                       opacities=torch.from_numpy(opac), up_axis="Y", meters_per_unit=0.01) as w:
        for f in range(2):
            w.write_frame(f, torch.from_numpy(pos[f]), torch.from_numpy(quats[f]),
                          torch.from_numpy(sig[f]))
    assert path.read_text()[:10] == "#usda 1.0\n"
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01


def test_exception_inside_with_leaves_nothing(tmp_path, data):
    pos, quats, sig, sh, opac = data
    path = tmp_path / "fail.usd"
    path.write_bytes(b"previous bake")  # an older result must survive a failed bake
    with pytest.raises(RuntimeError, match="guard"):
        with UsdBakeWriter(path, n_points=N, fps=30, sh=sh) as w:
            w.write_frame(0, pos[0], quats[0], sig[0])
            raise RuntimeError("stability guard stopped the bake")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fail.usd"]
    assert path.read_bytes() == b"previous bake"


def test_bad_frames_raise_and_clean_up(tmp_path, data):
    pos, quats, sig, sh, opac = data
    path = tmp_path / "bad.usd"
    bad = pos[0].copy()
    bad[3, 1] = np.nan
    with pytest.raises(UsdExportError, match="NaN"):
        with UsdBakeWriter(path, n_points=N, fps=30) as w:
            w.write_frame(0, bad, quats[0], sig[0])
    assert list(tmp_path.iterdir()) == []
    w = UsdBakeWriter(path, n_points=N, fps=30)
    with pytest.raises(UsdExportError, match=r"shape \(299, 3\)"):
        w.write_frame(0, pos[0][:-1], quats[0], sig[0])
    w.write_frame(0, pos[0], quats[0], sig[0])
    with pytest.raises(UsdExportError, match="increase"):
        w.write_frame(0, pos[0], quats[0], sig[0])
    with pytest.raises(UsdExportError, match="> 0"):
        w.write_frame(1, pos[0], quats[0], -sig[0])
    w.abort()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kw,match", [
    (dict(fmt="mesh"), "format"), (dict(up_axis="X"), "up_axis"), (dict(fps=0), "fps"),
    (dict(opacities=np.full(N, 2.0)), "0-1"), (dict(sh=np.zeros((N, 5, 3))), "degree"),
    (dict(ids=np.zeros(N)), "distinct")])
def test_bad_arguments(tmp_path, kw, match):
    args = dict(n_points=N, fps=30) | kw
    with pytest.raises(UsdExportError, match=match):
        UsdBakeWriter(tmp_path / "x.usd", **args)
    assert list(tmp_path.iterdir()) == []


def test_bad_suffix(tmp_path):
    with pytest.raises(UsdExportError, match=r"\.usda"):
        UsdBakeWriter(tmp_path / "x.abc", n_points=3, fps=30)
    assert list(tmp_path.iterdir()) == []


def test_streams_samples_to_disk_while_writing(tmp_path, data):
    pos, quats, sig, sh, opac = data
    w = UsdBakeWriter(tmp_path / "s.usd", n_points=N, fps=30, fmt="both", sh=sh, flush_bytes=1)
    sizes = []
    for f in range(3):
        w.write_frame(f, pos[f], quats[f], sig[f])
        sizes.append(w._tmp.stat().st_size)
    # every frame is appended to the temporary crate file as it is written; the
    # crate stores equal arrays once, so positions count once for all three prims:
    # positions 12 + quath 8 (the splat's orientationsh too) + instancer scales 12 +
    # sigmas 12 bytes (the sigmas change every frame here)
    per_frame = N * (12 + 8 + 12 + 12)
    assert sizes[1] - sizes[0] >= per_frame and sizes[2] - sizes[1] >= per_frame
    assert not (tmp_path / "s.usd").exists()
    w.close()
    assert (tmp_path / "s.usd").exists()


def test_validate_rejects_broken_files(tmp_path):
    bad = tmp_path / "bad.usda"
    bad.write_text('''#usda 1.0
(
    defaultPrim = "Root"
)
def Xform "Root"
{
    def PointInstancer "I"
    {
        point3f[] positions.timeSamples = { 1: [(0, 0, 0), (5, 0, 0)] }
        quath[] orientations.timeSamples = { 1: [(1, 0, 0, 0), (2, 0, 0, 0)] }
        float3[] scales.timeSamples = { 1: [(1, 1, 1)] }
        float3[] extent.timeSamples = { 1: [(-1, -1, -1), (1, 1, 1)] }
        int[] protoIndices = [0, 0]
        rel prototypes = </Root/I/P/S>
        def Scope "P"
        {
            def Sphere "S"
            {
            }
        }
    }
}
''')
    with pytest.raises(UsdExportError) as e:
        validate_usd(bad)
    msg = str(e.value)
    for needle in ("upAxis", "metersPerUnit", "timeCodesPerSecond", "scales has 1 elements",
                   "not unit length", "does not contain"):
        assert needle in msg, (needle, msg)
    assert "\n" not in msg


def test_validate_runs_pxr_validators(tmp_path):
    # A composition error (a reference to a missing file) is caught by
    # UsdValidation's CompositionErrorTest / MissingReferenceValidator, not by us.
    bad = tmp_path / "ref.usda"
    bad.write_text('''#usda 1.0
(
    defaultPrim = "Root"
    upAxis = "Z"
    metersPerUnit = 1
    timeCodesPerSecond = 30
    framesPerSecond = 30
    startTimeCode = 0
    endTimeCode = 0
)
def Xform "Root" ( prepend references = @./missing_file.usd@ ) {}
''')
    with pytest.raises(UsdExportError, match=r"\[(CompositionError|UnresolvableDependency)\]"):
        validate_usd(bad)
    assert validate_usd(bad, usd_validators=False) == []


def test_not_a_usd_file(tmp_path):
    p = tmp_path / "x.usd"
    p.write_bytes(b"\x00garbage")
    with pytest.raises(UsdExportError, match="not a readable USD"):
        validate_usd(p)


def test_import_is_lazy():
    # pxr loads only when the writer or validator is first used (design: heavy
    # imports on use); a subprocess sees a clean sys.modules.
    import subprocess
    import sys
    code = ("import sys, usd_export; assert 'pxr' not in sys.modules; "
            "usd_export.UsdBakeWriter; assert 'pxr' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_dropped_writer_removes_its_temporary(tmp_path, data):
    import gc
    pos, quats, sig, sh, opac = data
    w = UsdBakeWriter(tmp_path / "dropped.usd", n_points=N, fps=30)
    w.write_frame(0, pos[0], quats[0], sig[0])
    assert len(list(tmp_path.iterdir())) == 1  # the hidden temporary
    del w
    gc.collect()
    assert list(tmp_path.iterdir()) == []


def test_usd_instance_transforms_match_our_convention(both_file, data):
    # USD's own instancer math (quath -> rotation, scale, translation) must put the
    # unit sphere where we meant it: R(q) diag(2 sigma) u + p, in row-vector form.
    from pd_tool.core.quaternion import quat_to_matrix_np
    pos, quats, sig, sh, opac = data
    stage = Usd.Stage.Open(str(both_file))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    f = 3
    mats = inst.ComputeInstanceTransformsAtTime(Usd.TimeCode(1 + f), Usd.TimeCode(1 + f))
    m = np.array([np.array(x) for x in mats])  # [N, 4, 4], row vectors: v' = v M
    want = quat_to_matrix_np(quats[f]) * (2.0 * sig[f])[:, None, :]  # column form R S
    np.testing.assert_allclose(m[:, :3, :3].transpose(0, 2, 1), want, atol=2e-3 * sig[f].max())
    np.testing.assert_allclose(m[:, 3, :3], pos[f], atol=1e-6)
    # and USD's bound (prototype box through these transforms) contains ours
    usd_box = np.asarray(inst.ComputeExtentAtTime(Usd.TimeCode(1 + f), Usd.TimeCode(1 + f)))
    ours = np.asarray(inst.GetExtentAttr().Get(1 + f))
    assert (usd_box[0] <= ours[0] + 1e-6).all() and (ours[1] <= usd_box[1] + 1e-6).all()


def test_threaded_writes_the_same_file(tmp_path, data):
    pos, quats, sig, sh, opac = data
    a = write(tmp_path / "sync.usd", data, hold_to=FRAMES + 3)
    b = write(tmp_path / "thread.usd", data, hold_to=FRAMES + 3, threaded=True, flush_bytes=1)
    sa, sb = Usd.Stage.Open(str(a)), Usd.Stage.Open(str(b))
    assert sb.GetEndTimeCode() == sa.GetEndTimeCode() == FRAMES + 3
    for prim_path, attr in (("/Root/Instancer", "positions"), ("/Root/Instancer", "orientations"),
                            ("/Root/Splats", "scales"), ("/Root/SplatColors", "extent")):
        x, y = sa.GetPrimAtPath(prim_path).GetAttribute(attr), sb.GetPrimAtPath(prim_path).GetAttribute(attr)
        assert x.GetTimeSamples() == y.GetTimeSamples()
        for t in x.GetTimeSamples():
            np.testing.assert_array_equal(np.asarray(x.Get(t)), np.asarray(y.Get(t)))


def test_threaded_copies_inputs(tmp_path, data):
    pos, quats, sig, sh, opac = data
    buf = pos[0].copy()
    path = tmp_path / "copy.usd"
    with UsdBakeWriter(path, n_points=N, fps=30, threaded=True) as w:
        for f in range(3):
            buf[:] = pos[f]  # the caller reuses one buffer, as a solver would
            w.write_frame(f, buf, quats[f], sig[f])
    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/Root/Instancer").GetAttribute("positions")
    for f in range(3):
        np.testing.assert_array_equal(np.asarray(attr.Get(f)), pos[f])


@pytest.mark.parametrize("threaded", [False, True])
def test_failed_save_raises_and_leaves_nothing(tmp_path, data, threaded):
    import shutil
    pos, quats, sig, sh, opac = data
    folder = tmp_path / "out"
    folder.mkdir()
    # pxr's error text depends on the platform and on when the save meets the missing
    # folder: with an OS error in it the writer says "cannot write" (OutputError), else it
    # passes pxr's words on (UsdExportError). Either is one line naming the file.
    with pytest.raises((UsdExportError, OutputError),
                       match=r"x\.usd.*(writing the USD file failed.*Unable to open|cannot write)") as e:
        with UsdBakeWriter(folder / "x.usd", n_points=N, fps=30, flush_bytes=1,
                           threaded=threaded) as w:
            w.write_frame(0, pos[0], quats[0], sig[0])
            shutil.rmtree(folder)  # the output folder disappears mid-bake
            w.write_frame(1, pos[1], quats[1], sig[1])
    assert "\n" not in str(e.value) and "pxrInternal" not in str(e.value)
    # USD's writer may recreate the folder; it must hold no result and no temporary
    assert not folder.exists() or list(folder.iterdir()) == []


def test_unwritable_folder(tmp_path):
    # root writes into read-only folders, but not into /proc
    if os.geteuid() == 0:
        if not Path("/proc").is_dir():
            pytest.skip("no unwritable folder available to root")
        target = Path("/proc/x.usd")
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        target = ro / "x.usd"
    try:
        with pytest.raises(UsdExportError, match="cannot create a USD file there") as e:
            UsdBakeWriter(target, n_points=3, fps=30)
        assert "\n" not in str(e.value) and "pxrInternal" not in str(e.value)
    finally:
        if target.parent != Path("/proc"):
            target.parent.chmod(0o700)


def test_missing_folder(tmp_path):
    with pytest.raises(UsdExportError, match="does not exist"):
        UsdBakeWriter(tmp_path / "nope" / "x.usd", n_points=3, fps=30)


# ---------------------------------------------------------------- static instances, held samples

def pinned_bake(n=400, frames=8, seed=1):
    """Half the instances pinned (their pose carries float-rounding jitter, as a bake's
    scene -> simulation -> scene round trip gives), half moving; constant sigmas."""
    pos, quats, sig, sh, opac = synthetic_bake(n, frames, seed=seed, sh_k=4)
    static = np.zeros(n, bool)
    static[: n // 2] = True
    rng = np.random.default_rng(seed)
    for f in range(frames):
        pos[f, static] = pos[0, static] * (1 + rng.uniform(-2e-7, 2e-7, (static.sum(), 3))).astype(np.float32)
        quats[f, static] = quats[0, static]
        sig[f] = sig[0]
    return (pos, quats, sig, sh, opac), static


def test_static_instances_are_written_once(tmp_path):
    from usd_export import instance_positions
    data, static = pinned_bake()
    pos, quats, sig, sh, opac = data
    path = write(tmp_path / "s.usd", data, start=0, static=static, hold_to=20)
    stage = Usd.Stage.Open(str(path))
    names = {p.GetName() for p in stage.GetDefaultPrim().GetChildren()}
    assert names == {"Instancer", "SplatColors", "Splats", "StaticInstancer", "StaticSplatColors", "StaticSplats"}
    for prim in ("StaticInstancer", "StaticSplatColors", "StaticSplats"):
        for attr in stage.GetPrimAtPath(f"/Root/{prim}").GetAttributes():
            assert attr.GetNumTimeSamples() == 0, attr.GetPath()  # default values only
    st = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/StaticInstancer"))
    np.testing.assert_array_equal(np.asarray(st.GetIdsAttr().Get()), np.flatnonzero(static))
    np.testing.assert_array_equal(np.asarray(st.GetPositionsAttr().Get()), pos[0, static])
    mv = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    np.testing.assert_array_equal(np.asarray(mv.GetIdsAttr().Get()), np.flatnonzero(~static))
    # constant sigmas: one sample; the moving positions: one per frame
    assert mv.GetScalesAttr().GetTimeSamples() == [0.0]
    assert mv.GetPositionsAttr().GetTimeSamples() == list(range(8))
    # what a reader sees at every frame: all instances, by id, where they were written
    for f in range(8):
        ids, p = instance_positions(stage, f)
        np.testing.assert_array_equal(ids, np.arange(len(static)))
        np.testing.assert_allclose(p, pos[f], rtol=0, atol=1e-6)
    validate_usd(path)


def test_instance_arrays_read_back_every_instances_pose_and_where_it_sits(tmp_path):
    from usd_export import instance_arrays
    from usd_export.writer import DEFAULT_SCALE_FACTOR
    data, static = pinned_bake()
    pos, quats, sig, sh, opac = data
    stage = Usd.Stage.Open(str(write(tmp_path / "s.usd", data, start=0, static=static)))
    for f in (0, 3, 7):
        ids, where, a = instance_arrays(stage, f, ("positions", "orientations", "scales"))
        np.testing.assert_array_equal(ids, np.arange(len(static)))
        np.testing.assert_array_equal(where, static)
        np.testing.assert_allclose(a["positions"], pos[f], rtol=0, atol=1e-6)
        # stored as half-precision (x, y, z, w); q and -q are one rotation
        q = a["orientations"][:, [3, 0, 1, 2]]
        sign = np.sign((q * quats[f]).sum(axis=1, keepdims=True))
        np.testing.assert_allclose(q * sign, quats[f], rtol=0, atol=2e-3)
        np.testing.assert_allclose(a["scales"], sig[f] * DEFAULT_SCALE_FACTOR, rtol=1e-6)
    empty = Usd.Stage.CreateInMemory()
    ids, where, a = instance_arrays(empty, 0, ("positions", "orientations"))
    assert ids.shape == (0,) and where.shape == (0,) and a["orientations"].shape == (0, 4)


def test_static_split_halves_the_per_frame_bytes_of_a_half_pinned_file(tmp_path):
    data, static = pinned_bake(n=4000, frames=40)
    full = write(tmp_path / "full.usd", data, start=0).stat().st_size
    split = write(tmp_path / "split.usd", data, start=0, static=static).stat().st_size
    # per frame half the bytes; the constant arrays (colours, SH, ids) are not halved
    assert full > 1.7 * split, (full, split)


def test_static_instances_that_move_are_refused(tmp_path):
    data, static = pinned_bake()
    pos = data[0].copy()
    pos[3, 7] += 1e-3  # instance 7 is static
    with pytest.raises(UsdExportError, match="instances passed as static changed since the first frame"):
        write(tmp_path / "m.usd", (pos, *data[1:]), start=0, static=static)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(UsdExportError, match="static must be 400 booleans"):
        write(tmp_path / "m.usd", data, static=np.ones(3, bool))


@pytest.mark.parametrize("what", ["position", "orientation", "scale"])
def test_static_instances_handed_over_unchanged_then_moved_are_refused(tmp_path, what):
    # a bake hands its static instances over bit for bit, which the writer compares first:
    # a change after such frames must still be caught, however it moves them
    data, static = pinned_bake()
    pos, quats, sig = data[0].copy(), data[1].copy(), data[2].copy()
    pos[:, static], quats[:, static], sig[:, static] = pos[0, static], quats[0, static], sig[0, static]
    write(tmp_path / "ok.usd", (pos, quats, sig, *data[3:]), start=0, static=static)
    if what == "position":
        pos[5, 9] += 1e-3
    elif what == "orientation":
        quats[5, 9] = quats[5, 9, [1, 0, 3, 2]]
    else:
        sig[5, 9] *= 1.01
    with pytest.raises(UsdExportError, match="instances passed as static changed since the first frame"):
        write(tmp_path / "m.usd", (pos, quats, sig, *data[3:]), start=0, static=static)
    assert not (tmp_path / "m.usd").exists()


def test_unchanged_frames_are_not_sampled_again(tmp_path):
    """An object at rest repeats its pose: no new samples, yet every frame reads its
    pose, and motion after the rest does not blend back into it."""
    pos, quats, sig, sh, opac = synthetic_bake(n=50, frames=4)
    frames = [0, 1, 2, 3, 3, 3, 3, 3, 0]  # frames 3-7 at rest, frame 8 moves again
    path = tmp_path / "r.usd"
    with UsdBakeWriter(path, n_points=50, fps=30, sh=sh) as w:
        for t, f in enumerate(frames):
            w.write_frame(t, pos[f], quats[f], sig[0])
        w.hold_frames(12)
    stage = Usd.Stage.Open(str(path))
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    assert inst.GetPositionsAttr().GetTimeSamples() == [0, 1, 2, 3, 7, 8]
    assert inst.GetScalesAttr().GetTimeSamples() == [0]
    for t, f in enumerate(frames):
        np.testing.assert_array_equal(np.asarray(inst.GetPositionsAttr().Get(t)), pos[f])
    # between two equal samples, interpolation is the pose (to 1 ulp)
    np.testing.assert_allclose(np.asarray(inst.GetPositionsAttr().Get(5.5)), pos[3], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(inst.GetPositionsAttr().Get(12)), pos[0])
    validate_usd(path)


def test_validate_rejects_ids_repeated_across_instancers(tmp_path):
    data, static = pinned_bake()
    path = write(tmp_path / "d.usd", data, start=0, static=static)
    layer = Sdf.Layer.FindOrOpen(str(path))
    stage = Usd.Stage.Open(layer)
    UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/StaticInstancer")).GetIdsAttr().Set(
        np.flatnonzero(~static).astype(np.int64))
    layer.Save()
    with pytest.raises(UsdExportError, match="instance ids repeat"):
        validate_usd(path, usd_validators=False)


@pytest.mark.parametrize("threaded", [False, True])
def test_constant_scales_written_once_and_a_change_in_a_reused_buffer_lands(tmp_path, data, threaded):
    """A bake hands the same scales every frame: they are authored once. A caller that
    changes them in the same buffer gets the change, held values bracketed correctly."""
    pos, quats, sig, sh, opac = data
    s = sig[0].copy()
    path = tmp_path / "s.usdc"
    with UsdBakeWriter(path, n_points=N, fps=30, fmt="both", sh=sh, opacities=opac, threaded=threaded) as w:
        for f in range(5):
            if f == 3:
                s *= 1.5  # in place: the writer must not keep a view of the caller's buffer
            w.write_frame(f, pos[f], quats[f], s)
    stage = Usd.Stage.Open(str(path))
    from pxr import UsdVol
    inst = UsdGeom.PointInstancer(stage.GetPrimAtPath("/Root/Instancer"))
    field = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/Root/Splats"))
    for attr, factor in ((inst.GetScalesAttr(), 2.0), (field.GetScalesAttr(), 1.0)):
        assert attr.GetTimeSamples() == [0, 2, 3]  # held from 0 to 2, changed at 3
        for f in range(5):
            want = factor * sig[0] * (1.5 if f >= 3 else 1.0)
            np.testing.assert_allclose(np.asarray(attr.Get(f)), want, rtol=1e-6)
    for f in (2, 4):  # the extents follow the changed radii
        assert_box_bounds(np.asarray(inst.GetExtentAttr().Get(f)), pos[f], 2 * sig[0] * (1.5 if f >= 3 else 1.0))
        assert_box_bounds(np.asarray(field.GetExtentAttr().Get(f)), pos[f], 3 * sig[0] * (1.5 if f >= 3 else 1.0))


def test_sample_comparison_sees_a_change_off_its_stride():
    from usd_export._held import same_values as _same
    a = np.random.default_rng(0).normal(size=(5000, 3)).astype(np.float32)
    assert _same(a, a.copy())
    for i in (0, 1, 7, a.size - 1):  # on and off the strided thousandth
        b = a.copy()
        b.reshape(-1)[i] += 1e-3
        assert not _same(a, b)
    assert not _same(a, a[:-1])
    h = a.astype(np.float16)
    assert _same(h, h.copy()) and not _same(h, -h)
