"""Sub-particles: each simulated Gaussian as a small lattice over its extent, so that a grid
finer than the capture's Gaussians still holds several particles a cell.

MPM with about one particle a cell is not a converged simulation: neighbours a cell apart
share no grid node and separate under a push (a scan of 2,000 Gaussians on 128 cells puts
one particle in 95% of its occupied cells). The converged references of the benchmarks
simulate every sub-particle (`split_particles`); a bake clusters them into drivers, a
floor of them a cell (`split_drivers`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from pd_tool.core.quaternion import quat_to_matrix_np
from pd_tool.drivers.build import MIN_PER_CELL, NEIGHBORS, DriverSet, build_drivers, driver_count
from pd_tool.drivers.knn import nearest_drivers

if TYPE_CHECKING:
    from pd_tool.core.scene import GaussianScene
    from pd_tool.prepare.preparation import PreparedScene

SPLIT_PER_CELL = 2  # sub-particles per grid cell along each axis (8 a cell, as the fill)
SPLIT_MOST = 4  # at most this many along each of a Gaussian's axes


@dataclass
class SubParticles:
    """Particles sampling the simulated Gaussians' extents.

    positions [Q, 3] float32 simulation metres; volume [Q] m^3 and mass [Q] kg (each
    particle's shared evenly); static [Q] bool (a static particle's sub-particles pin);
    owner [Q] int64 numpy, the particle (index into prep.positions_sim) each came from,
    in particle order.
    """

    positions: Tensor
    volume: Tensor
    mass: Tensor
    static: Tensor
    owner: np.ndarray

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def to(self, device: str | torch.device) -> SubParticles:
        """The same sub-particles with their tensors on `device`."""
        return SubParticles(positions=self.positions.to(device), volume=self.volume.to(device),
                            mass=self.mass.to(device), static=self.static.to(device), owner=self.owner)


def sub_particles(scene: GaussianScene, prep: PreparedScene, *, per_cell: int = SPLIT_PER_CELL,
                  most: int = SPLIT_MOST, device: str | torch.device = "cpu") -> SubParticles:
    """Every simulated particle of `prep` as one or more sub-particles.

    A Gaussian becomes a lattice of n_a points along each principal axis a, spread over
    +-1 sigma, with n_a = ceil(2 sigma_a / spacing) clipped to [1, most] and spacing
    dx / per_cell: a surface splat becomes a sheet of points and a thin one stays one layer
    thick. The fill's interior particles (already two a cell along each axis) stay single.
    """
    dev = torch.device(device)
    x = np.asarray(prep.positions_sim, np.float64)
    m_all, f = len(x), prep.count
    fg = np.asarray(prep.foreground)
    sigma = scene.scales.detach().cpu().double().numpy()[fg] * prep.transform.scale  # [F, 3] metres
    axes = np.einsum("ij,njk->nik", prep.transform.R, quat_to_matrix_np(scene.quats.detach().cpu().double().numpy()[fg]))
    counts = np.clip(np.ceil(2.0 * sigma / (prep.dx / per_cell)), 1, most).astype(np.int64)  # [F, 3]
    parts, owner = [], []
    for shape in {tuple(c) for c in counts}:  # one lattice per count triple
        rows = np.flatnonzero((counts == shape).all(axis=1))
        grids = [(np.arange(n) + 0.5) / n * 2.0 - 1.0 for n in shape]  # in (-1, 1) sigma
        u = np.stack(np.meshgrid(*grids, indexing="ij"), -1).reshape(-1, 3)  # [k, 3]
        local = u[None, :, :] * sigma[rows, None, :]  # [r, k, 3] along the Gaussian's axes
        parts.append((x[rows, None, :] + np.einsum("rij,rkj->rki", axes[rows], local)).reshape(-1, 3))
        owner.append(np.repeat(rows, len(u)))
    parts.append(x[f:])
    owner.append(np.arange(f, m_all))
    pos, owner = np.concatenate(parts), np.concatenate(owner)
    order = np.argsort(owner, kind="stable")  # each particle's sub-particles together, in particle order
    pos, owner = pos[order], owner[order]
    share = 1.0 / np.bincount(owner, minlength=m_all)[owner]
    t = lambda a, dt=torch.float32: torch.as_tensor(a, dtype=dt, device=dev)  # noqa: E731
    return SubParticles(positions=t(pos), volume=t(np.asarray(prep.volumes, np.float64)[owner] * share),
                        mass=t(np.asarray(prep.masses, np.float64)[owner] * share),
                        static=t(np.asarray(prep.static, bool)[owner], torch.bool), owner=owner)


def split_particles(scene: GaussianScene, prep: PreparedScene, *, per_cell: int = SPLIT_PER_CELL,
                    most: int = SPLIT_MOST, device: str | torch.device = "cpu") -> tuple[DriverSet, np.ndarray]:
    """Every sub-particle (`sub_particles`) as a driver: a converged reference's particles.

    Returns (DriverSet, owner): positions [Q, 3], volume [Q], mass [Q], static [Q],
    neighbors [M, 8] (each particle's 8 nearest sub-particles, so that
    pd_tool.bake.animate.GaussianAnimator moves it) and labels [M] (the first sub-particle
    of each) over the M = len(prep.positions_sim) particles, counts [Q] ones; owner [Q].
    """
    sub = sub_particles(scene, prep, per_cell=per_cell, most=most, device=device)
    dev = sub.positions.device
    per = np.bincount(sub.owner, minlength=len(prep.positions_sim))
    first = np.concatenate([[0], np.cumsum(per)[:-1]])
    points = torch.as_tensor(np.asarray(prep.positions_sim), dtype=torch.float32, device=dev)
    drivers = DriverSet(positions=sub.positions, volume=sub.volume, mass=sub.mass, static=sub.static,
                        labels=torch.as_tensor(first, dtype=torch.long, device=dev),
                        neighbors=nearest_drivers(points, sub.positions, min(NEIGHBORS, len(sub))),
                        points_rest=points, counts=torch.ones(len(sub), dtype=torch.long, device=dev))
    return drivers, sub.owner


def split_driver_count(sub: SubParticles, dx: float, per_cell: int = MIN_PER_CELL) -> int | None:
    """Moving drivers split_drivers clusters from `sub`: `per_cell` in each grid cell (of
    spacing dx) its moving sub-particles occupy, at most one per sub-particle; None where
    none moves."""
    free = sub.positions[~sub.static]
    return driver_count(free, dx, min_per_cell=per_cell) if len(free) else None


def split_drivers(scene: GaussianScene, prep: PreparedScene, *, per_cell: int = MIN_PER_CELL, seed: int = 0,
                  device: str | torch.device = "cpu", sub: SubParticles | None = None) -> DriverSet:
    """Drivers clustered (K-Means) from the sub-particles, `per_cell` in each grid cell the
    moving sub-particles occupy (at most one per sub-particle), with prep's particles hung
    on their nearest drivers. Mass and volume are conserved per driver as in build_drivers.

    Against a converged reference, a 3,000-Gaussian plant on 48 cells moved 2.4% of its size
    off with 2.6 drivers a cell clustered from the Gaussians, and 0.17% with 8 a cell
    clustered from its sub-particles (docs/benchmarks.md, "Driving particles").
    sub: `sub_particles(scene, prep)` when the caller has them already.
    """
    sub = sub_particles(scene, prep, device=device) if sub is None else sub.to(device)
    count = split_driver_count(sub, prep.dx, per_cell)
    d = build_drivers(sub.positions, sub.volume, sub.mass, sub.static, prep.dx, count=count, seed=seed)
    points = torch.as_tensor(np.asarray(prep.positions_sim), dtype=torch.float32, device=sub.positions.device)
    return d.hung_on(points)
