"""Warp kernels of interior filling (device code only; `pd_tool.prepare.fill` launches them).

Twin: `pd_tool.prepare.fill.splat_density_ref` (torch, batched) for `splat_density`.
"""
from __future__ import annotations

import warp as wp


@wp.kernel(enable_backward=False)
def splat_density(
    u: wp.array(dtype=wp.vec3),  # [N] Gaussian centres, voxel units (voxel i spans [i, i+1))
    prec: wp.array(dtype=wp.mat33),  # [N] inverse covariances, 1 / voxel^2
    opacity: wp.array(dtype=float),  # [N] 0-1
    radius: wp.array(dtype=wp.vec3i),  # [N] half box per axis, voxels
    dens: wp.array(dtype=float, ndim=3),  # [X, Y, Z] accumulated alpha * exp(-m / 2)
):
    i = wp.tid()
    c = u[i]
    p = prec[i]
    r = radius[i]
    a = opacity[i]
    # Nearest voxel centre (centres sit at integer + 0.5): the box is centred on it.
    bx = int(wp.round(c[0] - 0.5))
    by = int(wp.round(c[1] - 0.5))
    bz = int(wp.round(c[2] - 0.5))
    nx = dens.shape[0]
    ny = dens.shape[1]
    nz = dens.shape[2]
    for ox in range(-r[0], r[0] + 1):
        ix = bx + ox
        if ix < 0 or ix >= nx:
            continue
        for oy in range(-r[1], r[1] + 1):
            iy = by + oy
            if iy < 0 or iy >= ny:
                continue
            for oz in range(-r[2], r[2] + 1):
                iz = bz + oz
                if iz < 0 or iz >= nz:
                    continue
                d = wp.vec3(float(ix) + 0.5, float(iy) + 0.5, float(iz) + 0.5) - c
                m = wp.dot(d, p * d)
                if m <= 9.0:  # 3-sigma support
                    wp.atomic_add(dens, ix, iy, iz, a * wp.exp(-0.5 * m))
