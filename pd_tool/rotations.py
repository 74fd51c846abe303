"""Quaternion helpers, (w, x, y, z) order, torch, batched over leading dimensions."""
from __future__ import annotations

import torch


def quat_multiply(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of [..., 4] (w, x, y, z) quaternions (rotate by b, then a)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """Inverse of a unit quaternion [..., 4]."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [..., 3, 3] from quaternions [..., 4] (normalised here)."""
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ),
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] (w >= 0) from rotation matrices [..., 3, 3].

    Picks, per matrix, the largest of 4w^2, 4x^2, 4y^2, 4z^2 as the divisor, so it stays
    accurate for every rotation angle (no division by a small w near 180 degrees).
    """
    m = R
    t = torch.stack(
        (
            1 + m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2],
            1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2],
            1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2],
        ),
        dim=-1,
    ).clamp_min(1e-12)
    s = t.sqrt() * 2  # 4 * |w|, 4 * |x|, 4 * |y|, 4 * |z|
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s01, s02, s12 = m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1]
    sw, sx, sy, sz = s.unbind(-1)
    cands = torch.stack(
        (
            torch.stack((sw / 4, d21 / sw, d02 / sw, d10 / sw), -1),
            torch.stack((d21 / sx, sx / 4, s01 / sx, s02 / sx), -1),
            torch.stack((d02 / sy, s01 / sy, sy / 4, s12 / sy), -1),
            torch.stack((d10 / sz, s02 / sz, s12 / sz, sz / 4), -1),
        ),
        dim=-2,
    )  # [..., candidate, 4]
    best = t.argmax(dim=-1)[..., None, None].expand(*t.shape[:-1], 1, 4)
    q = torch.gather(cands, -2, best).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)
