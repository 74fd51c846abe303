"""Numpy geometry for the USD writer: quaternions, ellipsoid bounds, SH colour.

No pxr here, so these run (and are tested) without usd-core. Quaternions are
(w, x, y, z) like the rest of pdtool; the xyzw reordering USD's Vt arrays want
happens in `wxyz_to_xyzw`, the only place that knows about it.
"""
from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814  # Y_0^0 = 1 / (2 sqrt(pi)); 3DGS colour = 0.5 + SH_C0 * dc
SPLAT_SUPPORT_SIGMAS = 3.0  # the schema's Gaussian kernel holds 99.7% within 3 sigma


def normalize_quats(q: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] float32 (same order as given); zero rows become identity.

    A zero quaternion has no rotation to normalise, so it is mapped to (1, 0, 0, 0)
    rather than to NaN (which would poison the extent and the file).
    """
    q = np.asarray(q, dtype=np.float32)
    n = np.linalg.norm(q, axis=1, keepdims=True)
    out = np.where(n > 0, q / np.where(n > 0, n, 1), 0).astype(np.float32)
    out[n[:, 0] == 0, 0] = 1.0
    return out


def wxyz_to_xyzw(q: np.ndarray) -> np.ndarray:
    """[N, 4] (w, x, y, z) -> [N, 4] (x, y, z, w), the layout Vt.Quat*Array.FromNumpy reads."""
    return np.ascontiguousarray(q[:, [1, 2, 3, 0]])


def xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    """[N, 4] (x, y, z, w) -> [N, 4] (w, x, y, z); inverse of `wxyz_to_xyzw`."""
    return np.ascontiguousarray(q[:, [3, 0, 1, 2]])


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [N, 3, 3] from unit quaternions [N, 4] (w, x, y, z)."""
    w, x, y, z = (q[:, i].astype(np.float64) for i in range(4))
    r = np.empty((q.shape[0], 3, 3), dtype=np.float64)
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - w * z)
    r[:, 0, 2] = 2 * (x * z + w * y)
    r[:, 1, 0] = 2 * (x * y + w * z)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - w * x)
    r[:, 2, 0] = 2 * (x * z - w * y)
    r[:, 2, 1] = 2 * (y * z + w * x)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def ellipsoid_half_extents(quats: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Axis-aligned half sizes [N, 3] of ellipsoids R diag(radii) (unit sphere).

    The support of {R S u : |u| <= 1} along world axis i is |row_i(R S)|, so the
    tight box half size is the row norm of R S; exact, not the looser box-of-a-box.

    Args:
        quats: [N, 4] unit (w, x, y, z).
        radii: [N, 3] semi-axes along the local axes, scene units.
    """
    m = quat_to_rotmat(quats) * radii.astype(np.float64)[:, None, :]
    return np.sqrt((m * m).sum(axis=2))


def ellipsoid_extent(positions: np.ndarray, quats: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """[2, 3] float32 (min, max) box of all ellipsoids, rounded outwards to float32."""
    if positions.shape[0] == 0:
        return np.zeros((2, 3), dtype=np.float32)
    h = ellipsoid_half_extents(quats, radii)
    p = positions.astype(np.float64)
    lo = (p - h).min(axis=0)
    hi = (p + h).max(axis=0)
    return _outward_f32(lo, hi)


def sphere_extent(positions: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """[2, 3] float32 box of spheres (positions [N, 3], radii [N]), rounded outwards."""
    if positions.shape[0] == 0:
        return np.zeros((2, 3), dtype=np.float32)
    p = positions.astype(np.float64)
    r = radii.astype(np.float64)[:, None]
    return _outward_f32((p - r).min(axis=0), (p + r).max(axis=0))


def _outward_f32(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    # float32 rounding of the box may cut a point's last ulp off; step outwards so
    # that "extent contains the points" holds exactly in float32.
    lo32 = np.nextafter(lo.astype(np.float32), np.float32(-np.inf))
    hi32 = np.nextafter(hi.astype(np.float32), np.float32(np.inf))
    return np.stack([lo32, hi32]).astype(np.float32)


def sh_dc_to_rgb(sh_dc: np.ndarray) -> np.ndarray:
    """3DGS degree-0 colour [N, 3] in 0-1 from DC coefficients [N, 3] (clamped)."""
    return np.clip(0.5 + SH_C0 * sh_dc, 0.0, 1.0).astype(np.float32)


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Inverse of `sh_dc_to_rgb` (without the clamp): DC coefficients [N, 3]."""
    return ((rgb.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)


def sh_degree(k: int) -> int:
    """SH degree d with (d + 1)^2 == k; raises ValueError for other k."""
    d = int(round(np.sqrt(k))) - 1
    if d < 0 or (d + 1) ** 2 != k:
        raise ValueError(f"{k} SH coefficients per splat is not (degree + 1)^2")
    return d
