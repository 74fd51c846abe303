"""Diffusion of the per-driver log-E residuals over the driver graph (FitSettings.residual_diffusion),
and means over parts of the drivers (residual_parts, residual_pool_parts).

One explicit step moves each driver's residual a fraction of the way toward the mean of its
nearest drivers. The fraction is D dx^2 / h^2, with D in grid cells squared, dx the grid
spacing and h the driver's mean distance to those drivers. On a chain with spacing h, a mode
of wavenumber k is multiplied by 1 - (D dx^2 / h^2)(1 - cos kh), about 1 - D dx^2 k^2 / 2 when
kh is small: a long-wavelength pattern decays at the same rate per step whatever the driver
density, so the smoothing covers the same length of object at 3k and at 100k Gaussians.
"""
from __future__ import annotations

import torch

MAX_FRACTION = 0.9  # 1 would swap neighbours' values on a chain instead of smoothing them


def diffusion_fractions(spacing: torch.Tensor, dx: float, cells2: float) -> torch.Tensor:
    """[Q] fraction of the way each residual moves per step: cells2 * dx^2 / spacing^2,
    at most MAX_FRACTION. spacing [Q] and dx in the same length unit; cells2 in grid cells
    squared."""
    h2 = spacing.clamp_min(1e-6 * dx) ** 2
    return (cells2 * dx**2 / h2).clamp(max=MAX_FRACTION)


@torch.no_grad()
def diffuse(values: torch.Tensor, pairs: torch.Tensor, fractions: torch.Tensor) -> None:
    """One explicit diffusion step, in place: values += fractions * (neighbours' mean - values).
    Every point updates from the old values, so the step never leaves [min, max] of them.
    A point set too small to have neighbours (pairs [Q, 0]) is left as it is."""
    if pairs.shape[1] == 0:
        return
    values.add_(fractions * (values[pairs].mean(dim=1) - values))


def part_means(values: torch.Tensor, parts: torch.Tensor) -> torch.Tensor:
    """A copy of values [Q] in which each entry with a part label >= 0 (parts [Q] int64)
    holds its part's mean; an entry labelled -1 keeps its own value."""
    out = values.clone()
    own = parts >= 0
    if not bool(own.any()):
        return out
    lab = parts[own]
    k = int(lab.max()) + 1
    sums = torch.zeros(k, dtype=values.dtype, device=values.device).index_add_(0, lab, values[own])
    counts = torch.bincount(lab, minlength=k).to(values.dtype)
    out[own] = (sums / counts)[lab]
    return out
