"""usd_export._geom (numpy) against dense references, and the quaternion order through pxr."""
from __future__ import annotations

import numpy as np
import pytest

from pd_tool.core.quaternion import quat_to_matrix_np
from usd_export._geom import (
    ellipsoid_extent, ellipsoid_extent_dense, ellipsoid_half_extents, normalize_quats, rgb_to_sh_dc,
    sh_dc_to_rgb, sh_degree, sphere_extent, unit_xyzw_half,
)

RNG_SEED = 7


def _random_quats(n: int, rng) -> np.ndarray:
    return normalize_quats(rng.normal(size=(n, 4)).astype(np.float32))


def test_rotmat_matches_pxr():
    Gf = pytest.importorskip("pxr.Gf")
    rng = np.random.default_rng(RNG_SEED)
    q = _random_quats(20, rng)
    r = quat_to_matrix_np(q)
    for qi, ri in zip(q, r):
        gq = Gf.Quatd(float(qi[0]), Gf.Vec3d(*map(float, qi[1:])))
        # Gf matrices act on row vectors (v * M), so Gf's matrix is our R transposed.
        m = np.array(Gf.Matrix3d(Gf.Rotation(gq)))
        np.testing.assert_allclose(ri, m.T, atol=1e-6)
    np.testing.assert_allclose(r @ r.transpose(0, 2, 1), np.broadcast_to(np.eye(3), r.shape), atol=1e-6)


def test_ellipsoid_half_extents_against_dense_surface_samples():
    rng = np.random.default_rng(RNG_SEED)
    q = _random_quats(16, rng)
    radii = rng.uniform(0.1, 2.0, (16, 3)).astype(np.float32)
    # Dense reference: max |(R S u)_i| over many unit vectors u. Sampling only
    # approaches the supremum from below, so the exact value must be >= and close.
    u = rng.normal(size=(200_000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    m = quat_to_matrix_np(q) * radii.astype(np.float64)[:, None, :]
    ref = np.abs(np.einsum("nij,kj->nki", m, u)).max(axis=1)
    got = ellipsoid_half_extents(q, radii)
    assert (got >= ref - 1e-12).all()
    np.testing.assert_allclose(got, ref, rtol=2e-3)


@pytest.mark.parametrize("spread", [0.01, 1.0, 100.0])
def test_ellipsoid_extent_candidates_equal_dense(spread):
    # spread: positions vs radii; at 100 the radii decide which ellipsoid is extreme
    rng = np.random.default_rng(RNG_SEED)
    n = 5000
    p = (rng.normal(size=(n, 3)) * spread).astype(np.float32)
    q = _random_quats(n, rng)
    radii = rng.lognormal(0, 1, (n, 3)).astype(np.float32)
    np.testing.assert_array_equal(ellipsoid_extent(p, q, radii), ellipsoid_extent_dense(p, q, radii))
    # quaternions of any length are normalised (a frame's orientations arrive as given)
    np.testing.assert_allclose(ellipsoid_extent(p, 3 * q, radii), ellipsoid_extent(p, q, radii), rtol=1e-6, atol=0)
    # and the box holds every ellipsoid's densely sampled surface
    u = rng.normal(size=(64, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    surf = p[:, None, :] + np.einsum("nij,kj->nki", quat_to_matrix_np(q) * radii[:, None, :], u)
    box = ellipsoid_extent(p, q, radii)
    assert (surf >= box[0]).all() and (surf <= box[1]).all()


def test_ellipsoid_extent_contains_centres_and_is_float32_outward():
    rng = np.random.default_rng(RNG_SEED)
    p = rng.normal(size=(100, 3)).astype(np.float32) * 1e3
    q = _random_quats(100, rng)
    box = ellipsoid_extent(p, q, np.full((100, 3), 1e-9, np.float32))
    assert box.dtype == np.float32
    assert (p >= box[0]).all() and (p <= box[1]).all()


def test_written_orientations_are_unit_xyzw_halves_that_vt_and_gf_read_as_wxyz():
    Vt = pytest.importorskip("pxr.Vt")
    rng = np.random.default_rng(RNG_SEED)
    wxyz = rng.normal(size=(50, 4)).astype(np.float32) * 2  # not unit: normalised on the way
    wxyz[7] = 0  # no rotation to normalise: the identity
    half = unit_xyzw_half(wxyz)
    assert half.dtype == np.float16
    # the same values as normalising, reordering and rounding one step at a time
    np.testing.assert_array_equal(half, normalize_quats(wxyz)[:, [1, 2, 3, 0]].astype(np.float16))
    unit = normalize_quats(wxyz)
    arr = Vt.QuathArray.FromNumpy(half)
    for i in (0, 7, 17, 49):
        g = arr[i]  # Gf.Quath: real part is w
        got = np.array([g.GetReal(), *g.GetImaginary()], dtype=np.float64)
        np.testing.assert_allclose(got, unit[i], atol=1e-3)
    np.testing.assert_array_equal(unit[7], [1, 0, 0, 0])


def test_normalize_handles_zero_and_scale():
    q = np.array([[0, 0, 0, 0], [2, 0, 0, 0], [0, 3, 4, 0]], np.float32)
    out = normalize_quats(q)
    np.testing.assert_allclose(out, [[1, 0, 0, 0], [1, 0, 0, 0], [0, 0.6, 0.8, 0]], atol=1e-7)
    q = np.random.default_rng(RNG_SEED).normal(size=(1000, 4)).astype(np.float32) * 3
    ref = q.astype(np.float64) / np.linalg.norm(q.astype(np.float64), axis=1, keepdims=True)
    out = normalize_quats(q)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, ref, rtol=0, atol=3e-7)


def test_sh_colour_round_trip_and_degree():
    rgb = np.random.default_rng(RNG_SEED).uniform(0, 1, (10, 3)).astype(np.float32)
    np.testing.assert_allclose(sh_dc_to_rgb(rgb_to_sh_dc(rgb)), rgb, atol=1e-6)
    assert [sh_degree(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    with pytest.raises(ValueError):
        sh_degree(5)


def test_sphere_extent_against_dense():
    rng = np.random.default_rng(RNG_SEED)
    p = rng.normal(size=(1000, 3)).astype(np.float32)
    r = rng.uniform(0, 0.3, 1000).astype(np.float32)
    ref_lo = (p.astype(np.float64) - r[:, None]).min(0)
    ref_hi = (p.astype(np.float64) + r[:, None]).max(0)
    box = sphere_extent(p, r)
    assert (box[0] <= ref_lo).all() and (box[1] >= ref_hi).all()
    np.testing.assert_allclose(box, np.stack([ref_lo, ref_hi]), rtol=0, atol=1e-5)


def test_srgb_eotf_is_the_exact_piecewise_curve():
    from usd_export._geom import linear_to_srgb, srgb_to_linear
    # reference values of IEC 61966-2-1: linear segment below 0.04045, power 2.4 above
    c = np.array([0.0, 0.02, 0.04045, 0.5, 0.73536, 1.0])
    want = np.array([0.0, 0.02 / 12.92, 0.04045 / 12.92, ((0.5 + 0.055) / 1.055) ** 2.4,
                     ((0.73536 + 0.055) / 1.055) ** 2.4, 1.0])
    np.testing.assert_allclose(srgb_to_linear(c), want, rtol=1e-6, atol=1e-9)
    assert abs(srgb_to_linear(np.array([0.5]))[0] - 0.21404114) < 1e-7
    x = np.linspace(0, 1, 1001)
    np.testing.assert_allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-6)
