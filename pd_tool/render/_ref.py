"""Dense float64 torch twin of the rasteriser: slow but obviously right, differentiable.

``project_gaussians_ref`` mirrors ``kernels.project_gaussians`` and ``render_ref``
evaluates every Gaussian at every pixel, composited in one global depth order, so no tiles,
no sorting per tile and no hand-written backward are involved (torch autograd gives its
gradients). To match the tile-based kernels to float32 rounding it applies the same
cut-offs as 3DGS, which are part of the algorithm rather than approximations of it:

- a Gaussian reaches a pixel only if the pixel's 16x16 tile lies in the Gaussian's
  3-sigma tile rectangle (the tile lists of the kernel);
- alpha = min(0.99, opacity * G); contributions with alpha < 1/255 or G's exponent > 0 are
  skipped;
- compositing stops before the first Gaussian that would take T below 1e-4.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from pd_tool.core.quaternion import quat_to_matrix
from pd_tool.render import kernels as K

SH_C2 = (K.SH_C2_0, K.SH_C2_1, K.SH_C2_2, K.SH_C2_3, K.SH_C2_4)
SH_C3 = (K.SH_C3_0, K.SH_C3_1, K.SH_C3_2, K.SH_C3_3, K.SH_C3_4, K.SH_C3_5, K.SH_C3_6)


def eval_sh_ref(sh: torch.Tensor, degree: int, d: torch.Tensor) -> torch.Tensor:
    """sh [N, K, 3], unit directions d [N, 3] -> colour before the +0.5 offset [N, 3]."""
    c = K.SH_C0 * sh[:, 0]
    if degree > 0:
        x, y, z = (d[:, i : i + 1] for i in range(3))
        c = c - K.SH_C1 * y * sh[:, 1] + K.SH_C1 * z * sh[:, 2] - K.SH_C1 * x * sh[:, 3]
        if degree > 1:
            xx, yy, zz = x * x, y * y, z * z
            c = (
                c
                + SH_C2[0] * x * y * sh[:, 4]
                + SH_C2[1] * y * z * sh[:, 5]
                + SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + SH_C2[3] * x * z * sh[:, 7]
                + SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if degree > 2:
                c = (
                    c
                    + SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + SH_C3[1] * x * y * z * sh[:, 10]
                    + SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return c


def project_gaussians_ref(means, quats, scales, sh, settings):
    """Twin of kernels.project_gaussians in the dtype of the inputs.

    Returns means2d [N, 2], conics [N, 3], depths [N], colors [N, 3], rects [N, 4] long
    (tile x0, y0, x1, y1, max exclusive) and visible [N] bool.
    """
    s = settings
    dt = means.dtype
    w2c = torch.as_tensor(np.asarray(s.camera.world_to_camera), dtype=dt, device=means.device)
    rot, trans = w2c[:3, :3], w2c[:3, 3]
    cam_pos = -rot.T @ trans
    t = means @ rot.T + trans
    tz = t[:, 2]
    tz_safe = torch.where(tz > s.near, tz, torch.ones_like(tz))
    tan_fovx = 0.5 * s.camera.width / s.camera.fx
    tan_fovy = 0.5 * s.camera.height / s.camera.fy
    lim_xp = (s.camera.width - s.camera.cx) / s.camera.fx + K.FOV_CLAMP * tan_fovx
    lim_xn = s.camera.cx / s.camera.fx + K.FOV_CLAMP * tan_fovx
    lim_yp = (s.camera.height - s.camera.cy) / s.camera.fy + K.FOV_CLAMP * tan_fovy
    lim_yn = s.camera.cy / s.camera.fy + K.FOV_CLAMP * tan_fovy
    txc = torch.clamp(t[:, 0] / tz_safe, -lim_xn, lim_xp) * tz_safe
    tyc = torch.clamp(t[:, 1] / tz_safe, -lim_yn, lim_yp) * tz_safe
    zero = torch.zeros_like(tz)
    J = torch.stack(
        [s.camera.fx / tz_safe, zero, -s.camera.fx * txc / tz_safe**2, zero, s.camera.fy / tz_safe, -s.camera.fy * tyc / tz_safe**2],
        -1,
    ).reshape(-1, 2, 3)
    M = quat_to_matrix(quats, normalize=True) * scales[:, None, :]
    T = J @ rot
    cov = T @ (M @ M.transpose(1, 2)) @ T.transpose(1, 2)
    a = cov[:, 0, 0] + K.COV2D_DILATION
    b = cov[:, 0, 1]
    c = cov[:, 1, 1] + K.COV2D_DILATION
    det = a * c - b * b
    det_safe = torch.where(det > 0, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], -1)
    mid = 0.5 * (a + c)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    radius = torch.ceil(3.0 * torch.sqrt(lam)).detach()
    mx = s.camera.fx * t[:, 0] / tz_safe + s.camera.cx
    my = s.camera.fy * t[:, 1] / tz_safe + s.camera.cy
    ts = float(K.TILE_SIZE)
    tiles_x = (s.camera.width + K.TILE_SIZE - 1) // K.TILE_SIZE
    tiles_y = (s.camera.height + K.TILE_SIZE - 1) // K.TILE_SIZE
    mxd, myd = mx.detach(), my.detach()
    # torch.trunc = C's (int) cast, as in the kernel.
    x0 = torch.trunc((mxd - radius) / ts).clamp(0, tiles_x)
    y0 = torch.trunc((myd - radius) / ts).clamp(0, tiles_y)
    x1 = torch.trunc((mxd + radius + ts - 1) / ts).clamp(0, tiles_x)
    y1 = torch.trunc((myd + radius + ts - 1) / ts).clamp(0, tiles_y)
    rects = torch.stack([x0, y0, x1, y1], -1).long()
    visible = (tz > s.near) & (det > 0) & ((x1 - x0) * (y1 - y0) > 0)
    d = means - cam_pos
    d = d / d.norm(dim=-1, keepdim=True)
    colors = torch.clamp(eval_sh_ref(sh, s.sh_degree, d) + 0.5, min=0.0)
    means2d = torch.stack([mx, my], -1)
    return means2d, conics, tz, colors, rects, visible


def render_ref(means, quats, scales, opacities, sh, settings):
    """Dense rendering in the inputs' dtype (use float64): rgb [H, W, 3], alpha [H, W, 1],
    alpha-weighted depth sum [H, W, 1]. Differentiable by torch autograd."""
    s = settings
    means2d, conics, depths, colors, rects, visible = project_gaussians_ref(
        means, quats, scales, sh, s
    )
    order = torch.argsort(torch.where(visible, depths, torch.full_like(depths, math.inf)).detach())
    order = order[visible[order]]
    means2d, conics, depths, colors, rects = (x[order] for x in (means2d, conics, depths, colors, rects))
    opac = opacities[order]
    dt = means.dtype
    ys, xs = torch.meshgrid(
        torch.arange(s.camera.height, dtype=dt, device=means.device),
        torch.arange(s.camera.width, dtype=dt, device=means.device),
        indexing="ij",
    )
    px = (xs + 0.5).reshape(-1, 1)  # [P, 1]
    py = (ys + 0.5).reshape(-1, 1)
    tx = (xs.long() // K.TILE_SIZE).reshape(-1, 1)
    ty = (ys.long() // K.TILE_SIZE).reshape(-1, 1)
    in_rect = (tx >= rects[:, 0]) & (tx < rects[:, 2]) & (ty >= rects[:, 1]) & (ty < rects[:, 3])
    dx = px - means2d[:, 0]  # [P, N]
    dy = py - means2d[:, 1]
    power = -0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) - conics[:, 1] * dx * dy
    alpha = torch.clamp(opac * torch.exp(torch.clamp(power, max=0.0)), max=K.ALPHA_MAX)
    keep = in_rect & (power <= 0) & (alpha >= K.ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    T_after = torch.cumprod(one_minus, dim=1)
    # T_after is non-increasing along the list, so "stop at the first T < 1e-4" keeps a prefix.
    alive = (T_after >= K.T_MIN).detach()
    alpha = torch.where(alive, alpha, torch.zeros_like(alpha))
    T_after = torch.cumprod(1.0 - alpha, dim=1)
    T_before = torch.cat([torch.ones_like(T_after[:, :1]), T_after[:, :-1]], 1)
    w = alpha * T_before  # [P, N]
    T_final = T_after[:, -1:] if alpha.shape[1] else torch.ones_like(px)
    bg = torch.as_tensor(s.background, dtype=dt, device=means.device)
    rgb = w @ colors + T_final * bg
    depth = w @ depths[:, None]
    H, W = s.camera.height, s.camera.width
    return rgb.reshape(H, W, 3), (1.0 - T_final).reshape(H, W, 1), depth.reshape(H, W, 1)
