"""What a fit leaves beside the material file: report.json, a loss plot, the E field as a
coloured .ply and a rendered PNG, and a side-by-side preview (reference | fitted)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from pd_tool.atomic import atomic_output
from pd_tool.scene import GaussianScene, rgb_to_sh

# A perceptual blue -> green -> yellow ramp (viridis-like stops) for log E.
_STOPS = np.array([[0.267, 0.005, 0.329], [0.230, 0.322, 0.546], [0.128, 0.567, 0.551],
                   [0.369, 0.789, 0.383], [0.993, 0.906, 0.144]])


def colormap(u: np.ndarray) -> np.ndarray:
    """RGB [N, 3] in 0-1 for values u [N] in 0-1."""
    u = np.clip(np.asarray(u, np.float64), 0, 1) * (len(_STOPS) - 1)
    i = np.minimum(u.astype(int), len(_STOPS) - 2)
    f = (u - i)[:, None]
    return _STOPS[i] * (1 - f) + _STOPS[i + 1] * f


def e_field_scene(scene: GaussianScene, foreground: np.ndarray, gaussian_E: np.ndarray,
                  E_range: tuple[float, float] | None = None) -> tuple[GaussianScene, tuple[float, float]]:
    """A copy of the scene whose simulated Gaussians are coloured by log E (others grey)."""
    logE = np.log10(gaussian_E)
    lo, hi = (np.log10(E_range[0]), np.log10(E_range[1])) if E_range else (logE.min(), logE.max())
    if hi - lo < 1e-6:
        lo, hi = lo - 0.5, hi + 0.5
    rgb = np.full((scene.count, 3), 0.75)
    rgb[foreground] = colormap((logE - lo) / (hi - lo))
    sh = torch.zeros((scene.count, 1, 3), dtype=scene.sh.dtype, device=scene.device)
    sh[:, 0] = rgb_to_sh(torch.as_tensor(rgb, dtype=scene.sh.dtype, device=scene.device))
    return dataclasses.replace(scene, sh=sh, raw=None), (10 ** lo, 10 ** hi)


def write_report(path: Path, data: dict) -> Path:
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=float))
    return path


def write_fit_outputs(out_dir: Path, stem: str, scene: GaussianScene, result, videos: list, settings,
                      *, preview: bool = True) -> dict[str, Path]:
    """Write every side output of a fit into out_dir; returns their paths by kind."""
    from pd_tool.io import save_ply
    from pd_tool.plots import line_plot
    from pd_tool.preview import save_png, write_preview_any
    from pd_tool.reference import simulate_reference
    from pd_tool.views import render_image

    paths: dict[str, Path] = {}
    L = result.losses
    n1 = len(L["velocity"])
    series = {}
    if L["velocity"]:
        series["stage 1 (velocity)"] = (list(range(1, n1 + 1)), L["velocity"])
    if L["material"]:
        series["stage 2 (material)"] = (list(range(n1 + 1, n1 + 1 + len(L["material"]))), L["material"])
    if L.get("calibrate"):  # the whole-clip loss: on another footing than stage 2's, which sums one-frame steps
        n2 = n1 + len(L["material"])
        series["stage 3 (calibration)"] = (list(range(n2 + 1, n2 + 1 + len(L["calibrate"]))), L["calibrate"])
    if series:
        paths["loss_plot"] = line_plot(out_dir / f"{stem}.loss.png", series, title="fit loss (lambda L1 + (1-lambda) D-SSIM)",
                                       xlabel="iteration", ylabel="loss", logy=False)
    e_scene, e_range = e_field_scene(scene, result.prep.foreground, result.gaussian_E)
    paths["e_field_ply"] = save_ply(e_scene, out_dir / f"{stem}.E.ply")
    cam = videos[0].camera
    paths["e_field_png"] = save_png(out_dir / f"{stem}.E.png", render_image(e_scene, cam, background=settings.background))
    if preview:
        v0 = np.asarray(result.driver_v0, np.float64)
        sim = simulate_reference(scene, result.prep, result.drivers, result.driver_E, v0, cam,
                                 n_frames=videos[0].num_frames, fps=videos[0].fps, nu=settings.nu,
                                 damping=settings.damping, device=settings.device, background=settings.background)
        ref = (videos[0].frames.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        paths["preview"] = write_preview_any([np.concatenate([a, b], axis=1) for a, b in zip(ref, sim)],
                                             out_dir / f"{stem}.preview.mp4", videos[0].fps)
    report = {
        "material": str(result.material_path),
        "losses": L,
        "seconds": result.seconds,
        "drivers": int(len(result.driver_E)),
        "E_range_pa": list(e_range),
        "E_percentiles_pa": {str(q): float(np.percentile(result.gaussian_E, q)) for q in (5, 25, 50, 75, 95)},
        "outputs": {k: str(v) for k, v in paths.items()},
        "settings": dataclasses.asdict(settings),
    }
    paths["report"] = write_report(out_dir / f"{stem}.report.json", report)
    return paths
