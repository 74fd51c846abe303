"""Quaternion helpers, (w, x, y, z) order, torch, batched over leading dimensions.

One implementation serves the whole engine: the driving-particle code's (Hamilton product
and matrix as bilinear forms, matrix -> quaternion through Horn's matrix, stable at 180
degrees); this module is the general-purpose entry point for it.
"""
from __future__ import annotations

import torch

from pd_tool.drivers.interpolate import matrix_to_quat, quat_multiply
from pd_tool.drivers.interpolate import quat_to_matrix as _unit_quat_to_matrix

__all__ = ["matrix_to_quat", "quat_conjugate", "quat_multiply", "quat_to_matrix"]


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Inverse of a unit quaternion [..., 4]."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (normalised here)."""
    return _unit_quat_to_matrix(q / q.norm(dim=-1, keepdim=True))
