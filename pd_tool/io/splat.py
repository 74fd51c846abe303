"""The antimatter15 `.splat` web format: 32 bytes per Gaussian, no header.

Layout per record (little endian): position 3 x float32, linear scale 3 x float32,
colour RGBA 4 x uint8 (RGB = 0.5 + C0 * f_dc, A = opacity, both times 255),
rotation 4 x uint8 as round(q * 128 + 128) clipped to 0-255, in (w, x, y, z) order.
Only degree-0 colour is stored.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pd_tool.core.atomic import atomic_output
from pd_tool.core.errors import SplatFormatError
from pd_tool.core.scene import GaussianScene, rgb_to_sh, sh_to_rgb

RECORD_BYTES = 32  # bytes per Gaussian
SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == RECORD_BYTES


def load_splat(path: str | Path, device: str | torch.device = "cpu") -> GaussianScene:
    """Read a `.splat` file. Raises SplatFormatError with one line on malformed input."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise SplatFormatError(f"{path}: file is empty; export the splat again")
    if size % RECORD_BYTES:
        raise SplatFormatError(
            f"{path}: {size} bytes is not a multiple of {RECORD_BYTES} (one .splat record); "
            f"the file is truncated or not a .splat file"
        )
    rec = np.fromfile(path, dtype=SPLAT_DTYPE)
    pos = rec["position"].astype(np.float32)
    scale = rec["scale"].astype(np.float32)
    for label, arr in (("position", pos), ("scale", scale)):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise SplatFormatError(
                f"{path}: {int(bad.sum())} Gaussians have NaN/inf {label}, first at index "
                f"{int(np.flatnonzero(bad)[0])}; remove them or export again"
            )
    if (scale < 0).any():
        raise SplatFormatError(f"{path}: negative scales; .splat stores linear scales, so the file is corrupt")
    q = (rec["rot"].astype(np.float32) - 128.0) / 128.0
    norms = np.linalg.norm(q, axis=1)
    if (norms < 1e-6).any():
        raise SplatFormatError(
            f"{path}: {int((norms < 1e-6).sum())} Gaussians have a zero-length rotation; the file is corrupt"
        )
    rgba = rec["rgba"].astype(np.float32) / 255.0
    return GaussianScene(
        positions=torch.from_numpy(pos).to(device),
        quats=torch.from_numpy(q / norms[:, None]).to(device),
        scales=torch.from_numpy(scale).to(device),
        opacities=torch.from_numpy(rgba[:, 3].copy()).to(device),
        sh=rgb_to_sh(torch.from_numpy(rgba[:, None, :3].copy())).to(device),
        source=path,
        source_format="splat",
    )


def save_splat(scene: GaussianScene, path: str | Path) -> Path:
    """Write a `.splat` file (degree-0 colour only; quantises colour, opacity, rotation)."""
    path = Path(path)
    rec = np.zeros(scene.count, dtype=SPLAT_DTYPE)
    rec["position"] = scene.positions.detach().cpu().numpy()
    rec["scale"] = scene.scales.detach().cpu().numpy()
    rgb = sh_to_rgb(scene.sh[:, 0]).detach().cpu().numpy()
    rgba = np.concatenate([rgb, scene.opacities.detach().cpu().numpy()[:, None]], axis=1)
    rec["rgba"] = np.clip(np.round(rgba * 255.0), 0, 255).astype(np.uint8)
    q = scene.quats.detach().cpu().numpy()
    rec["rot"] = np.clip(np.round(q * 128.0 + 128.0), 0, 255).astype(np.uint8)
    with atomic_output(path) as tmp:
        rec.tofile(tmp)
    return path
