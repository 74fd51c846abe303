"""Public entry point of the differentiable Gaussian splatting rasteriser."""
from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import torch

from pd_tool.core.cameras import Camera
from pd_tool.core.errors import PdToolError


class RenderInputError(PdToolError, ValueError):
    """Tensors or options given to render() have the wrong shape, dtype, device or value."""


class RenderOutput(NamedTuple):
    """rgb [H, W, 3] float32 linear colour (background included); alpha [H, W, 1] float32
    coverage in 0-1; depth [H, W, 1] float32 expected camera z of the visible Gaussians
    (alpha-normalised, 0 where alpha = 0), or None unless asked for."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise RenderInputError(msg)


def render(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    sh: torch.Tensor,
    camera: Camera,
    *,
    background: Sequence[float] = (0.0, 0.0, 0.0),
    sh_degree: int | None = None,
    near: float = 0.01,
    return_depth: bool = False,
) -> RenderOutput:
    """Rasterise N 3D Gaussians into one image (tile-based 3DGS), differentiable.

    Args:
        means: [N, 3] centres in world units.
        quats: [N, 4] rotations as (w, x, y, z); normalised inside (any non-zero norm).
        scales: [N, 3] linear standard deviations along the rotated axes, world units.
        opacities: [N] in 0-1 (already activated, not logits).
        sh: [N, K, 3] SH coefficients, K = (degree + 1)^2 in {1, 4, 9, 16}, sh[:, 0] the DC
            term (graphdeco ordering: colour = 0.5 + 0.28209479 * sh_dc + ...,
            clamped at >= 0).
        camera: pd_tool.core.cameras.Camera (OpenCV world-to-camera, pixels).
        background: RGB colour behind the Gaussians (added as T_final * background).
        sh_degree: SH degree to evaluate (0-3, at most what K holds); None = all of K.
        near: Gaussians with camera z <= near (world units) are culled.
        return_depth: also return the expected depth map.

    Returns:
        RenderOutput(rgb [H, W, 3], alpha [H, W, 1], depth [H, W, 1] | None), float32 on
        means.device (cpu or cuda). Gradients flow to means, quats, scales, opacities
        and sh (float32 inputs; other float dtypes are cast, and their gradients cast back).
    """
    _check(isinstance(camera, Camera), f"render: camera must be a pd_tool.core.cameras.Camera, got {type(camera).__name__}")
    tensors = dict(means=means, quats=quats, scales=scales, opacities=opacities, sh=sh)
    for name, t in tensors.items():
        _check(isinstance(t, torch.Tensor), f"render: {name} must be a torch.Tensor, got {type(t).__name__}")
        _check(t.is_floating_point(), f"render: {name} must be a float tensor, got {t.dtype}")
        _check(t.device == means.device, f"render: {name} is on {t.device} but means is on {means.device}; move all tensors to one device")
    _check(means.ndim == 2 and means.shape[1] == 3, f"render: means must be [N, 3], got {list(means.shape)}")
    n = means.shape[0]
    _check(tuple(quats.shape) == (n, 4), f"render: quats must be [N, 4] (w, x, y, z) with N={n}, got {list(quats.shape)}")
    _check(tuple(scales.shape) == (n, 3), f"render: scales must be [N, 3] with N={n}, got {list(scales.shape)}")
    _check(tuple(opacities.shape) == (n,), f"render: opacities must be [N] with N={n}, got {list(opacities.shape)}")
    _check(sh.ndim == 3 and sh.shape[0] == n and sh.shape[2] == 3, f"render: sh must be [N, K, 3] with N={n}, got {list(sh.shape)}")
    k = sh.shape[1]
    max_degree = int(round(math.sqrt(k))) - 1
    _check(k in (1, 4, 9, 16), f"render: sh has K={k} coefficients; K must be (degree + 1)^2 = 1, 4, 9 or 16")
    if sh_degree is None:
        sh_degree = max_degree
    _check(0 <= int(sh_degree) <= max_degree, f"render: sh_degree={sh_degree} but sh holds degree {max_degree} at most (K={k})")
    _check(means.device.type in ("cpu", "cuda"), f"render: device {means.device} not supported; use cpu or cuda")
    bg = tuple(float(c) for c in background)
    _check(len(bg) == 3, f"render: background must have 3 values (RGB), got {len(bg)}")
    _check(near > 0, f"render: near must be > 0, got {near}")
    _check(camera.width > 0 and camera.height > 0, f"render: camera size {camera.width}x{camera.height} must be positive")

    from pd_tool.render.rasterize import RasterSettings, rasterize  # warp import is heavy

    settings = RasterSettings(camera, bg, int(sh_degree), float(near))
    f32 = [t.to(torch.float32).contiguous() for t in (means, quats, scales, opacities, sh)]
    rgb, alpha, depth_sum = rasterize(*f32, settings)
    depth = None
    if return_depth:
        safe = torch.where(alpha > 0, alpha, torch.ones_like(alpha))
        depth = torch.where(alpha > 0, depth_sum / safe, torch.zeros_like(depth_sum))
    return RenderOutput(rgb, alpha, depth)
