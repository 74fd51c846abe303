"""From simulated driving particles to every Gaussian of the scene (bake, fit, demo video).

`GaussianAnimator` holds the rest state in simulation axes and, given the drivers'
current positions (metres, simulation box), returns the whole scene's Gaussian centres and
orientations in scene units and axes. Gaussians that are not simulated (background,
outliers, transparent ones) and static ones (the Dirichlet region: a pot, a clamp) keep
their rest pose. Differentiable in the driver positions.
"""
from __future__ import annotations

import numpy as np
import torch

from pd_tool.core.quaternion import matrix_to_quat, quat_multiply
from pd_tool.core.scene import GaussianScene
from pd_tool.drivers import DriverInterpolator, DriverSet
from pd_tool.prepare.preparation import PreparedScene


class GaussianAnimator:
    """Rigidly interpolate every simulated Gaussian from its 8 nearest drivers.

    Args:
        scene: the full scene (scene units).
        prep: its preparation (foreground indices, transform).
        drivers: a pd_tool.drivers.DriverSet built on prep.positions_sim.
        device: torch device of the outputs.
    """

    def __init__(self, scene: GaussianScene, prep: PreparedScene, drivers: DriverSet,
                 device: str | torch.device = "cpu", mode: str = "rigid") -> None:
        self.device = torch.device(device)
        self.mode = mode
        dev = self.device
        self.fg = torch.as_tensor(prep.foreground, device=dev)
        R = torch.as_tensor(prep.transform.R, dtype=torch.float32, device=dev)
        self._R = R
        self._scale = float(prep.transform.scale)
        self._shift = torch.as_tensor(prep.transform.shift, dtype=torch.float32, device=dev)
        self._q_sim = matrix_to_quat(R.double()).float()  # scene axes -> sim axes
        self._q_scene = matrix_to_quat(R.double().T).float()  # sim axes -> scene axes
        q_fg = scene.quats.to(dev)[self.fg]
        f = prep.count  # filled interior particles (after the Gaussians) are simulated, never drawn
        self.rest_points = torch.as_tensor(prep.positions_sim[:f], dtype=torch.float32, device=dev)
        self.rest_quats = quat_multiply(self._q_sim.expand_as(q_fg), q_fg)
        self.drivers_rest = drivers.positions.to(dev, torch.float32)
        self.neighbors = drivers.neighbors[:f].to(dev)
        self.scene_positions = scene.positions.to(dev)
        self.scene_quats = scene.quats.to(dev)
        self._interp = DriverInterpolator(self.rest_points, self.rest_quats, self.drivers_rest, self.neighbors,
                                          mode=mode)
        # A static Gaussian near the edge of its region can have free drivers among its 8
        # nearest (one grid cell reaches deeper on a coarse grid): it must not follow them.
        # Static Gaussians keep the scene's own values, bit for bit: a round trip through
        # simulation axes would move them by a rounding error each frame, and the USD
        # writer would then check every static instance against its tolerance (15 ms a
        # frame at 300k) instead of comparing bytes.
        free = torch.as_tensor(~np.asarray(prep.static[:f], bool), device=dev)
        self._free_rows = torch.nonzero(free).squeeze(1)  # rows of the simulated Gaussians that move
        self._fg_free = self.fg[self._free_rows]

    def to_scene_points(self, x_sim: torch.Tensor) -> torch.Tensor:
        """Simulation metres [M, 3] -> scene units [M, 3] (torch, differentiable)."""
        return ((x_sim - self._shift) / self._scale) @ self._R

    def __call__(self, drivers_now: torch.Tensor | np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """Scene positions [N, 3] and quaternions [N, 4] (w, x, y, z) for drivers at
        `drivers_now` [Q, 3] (metres, simulation box)."""
        d = torch.as_tensor(drivers_now, dtype=torch.float32, device=self.device)
        pts, quats = self._interp(d)[:2]
        pts, quats = pts[self._free_rows], quats[self._free_rows]
        q_scene = quat_multiply(self._q_scene.expand_as(quats), quats)
        positions = self.scene_positions.index_put((self._fg_free,), self.to_scene_points(pts))
        orientations = self.scene_quats.index_put((self._fg_free,), q_scene)
        return positions, orientations
