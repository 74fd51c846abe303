"""Rendering a scene from a named or automatic camera (behind `pdtool render`)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pd_tool.core.cameras import Camera, auto_camera, load_cameras, select_view
from pd_tool.core.errors import CameraError
from pd_tool.core.scene import GaussianScene
from pd_tool.prepare.orient import resolve_up
from pd_tool.render import render

DEFAULT_SIZE = (768, 432)  # width, height of an automatic camera, pixels (16:9)


def scene_camera(
    scene: GaussianScene,
    camera_path: str | Path | None = None,
    view: str | int | None = None,
    *,
    width: int | None = None,
    height: int | None = None,
    up_axis: str = "+z",
) -> Camera:
    """The camera to render `scene` from: a view of a camera file, or an automatic one.

    width/height resize a file's camera keeping its field of view (give both, or one to
    keep the aspect ratio). up_axis "auto" takes the axis guessed from the splats
    (pd_tool.prepare.orient.guess_up; `auto_up` says which).
    """
    if camera_path is None:
        up_axis = auto_up(scene, up_axis)[0]
        if view is not None:
            raise CameraError("--view needs --camera FILE; without a camera file pdtool frames the object itself")
        w, h = width or DEFAULT_SIZE[0], height or DEFAULT_SIZE[1]
        return auto_camera(scene.positions.detach().cpu().numpy(), w, h, up_axis=up_axis.lstrip("+"))
    cam = select_view(load_cameras(camera_path), view)
    if width or height:
        w = width or round(cam.width * height / cam.height)
        h = height or round(cam.height * width / cam.width)
        cam = cam.resized(int(w), int(h))
    return cam


def auto_up(scene: GaussianScene, up_axis: str = "auto"):
    """(the up axis, the UpGuess behind it or None): `up_axis` itself unless "auto"."""

    return resolve_up(scene.positions.detach().cpu().double().numpy(), up_axis,
                      scene.scales.detach().cpu().double().numpy(), scene.opacities.detach().cpu().double().numpy())


def render_image(
    scene: GaussianScene,
    camera: Camera,
    *,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    positions: torch.Tensor | None = None,
    quats: torch.Tensor | None = None,
) -> np.ndarray:
    """Render to an 8-bit RGB image [H, W, 3]; positions/quats override the scene's (animation)."""

    with torch.no_grad():
        out = render(
            scene.positions if positions is None else positions,
            scene.quats if quats is None else quats,
            scene.scales, scene.opacities, scene.sh, camera, background=background,
        )
    return (out.rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()
