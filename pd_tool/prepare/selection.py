"""Seeing a preparation: the scene recoloured by role, to check the foreground box and the
static region before a long fit or bake (behind `pdtool select`)."""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from pd_tool.prepare.preparation import PreparedScene
from pd_tool.core.scene import GaussianScene, rgb_to_sh

LEFT_OUT_RGB = (0.90, 0.15, 0.15)  # not simulated (outside the foreground, faint, outliers)
STATIC_RGB = (0.15, 0.35, 0.95)  # simulated but fixed
LOOSE_RGB = (1.00, 0.60, 0.05)  # moving, but a cell or more apart from the static ones


def selection_scene(prep: PreparedScene) -> GaussianScene:
    """The prepared scene with left-out Gaussians red, static ones blue, loose ones orange
    (PreparedScene.detached: a push carries them off), moving ones as they are."""
    scene = prep.scene
    rgb = scene.colors.detach().cpu().numpy().astype(np.float64)
    role = np.zeros(scene.count, np.int8)  # 0 left out, 1 static, 2 moving, 3 loose
    # filled particles are never drawn
    role[prep.foreground] = np.where(prep.static[: prep.count], 1, np.where(prep.detached()[: prep.count], 3, 2))
    rgb[role == 0] = LEFT_OUT_RGB
    rgb[role == 1] = STATIC_RGB
    rgb[role == 3] = LOOSE_RGB
    sh = torch.zeros((scene.count, 1, 3), dtype=scene.sh.dtype, device=scene.device)
    sh[:, 0] = rgb_to_sh(torch.as_tensor(rgb, dtype=scene.sh.dtype, device=scene.device))
    return dataclasses.replace(scene, sh=sh, raw=None)
