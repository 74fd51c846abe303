"""GaussianScene: the one in-memory type for a splat, with activated values and raw values."""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

SH_C0 = 0.28209479177387814  # degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
REQUIRED_PLY_PROPERTIES = (
    "x", "y", "z",
    "f_dc_0", "f_dc_1", "f_dc_2",
    "opacity",
    "scale_0", "scale_1", "scale_2",
    "rot_0", "rot_1", "rot_2", "rot_3",
)


def sh_coeff_count(degree: int) -> int:
    """Coefficients per colour channel for an SH degree (1, 4, 9, 16)."""
    return (degree + 1) ** 2


def sh_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    """Degree-0 colour in 0-1 (unclamped) from the DC coefficients [..., 3]."""
    return 0.5 + SH_C0 * sh_dc


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Inverse of sh_to_rgb."""
    return (rgb - 0.5) / SH_C0


@dataclass
class GaussianScene:
    """A set of 3D Gaussians.

    Activated values (torch, on `device`):
        positions [N, 3] f32 scene units; quats [N, 4] f32 unit, (w, x, y, z);
        scales [N, 3] f32 linear standard deviations, scene units;
        opacities [N] f32 in 0-1; sh [N, K, 3] f32, K = (sh_degree + 1)^2,
        sh[:, 0] is the DC term (colour = 0.5 + 0.2821 * sh[:, 0] for degree 0).
    Raw values:
        raw: the file's vertex records (numpy structured array) for a lossless write,
        or None when the scene was built in memory; extra: names of properties that
        are not part of the 3DGS layout (kept in raw, written back).
    """

    positions: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    raw: np.ndarray | None = None
    source: Path | None = None
    source_format: str = "memory"
    extra: tuple[str, ...] = ()
    labels: np.ndarray | None = None  # optional per-Gaussian region label (synthetic scenes)
    label_names: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        n = self.positions.shape[0]
        for name, t, tail in (
            ("quats", self.quats, (4,)),
            ("scales", self.scales, (3,)),
            ("opacities", self.opacities, ()),
        ):
            if tuple(t.shape) != (n, *tail):
                raise ValueError(f"GaussianScene.{name} has shape {tuple(t.shape)}, expected {(n, *tail)}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianScene.sh has shape {tuple(self.sh.shape)}, expected [N, K, 3]")

    @property
    def count(self) -> int:
        return int(self.positions.shape[0])

    @property
    def sh_degree(self) -> int:
        return int(round(self.sh.shape[1] ** 0.5)) - 1

    @property
    def device(self) -> torch.device:
        return self.positions.device

    @property
    def colors(self) -> torch.Tensor:
        """Degree-0 colour [N, 3] clamped to 0-1."""
        return sh_to_rgb(self.sh[:, 0]).clamp(0.0, 1.0)

    def to(self, device: str | torch.device) -> "GaussianScene":
        return replace(
            self,
            positions=self.positions.to(device),
            quats=self.quats.to(device),
            scales=self.scales.to(device),
            opacities=self.opacities.to(device),
            sh=self.sh.to(device),
        )

    def subset(self, mask_or_index: np.ndarray | torch.Tensor) -> "GaussianScene":
        """The Gaussians selected by a boolean mask or an index array (raw values kept)."""
        idx = torch.as_tensor(np.asarray(mask_or_index.cpu() if torch.is_tensor(mask_or_index) else mask_or_index))
        if idx.dtype == torch.bool:
            idx = torch.nonzero(idx, as_tuple=False).flatten()
        idx_np = idx.numpy()
        dev_idx = idx.to(self.device)
        return replace(
            self,
            positions=self.positions[dev_idx],
            quats=self.quats[dev_idx],
            scales=self.scales[dev_idx],
            opacities=self.opacities[dev_idx],
            sh=self.sh[dev_idx],
            raw=None if self.raw is None else self.raw[idx_np],
            labels=None if self.labels is None else self.labels[idx_np],
        )

    def nbytes(self) -> int:
        """Bytes held by the activated tensors (what the engine works on)."""
        return sum(t.element_size() * t.nelement() for t in (self.positions, self.quats, self.scales, self.opacities, self.sh))
