"""Neural fields over the simulation box: a triplane followed by a 3-layer MLP.

PhysDreamer represents the Young's modulus E(x) and the initial velocity v0(x) as
triplane + MLP fields (method.md, "Fields and optimisation"). Inputs are positions
normalised to the unit cube [0, 1]^3 (the simulation box), as a torch tensor [N, 3].

Conventions of this module:
- A triplane holds three learnable feature planes [C, R, R]: xy, xz and yz. A point
  (x, y, z) samples plane xy at (x, y), xz at (x, z), yz at (y, z), bilinearly with
  `torch.nn.functional.grid_sample(align_corners=True)`: texel 0 sits exactly on
  coordinate 0 and texel R-1 on coordinate 1, so the planes span the box corner to
  corner. Points outside [0, 1]^3 take the edge texels (padding_mode="border"): a particle
  that drifts out of the box keeps a finite, continuous feature.
- The three plane features are concatenated by default ([N, 3C], the MLP can tell
  the planes apart) or summed (`reduce="sum"`, [N, C]).
- MLP: Linear -> SiLU -> Linear -> SiLU -> Linear. SiLU rather than ReLU: smooth, so
  finite-difference gradient checks and Adam see no kinks.
- Every field is an `nn.Module`; its `state_dict()` holds all weights, and
  `config()` / `from_config()` give the constructor arguments, so a field can be saved in
  a material file and rebuilt exactly (`field_arrays` / `load_field` do both for the
  .pdmat's `field.<name>.<param>` float32 arrays).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pd_tool.core.errors import MaterialFileError, PdToolError

PLANE_AXES = ((0, 1), (0, 2), (1, 2))  # xy, xz, yz: which coordinates index each plane
PLANE_NAMES = ("xy", "xz", "yz")
PLANE_INIT_STD = 0.1  # std of the random plane features at start; small but not zero,
# so that the MLP sees position-dependent inputs from the first iteration.


class FieldSettingsError(PdToolError):
    """Field settings (resolution, bounds, initial value) are impossible."""


def tv_loss(plane: Tensor) -> Tensor:
    """Total variation of a plane: sum_ij ||u[i+1,j] - u[i,j]||^2 + ||u[i,j+1] - u[i,j]||^2.

    Args:
        plane: [..., R, R] features (any leading dims, e.g. [C, R, R] or [3, C, R, R]);
            the two last dims are the plane's grid.
    Returns:
        scalar tensor, the sum over every channel and texel (not a mean: the paper's form).
    """
    d_i = plane[..., 1:, :] - plane[..., :-1, :]
    d_j = plane[..., :, 1:] - plane[..., :, :-1]
    return d_i.square().sum() + d_j.square().sum()


def _check_positions(x: Tensor) -> None:
    if x.dim() != 2 or x.shape[1] != 3:
        raise ValueError(f"positions must be [N, 3], got {tuple(x.shape)}")


class Triplane(nn.Module):
    """Three learnable feature planes (xy, xz, yz) over the unit cube, sampled bilinearly.

    Args:
        resolution: R, texels per side of each plane (>= 2).
        channels: C, features per texel.
        reduce: "concat" (output [N, 3C], planes in order xy, xz, yz) or "sum" ([N, C]).
    Attributes:
        planes: nn.Parameter [3, C, R, R] float32; planes[k, c, i, j] is the feature at
            row i (second coordinate of the plane) and column j (first coordinate).
    """

    def __init__(self, resolution: int, channels: int, *, reduce: str = "concat") -> None:
        super().__init__()
        if resolution < 2:
            raise FieldSettingsError(f"triplane resolution must be >= 2, got {resolution}; "
                                     f"use e.g. 8 (material) or 24 (velocity)")
        if channels < 1:
            raise FieldSettingsError(f"triplane channels must be >= 1, got {channels}")
        if reduce not in ("concat", "sum"):
            raise FieldSettingsError(f"triplane reduce must be 'concat' or 'sum', got {reduce!r}")
        self.resolution = int(resolution)
        self.channels = int(channels)
        self.reduce = reduce
        self.planes = nn.Parameter(PLANE_INIT_STD * torch.randn(3, channels, resolution, resolution))

    @property
    def out_features(self) -> int:
        """Width of the sampled feature: 3C for concat, C for sum."""
        return 3 * self.channels if self.reduce == "concat" else self.channels

    def sample_planes(self, x: Tensor) -> Tensor:
        """Per-plane features at x.

        Args:
            x: [N, 3] positions normalised to [0, 1]^3 (same dtype/device as the planes).
        Returns:
            [N, 3, C]: features from plane xy, xz, yz.
        """
        _check_positions(x)
        x = x.to(self.planes.dtype)  # float64 positions from the simulator are fine
        # grid_sample wants coordinates in [-1, 1] with grid[..., 0] indexing the width
        # (last dim, column j) and grid[..., 1] the height (row i).
        g = 2.0 * x - 1.0
        grid = torch.stack([g[:, list(ax)] for ax in PLANE_AXES])  # [3, N, 2]
        out = F.grid_sample(self.planes, grid[:, None], mode="bilinear",
                            padding_mode="border", align_corners=True)  # [3, C, 1, N]
        return out[:, :, 0, :].permute(2, 0, 1)  # [N, 3, C]

    def forward(self, x: Tensor) -> Tensor:
        """Features at x: [N, 3] in [0, 1]^3 -> [N, 3C] (concat) or [N, C] (sum)."""
        f = self.sample_planes(x)
        return f.reshape(f.shape[0], -1) if self.reduce == "concat" else f.sum(dim=1)

    def tv(self) -> Tensor:
        """Total variation summed over the three planes (scalar)."""
        return tv_loss(self.planes)


class TriplaneField(nn.Module):
    """Triplane followed by a 3-layer MLP: [N, 3] in [0, 1]^3 -> [N, out_dim].

    Args:
        resolution: triplane texels per side.
        channels: triplane features per texel.
        hidden: width of the two hidden MLP layers.
        out_dim: output width.
        reduce: how plane features combine, "concat" or "sum" (see Triplane).
    """

    def __init__(self, resolution: int, channels: int, hidden: int, out_dim: int,
                 *, reduce: str = "concat") -> None:
        super().__init__()
        if hidden < 1 or out_dim < 1:
            raise FieldSettingsError(f"MLP hidden and out_dim must be >= 1, got {hidden}, {out_dim}")
        self.triplane = Triplane(resolution, channels, reduce=reduce)
        self.mlp = nn.Sequential(
            nn.Linear(self.triplane.out_features, hidden), nn.SiLU(),
            nn.Linear(hidden, hidden), nn.SiLU(),
            nn.Linear(hidden, out_dim),
        )

    @property
    def last_layer(self) -> nn.Linear:
        return self.mlp[-1]

    def forward(self, x: Tensor) -> Tensor:
        """Raw MLP output at x: [N, 3] in [0, 1]^3 -> [N, out_dim]."""
        return self.mlp(self.triplane(x))

    def tv(self) -> Tensor:
        """Total variation of every plane (scalar); add weight * tv() to the loss."""
        return self.triplane.tv()


class MaterialField(nn.Module):
    """Young's modulus field: log E(x) (natural log of pascals) inside fixed bounds.

    log E = log_e_min + (log_e_max - log_e_min) * sigmoid(z(x)), z = TriplaneField(x).
    The sigmoid keeps log E inside (log_e_min, log_e_max) with a gradient everywhere
    (no clamp). The last MLP layer starts at zero weight and a bias of
    logit((init_log_e - log_e_min) / (log_e_max - log_e_min)), so the field starts at
    exactly init_log_e at every point; the first optimiser step on the last layer then
    opens the gradient path to the hidden layers and the planes.

    Args:
        resolution: triplane texels per side (paper: 8).
        log_e_min, log_e_max: bounds of log E, ln(Pa); log_e_min < log_e_max.
        init_log_e: starting value, ln(Pa), strictly between the bounds.
        channels, hidden: triplane channels and MLP width.
    """

    def __init__(self, resolution: int = 8, log_e_min: float = math.log(1e3),
                 log_e_max: float = math.log(1e9), init_log_e: float = math.log(1e5),
                 *, channels: int = 16, hidden: int = 64, reduce: str = "concat") -> None:
        super().__init__()
        lo, hi, init = float(log_e_min), float(log_e_max), float(init_log_e)
        if not all(math.isfinite(v) for v in (lo, hi, init)):
            raise FieldSettingsError(f"log E bounds/initial value must be finite, got "
                                     f"min={lo}, max={hi}, init={init}")
        if not lo < hi:
            raise FieldSettingsError(f"log E bounds are empty: min {lo:.4g} >= max {hi:.4g}; "
                                     f"give a lower min or a higher max")
        if not lo < init < hi:
            raise FieldSettingsError(
                f"initial E {math.exp(init):.4g} Pa is not strictly inside the bounds "
                f"[{math.exp(lo):.4g}, {math.exp(hi):.4g}] Pa; widen the bounds or change the initial E")
        self.log_e_min, self.log_e_max = lo, hi
        self.net = TriplaneField(resolution, channels, hidden, 1, reduce=reduce)
        self.reset_to(init)

    @torch.no_grad()
    def reset_to(self, log_e: float) -> None:
        """Make the field the constant log_e (ln Pa) everywhere: last layer zero, bias = logit."""
        u = (float(log_e) - self.log_e_min) / (self.log_e_max - self.log_e_min)
        if not 0.0 < u < 1.0:
            raise FieldSettingsError(f"log E {log_e:.4g} is not strictly inside "
                                     f"[{self.log_e_min:.4g}, {self.log_e_max:.4g}]")
        self.net.last_layer.weight.zero_()
        self.net.last_layer.bias.fill_(math.log(u) - math.log1p(-u))

    def forward(self, x: Tensor) -> Tensor:
        """log E at x: [N, 3] in [0, 1]^3 -> [N], ln(Pa)."""
        z = self.net(x)[:, 0]
        return self.log_e_min + (self.log_e_max - self.log_e_min) * torch.sigmoid(z)

    def youngs_modulus(self, x: Tensor) -> Tensor:
        """E at x in pascals: [N, 3] in [0, 1]^3 -> [N]."""
        return torch.exp(self(x))

    def tv(self) -> Tensor:
        """Total variation of the three planes (scalar)."""
        return self.net.tv()

    def config(self) -> dict[str, Any]:
        """Constructor arguments (JSON-friendly); `from_config(cfg)` + `load_state_dict` rebuilds."""
        t = self.net.triplane
        return {"kind": "material", "resolution": t.resolution, "log_e_min": self.log_e_min,
                "log_e_max": self.log_e_max, "channels": t.channels,
                "hidden": self.net.mlp[0].out_features, "reduce": t.reduce}

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "MaterialField":
        """A field with cfg's shape (its weights still to be loaded with load_state_dict)."""
        c = {k: v for k, v in cfg.items() if k != "kind"}
        mid = 0.5 * (c["log_e_min"] + c["log_e_max"])  # any inside value; the weights overwrite it
        return cls(c.pop("resolution"), c.pop("log_e_min"), c.pop("log_e_max"), mid, **c)


class VelocityField(nn.Module):
    """Initial velocity field v0(x) in m/s: scale * TriplaneField(x), starting at zero.

    The last MLP layer starts at zero (weight and bias), so v0 = 0 everywhere at start (the
    object at rest); `scale` (m/s) is a preconditioner: an MLP output of 1 means `scale` m/s,
    so set it near the expected speed in the video.

    Args:
        resolution: triplane texels per side (paper: 24).
        scale: m/s per unit of MLP output.
        channels, hidden: triplane channels and MLP width.
    """

    def __init__(self, resolution: int = 24, scale: float = 1.0, *, channels: int = 16,
                 hidden: int = 64, reduce: str = "concat") -> None:
        super().__init__()
        if not (math.isfinite(scale) and scale > 0):
            raise FieldSettingsError(f"velocity scale must be a positive number of m/s, got {scale}")
        self.scale = float(scale)
        self.net = TriplaneField(resolution, channels, hidden, 3, reduce=reduce)
        with torch.no_grad():
            self.net.last_layer.weight.zero_()
            self.net.last_layer.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        """v0 at x: [N, 3] in [0, 1]^3 -> [N, 3], m/s."""
        return self.scale * self.net(x)

    def tv(self) -> Tensor:
        """Total variation of the three planes (scalar)."""
        return self.net.tv()

    def config(self) -> dict[str, Any]:
        """Constructor arguments (JSON-friendly); `from_config(cfg)` + `load_state_dict` rebuilds."""
        t = self.net.triplane
        return {"kind": "velocity", "resolution": t.resolution, "scale": self.scale,
                "channels": t.channels, "hidden": self.net.mlp[0].out_features, "reduce": t.reduce}

    @classmethod
    def from_config(cls, cfg: dict[str, Any]) -> "VelocityField":
        """A field with cfg's shape (its weights still to be loaded with load_state_dict)."""
        c = {k: v for k, v in cfg.items() if k != "kind"}
        return cls(c.pop("resolution"), c.pop("scale"), **c)


FIELD_KINDS = {"material": MaterialField, "velocity": VelocityField}


def field_arrays(field: nn.Module) -> dict[str, np.ndarray]:
    """A field's weights as float32 numpy arrays keyed by state_dict name (for the .pdmat
    file's `field.<name>.<param>` entries; float32 is the fields' own dtype, so exact)."""
    return {k: v.detach().to("cpu", torch.float32).numpy().copy() for k, v in field.state_dict().items()}


def load_field(config: dict[str, Any], arrays: dict[str, Any], device: str | torch.device = "cpu") -> nn.Module:
    """Rebuild a field saved as `field.config()` + `field_arrays(field)`.

    Raises MaterialFileError (one line) when the kind is unknown or the arrays do not fit
    the config (a corrupt or hand-edited material file).
    """
    cls = FIELD_KINDS.get(config.get("kind")) if isinstance(config, dict) else None
    if cls is None:
        raise MaterialFileError(f"unknown field kind {config.get('kind') if isinstance(config, dict) else config!r}; "
                                f"expected one of {sorted(FIELD_KINDS)}: the material file is corrupt or newer than this pdtool")
    try:
        field = cls.from_config(config)
        field.load_state_dict({k: torch.as_tensor(v, dtype=torch.float32) for k, v in arrays.items()})
    except (KeyError, TypeError, RuntimeError, PdToolError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise MaterialFileError(f"{config['kind']} field weights do not match its settings ({first[:100]}); "
                                f"the material file is corrupt: run `pdtool fit` again") from None
    return field.to(device)
