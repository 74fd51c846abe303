"""What a fit leaves beside the material file: report.json, a loss plot, the E field as a
coloured .ply and a rendered PNG (with a colour bar in Pa and the E statistics under it),
and a side-by-side preview (reference | fitted)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import torch

from pd_tool.core.atomic import WRITTEN_BY, atomic_output, check_destination, check_outputs, check_own_file
from pd_tool.core.scene import GaussianScene, rgb_to_sh
from pd_tool.fit.reference import simulate_reference
from pd_tool.fit.run import FitResult
from pd_tool.fit.settings import FitSettings
from pd_tool.io import save_ply
from pd_tool.render.plots import STRIP_MIN_WIDTH, colorbar_strip, line_plot, sci_label
from pd_tool.render.preview import ffmpeg_exe, save_png, write_preview_any
from pd_tool.render.views import render_image


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


E_PERCENTILES = (5, 25, 50, 75, 95)  # %, of the simulated Gaussians' E, in the report
E_PICTURE_PERCENTILES = (5, 50, 95)  # %, the ones printed on the E picture


def e_statistics(scene: GaussianScene, foreground: np.ndarray, static: np.ndarray,
                 gaussian_E: np.ndarray) -> dict:
    """E of the simulated Gaussians, summed up: {"percentiles_pa": {"5": E, ...} over all of
    them (E_PERCENTILES), "regions": {name: {"E_median_pa": E or None, "simulated": n,
    "fixed": k}}}, regions from scene.labels ({} without them), named by scene.label_names
    ("region i" where a label has no name: a PLY keeps the labels, not the names). A
    region's median is over its simulated Gaussians, fixed (static) ones included; None
    when none of its Gaussians is simulated.

    foreground: indices [F] into the scene; static: PreparedScene.static, bool [F] or
    longer (interior particles from filling follow the F Gaussians); gaussian_E [F] Pa."""
    E = np.asarray(gaussian_E, np.float64)
    out: dict = {"percentiles_pa": {str(q): float(np.percentile(E, q)) for q in E_PERCENTILES}, "regions": {}}
    if scene.labels is None:
        return out
    all_labels = np.asarray(scene.labels)
    labels = all_labels[np.asarray(foreground)]
    static = np.asarray(static, bool)[: len(labels)]
    names = tuple(scene.label_names)
    ids = range(len(names)) if names else (int(i) for i in np.unique(all_labels))
    for i in ids:
        sel = labels == i
        name = str(names[i]) if i < len(names) else f"region {i}"
        out["regions"][name] = {"E_median_pa": float(np.median(E[sel])) if sel.any() else None,
                                "simulated": int(sel.sum()), "fixed": int((sel & static).sum())}
    return out


def e_picture_notes(stats: dict, n_simulated: int) -> list[str]:
    """The lines of statistics printed under the E picture (stats from e_statistics)."""
    pct = stats["percentiles_pa"]
    notes = [f"E of the {n_simulated:,} simulated Gaussians: "
             + ", ".join(f"{q}% {sci_label(pct[str(q)])}" for q in E_PICTURE_PERCENTILES) + " Pa"]
    regions = []
    for name, r in stats["regions"].items():
        if r["E_median_pa"] is None:
            regions.append(f"{name} not simulated")
        else:
            fixed = " (fixed)" if r["fixed"] == r["simulated"] else ""
            regions.append(f"{name} {sci_label(r['E_median_pa'])}{fixed}")
    if regions:
        notes.append("median E per region: " + ", ".join(regions) + " Pa")
    notes.append("grey: not simulated")
    return notes


def e_field_picture(render: np.ndarray, E_range: tuple[float, float], notes: list[str]) -> np.ndarray:
    """The E picture: the render [H, W, 3] uint8 at the top left, unchanged, over a strip
    holding the colour bar of `colormap` for E_range (Pa, log scale, as e_field_scene
    coloured it) and the notes. Returns uint8 [H + strip, max(W, STRIP_MIN_WIDTH), 3]."""
    h, w = render.shape[:2]
    width = max(w, STRIP_MIN_WIDTH)
    strip = colorbar_strip(width, E_range[0], E_range[1], colormap, label="Young's modulus E, Pa (log scale)",
                           notes=notes)
    out = np.full((h + len(strip), width, 3), 255, np.uint8)
    out[:h, :w] = render[..., :3]
    out[h:] = strip
    return out


def write_report(path: Path, data: dict, *, own_only: bool = True) -> Path:
    """Write the fit's report.json (marked as pdtool's); by default it replaces only a
    file that pdtool wrote."""
    with atomic_output(path, own_only=own_only, what="the fit's report") as tmp:
        tmp.write_text(json.dumps({"written_by": WRITTEN_BY, **data}, indent=2, default=float))
    return path


def fit_output_paths(out_dir: str | Path, stem: str, *, preview: bool = True) -> dict[str, tuple[Path, str]]:
    """The side outputs a fit writes beside its material file: {kind: (path, what it is)}.
    The preview is listed as .mp4 (and as .gif too when no mp4 encoder is installed, the
    fallback name)."""
    out_dir = Path(out_dir)
    paths = {
        "loss_plot": (out_dir / f"{stem}.loss.png", "the fit's loss plot"),
        "e_field_ply": (out_dir / f"{stem}.E.ply", "the fit's E field"),
        "e_field_png": (out_dir / f"{stem}.E.png", "the fit's E field picture"),
        "report": (out_dir / f"{stem}.report.json", "the fit's report"),
    }
    if preview:
        paths["preview"] = (out_dir / f"{stem}.preview.mp4", "the fit's preview video")
        try:
            ffmpeg_exe()
        except (ImportError, RuntimeError):
            paths["preview_gif"] = (out_dir / f"{stem}.preview.gif", "the fit's preview video")
    return paths


def check_fit_outputs(out_dir: str | Path, stem: str, *, preview: bool = True,
                      inputs: dict[str, str | Path | None] | None = None) -> None:
    """Refuse (OutputError, one line naming the file), before a fit runs, side outputs
    that would replace a file pdtool did not write or one of the fit's inputs (the scene,
    a video). Nobody named these files, so unlike -o they never replace someone else's."""

    paths = fit_output_paths(out_dir, stem, preview=preview)
    check_outputs({f"{what}{' (gif)' if kind.endswith('gif') else ''}": p for kind, (p, what) in paths.items()}, {},
                  inputs or {})
    fix = "move or rename it, or write the fit elsewhere with -o"
    for p, what in paths.values():
        check_own_file(p, what, fix)
    for p, what in paths.values():
        check_destination(p)


def fit_simulation_record(result: "FitResult", settings: "FitSettings") -> dict:
    """How the fit simulated, for its report: the quality, the grid (cells along the longest
    axis, cells per axis, cell size in m, metres per scene unit), the CFL safety factor,
    quantile and substep floor, the least and most substeps per frame it took ([lo, hi];
    None when unknown), the drivers, and the iterations per stage.

    result: the FitResult; settings: the FitSettings the fit ran at, resolved."""
    prep, substeps, cfl_safety = result.prep, result.substeps, result.cfl_safety
    return {
        "quality": settings.quality,
        "grid_res": int(prep.options.grid_res),
        "grid_dims": [int(n) for n in prep.grid_dims],
        "dx_m": float(prep.dx),
        "meters_per_unit": float(prep.transform.scale),
        "cfl_safety": None if cfl_safety is None else float(cfl_safety),
        "cfl_quantile": settings.cfl_quantile,
        "substeps_floor": settings.substeps,
        "substeps_per_frame": None if substeps is None else [int(substeps[0]), int(substeps[1])],
        "driver_ratio": settings.driver_ratio,
        "min_drivers_per_cell": settings.min_drivers_per_cell,
        "driver_seed": settings.seed,
        "iterations": {"rounds": settings.rounds, "velocity": settings.velocity_iters,
                       "material": settings.material_iters, "polish": settings.polish_iters,
                       "calibrate": settings.calibrate_iters},
    }


def write_fit_outputs(out_dir: Path, stem: str, scene: GaussianScene, result, videos: list, settings,
                      *, preview: bool = True, clips: list[dict] | None = None) -> dict[str, Path]:
    """Write every side output of a fit into out_dir; returns their paths by kind. `clips`:
    per video, which frames of the clip the fit used and whether it was stabilised
    (pd_tool.video.clip.ClipChoice as a dict), recorded in the report.

    Each one replaces only a file that pdtool wrote (they are checked together first, so
    a refusal writes none of them) and none of the fit's inputs. Raises OutputError."""

    inputs: dict[str, str | Path | None] = {"SCENE": getattr(scene, "source", None)}
    for i, v in enumerate(videos):
        inputs[f"VIDEO {i}"] = getattr(v, "folder", None)
        inputs[f"the camera of VIDEO {i}"] = getattr(v, "camera_path", None)
    check_fit_outputs(out_dir, stem, preview=preview, inputs=inputs)
    planned = fit_output_paths(out_dir, stem, preview=preview)
    paths: dict[str, Path] = {}
    L = result.losses
    n1 = len(L["velocity"])
    series = {}
    if L["velocity"]:
        series["stage 1 (velocity)"] = (list(range(1, n1 + 1)), L["velocity"])
    if L["material"]:
        series["stage 2 (material)"] = (list(range(n1 + 1, n1 + 1 + len(L["material"]))), L["material"])
    if L.get("calibrate"):  # the whole-clip loss: on stage 2's footing only when its horizon is every frame
        n2 = n1 + len(L["material"])
        series["stage 3 (calibration)"] = (list(range(n2 + 1, n2 + 1 + len(L["calibrate"]))), L["calibrate"])
    if series:
        paths["loss_plot"] = line_plot(planned["loss_plot"][0], series,
                                       title="fit loss (lambda L1 + (1-lambda) D-SSIM)",
                                       xlabel="iteration", ylabel="loss", logy=False, own_only=True)
    e_scene, e_range = e_field_scene(scene, result.prep.foreground, result.gaussian_E)
    paths["e_field_ply"] = save_ply(e_scene, planned["e_field_ply"][0], own_only=True, what=planned["e_field_ply"][1])
    stats = e_statistics(scene, result.prep.foreground, result.prep.static, result.gaussian_E)
    cam = videos[0].camera
    picture = e_field_picture(render_image(e_scene, cam, background=settings.background), e_range,
                              e_picture_notes(stats, result.prep.count))
    paths["e_field_png"] = save_png(planned["e_field_png"][0], picture, own_only=True, what=planned["e_field_png"][1])
    if preview:
        v0 = np.asarray(result.driver_v0, np.float64)
        sim = simulate_reference(scene, result.prep, result.drivers, result.driver_E, v0, cam,
                                 n_frames=videos[0].num_frames, fps=videos[0].fps, nu=settings.nu,
                                 damping=settings.damping, device=settings.device, background=settings.background)
        ref = (videos[0].frames.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        paths["preview"] = write_preview_any([np.concatenate([a, b], axis=1) for a, b in zip(ref, sim)],
                                             planned["preview"][0], videos[0].fps, own_only=True)
    ran = result.settings or settings.resolved()
    report = {
        "material": str(result.material_path),
        "videos": [str(v.folder) for v in videos],  # what it was fitted to, in the fit's order
        "clips": clips if clips is not None else [],
        "losses": L,
        "seconds": result.seconds,
        "drivers": int(len(result.driver_E)),
        "E_range_pa": list(e_range),
        "E_percentiles_pa": stats["percentiles_pa"],
        "E_region_median_pa": {k: r["E_median_pa"] for k, r in stats["regions"].items()},
        "region_gaussians": {k: {"simulated": r["simulated"], "fixed": r["fixed"]}
                             for k, r in stats["regions"].items()},
        "outputs": {k: str(v) for k, v in paths.items()},
        "settings": dataclasses.asdict(ran),
        "simulation": fit_simulation_record(result, ran),
        "prepare": result.prep.options.to_dict(),
    }
    paths["report"] = write_report(planned["report"][0], report)
    return paths
