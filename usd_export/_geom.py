"""Numpy geometry for the USD writer: quaternions, ellipsoid bounds, SH colour.

No pxr here, so these run (and are tested) without usd-core. Quaternions are
(w, x, y, z) like the rest of pdtool; the xyzw reordering USD's Vt arrays want
happens in `unit_xyzw_half`, the only place that knows about it.
"""
from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi)); 3DGS colour = 0.5 + SH_C0 * dc
SPLAT_SUPPORT_SIGMAS = 3.0  # the schema's Gaussian kernel holds 99.7% within 3 sigma
HALF_EXTENT_SLACK = 1e-5  # relative; covers float32 rounding of the half sizes


def normalize_quats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] float32 (same order as given); zero rows become identity.

    A zero quaternion has no rotation to normalise, so it is mapped to (1, 0, 0, 0)
    rather than to NaN (which would poison the extent and the file).
    """
    q = np.asarray(q, dtype=np.float32)
    # column by column: numpy's row reductions and [N, 1] broadcasts over [N, 4] run several
    # times slower than 1-D passes (this is on every frame of a bake)
    n2 = q[:, 0] * q[:, 0]
    for c in range(1, 4):
        n2 += q[:, c] * q[:, c]
    zero = n2 == 0
    inv = 1.0 / np.sqrt(np.where(zero, np.float32(1), n2))
    out = np.empty_like(q)
    for c in range(4):
        np.multiply(q[:, c], inv, out=out[:, c])
    if zero.any():
        out[zero] = (1, 0, 0, 0)
    return out


def unit_xyzw_half(q: np.ndarray) -> np.ndarray:
    """[N, 4] (w, x, y, z) -> unit quaternions [N, 4] float16 (x, y, z, w): the orientations
    a frame writes, in the layout Vt.QuathArray.FromNumpy reads. The writer makes them once
    a frame for all its prims. (Normalising into a float16 array column by column, in one
    pass, measured slower than normalising, then reordering with a cast: 134 / 119 against
    88 ms for 2.3M quaternions.)"""
    u = normalize_quats(q)
    out = np.empty(u.shape, np.float16)
    out[:, :3] = u[:, 1:]
    out[:, 3] = u[:, 0]
    return out


def ellipsoid_half_extents(quats: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Axis-aligned half sizes [N, 3] float32 of ellipsoids R diag(radii) (unit sphere).

    The support of {R S u : |u| <= 1} along world axis i is |row_i(R S)|, so the
    tight box half size is the row norm of R S; exact, not the looser box-of-a-box.
    Computed in float32 entry by entry (the bake's hot path: ~N x 30 flops, no
    [N, 3, 3] temporaries) and inflated by HALF_EXTENT_SLACK to cover rounding.

    Args:
        quats: [N, 4] unit (w, x, y, z).
        radii: [N, 3] semi-axes along the local axes, scene units.
    """
    q = np.asarray(quats, dtype=np.float32)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    sx, sy, sz = (np.asarray(radii, dtype=np.float32)[:, i] for i in range(3))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    rows = (
        (1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)),
        (2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)),
        (2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)),
    )
    h = np.empty((q.shape[0], 3), dtype=np.float32)
    for i, (a, b, c) in enumerate(rows):
        h[:, i] = np.sqrt((a * sx) ** 2 + (b * sy) ** 2 + (c * sz) ** 2)
    return h * np.float32(1 + HALF_EXTENT_SLACK)


def ellipsoid_extent(positions: np.ndarray, quats: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """[2, 3] float32 (min, max) tight box of all ellipsoids, rounded outwards.

    Exact, but computed for few ellipsoids: ellipsoid i's half size on each axis
    lies in [min radius_i, max radius_i], so only those whose loose bound
    p - r_max reaches past the best guaranteed bound min_j(p_j - r_min_j) can
    hold the box's face; their exact half sizes settle it. Typically a handful
    of the N, which keeps the per-frame cost at a few O(N) passes. quats: [N, 4]
    (w, x, y, z), normalised here (only the candidates').
    """
    if positions.shape[0] == 0:
        return np.zeros((2, 3), dtype=np.float32)
    p = np.asarray(positions, dtype=np.float32)
    r = np.asarray(radii, dtype=np.float32)
    # Column by column: numpy reduces along axis 1 of [N, 3] and broadcasts [N, 1]
    # several times slower than it runs 1-D passes.
    r_min = np.minimum(np.minimum(r[:, 0], r[:, 1]), r[:, 2])
    r_max = np.maximum(np.maximum(r[:, 0], r[:, 1]), r[:, 2])
    lo_sure, hi_sure = np.empty(3, np.float32), np.empty(3, np.float32)
    cand = np.zeros(p.shape[0], dtype=bool)
    for a in range(3):
        pa = p[:, a]
        lo_sure[a], hi_sure[a] = (pa - r_min).min(), (pa + r_min).max()
        cand |= (pa - r_max <= lo_sure[a]) | (pa + r_max >= hi_sure[a])
    idx = np.flatnonzero(cand)
    h = ellipsoid_half_extents(normalize_quats(np.asarray(quats)[idx]), r[idx])
    lo = np.minimum(col_min(p[idx] - h), lo_sure)
    hi = np.maximum(col_max(p[idx] + h), hi_sure)
    return _outward_f32(lo, hi)


def ellipsoid_extent_dense(positions: np.ndarray, quats: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Reference for `ellipsoid_extent`: every ellipsoid's half sizes, then the box."""
    h = ellipsoid_half_extents(normalize_quats(quats), radii)
    p = np.asarray(positions, dtype=np.float32)
    return _outward_f32(col_min(p - h), col_max(p + h))


def sphere_extent(positions: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """[2, 3] float32 box of spheres (positions [N, 3], radii [N]), rounded outwards."""
    if positions.shape[0] == 0:
        return np.zeros((2, 3), dtype=np.float32)
    p = np.asarray(positions, dtype=np.float32)
    r = np.asarray(radii, dtype=np.float32) * np.float32(1 + HALF_EXTENT_SLACK)
    lo = np.array([(p[:, a] - r).min() for a in range(3)], dtype=np.float32)
    hi = np.array([(p[:, a] + r).max() for a in range(3)], dtype=np.float32)
    return _outward_f32(lo, hi)


def col_min(a: np.ndarray) -> np.ndarray:
    """Column minima of [N, C]; numpy's axis-0 reduction of a C-order array is ~20x slower."""
    return np.array([a[:, i].min() for i in range(a.shape[1])], dtype=a.dtype)


def col_max(a: np.ndarray) -> np.ndarray:
    """Column maxima of [N, C] (see `col_min`)."""
    return np.array([a[:, i].max() for i in range(a.shape[1])], dtype=a.dtype)


def _outward_f32(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    # One more float32 step outwards: with p - h rounded to nearest, a box edge
    # could otherwise sit half an ulp inside an ellipsoid's surface.
    lo32 = np.nextafter(lo.astype(np.float32), np.float32(-np.inf))
    hi32 = np.nextafter(hi.astype(np.float32), np.float32(np.inf))
    return np.stack([lo32, hi32]).astype(np.float32)


def sh_dc_to_rgb(sh_dc: np.ndarray) -> np.ndarray:
    """3DGS degree-0 colour [N, 3] in 0-1 from DC coefficients [N, 3] (clamped)."""
    return np.clip(0.5 + SH_C0 * sh_dc, 0.0, 1.0).astype(np.float32)


def srgb_to_linear(rgb: np.ndarray) -> np.ndarray:
    """sRGB-encoded 0-1 values -> linear 0-1 (IEC 61966-2-1 EOTF, the exact piecewise curve).

    3DGS colours (0.5 + SH_C0 * dc) are display values, i.e. sRGB encoded, while USD
    defines primvars:displayColor as linear; without this Blender, usdview and Omniverse
    show the splats washed out (sRGB applied twice). Computed in float64.
    """
    c = np.asarray(rgb, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(lin: np.ndarray) -> np.ndarray:
    """Inverse of `srgb_to_linear` (the sRGB OETF), float32."""
    c = np.asarray(lin, dtype=np.float64)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * np.maximum(c, 0) ** (1 / 2.4) - 0.055).astype(np.float32)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Inverse of `sh_dc_to_rgb` (without the clamp): DC coefficients [N, 3]."""
    return ((rgb.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)


def sh_degree(k: int) -> int:
    """SH degree d with (d + 1)^2 == k; raises ValueError for other k."""
    d = int(round(np.sqrt(k))) - 1
    if d < 0 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per splat is not (degree + 1)^2")
    return d
