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


def selection_scene(prep: PreparedScene) -> GaussianScene:
    """The prepared scene with left-out Gaussians red, static ones blue, moving ones as they are."""
    scene = prep.scene
    rgb = scene.colors.detach().cpu().numpy().astype(np.float64)
    role = np.zeros(scene.count, np.int8)  # 0 left out, 1 static, 2 moving
    role[prep.foreground] = np.where(prep.static[: prep.count], 1, 2)  # filled particles are never drawn
    rgb[role == 0] = LEFT_OUT_RGB
    rgb[role == 1] = STATIC_RGB
    sh = torch.zeros((scene.count, 1, 3), dtype=scene.sh.dtype, device=scene.device)
    sh[:, 0] = rgb_to_sh(torch.as_tensor(rgb, dtype=scene.sh.dtype, device=scene.device))
    return dataclasses.replace(scene, sh=sh, raw=None)
