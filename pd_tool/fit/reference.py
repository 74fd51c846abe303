"""Synthetic reference videos: simulate a known material with a known initial push, render
it, and write a video folder that `pdtool fit` reads (the demo and the recovery benchmark).

It uses the same preparation, driving particles, simulator, interpolation and rasteriser as
bake and fit, so a fit of such a video tests the whole chain against a known truth.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from pd_tool.bake.animate import GaussianAnimator
from pd_tool.bake.baker import ForceSpec, force_mask
from pd_tool.core.cameras import Camera
from pd_tool.core.scene import GaussianScene
from pd_tool.io import load_splats, save_splats
from pd_tool.io.synthetic import POT_TOP, REGIONS, REGION_TRUTH_E, make_plant
from pd_tool.materials.presets import fit_min_per_cell, fit_simulation, load_preset
from pd_tool.prepare.preparation import PrepareOptions, PreparedScene, prepare_scene
from pd_tool.render.views import render_image, scene_camera
from pd_tool.sim import MPMSolver, SimConfig
from pd_tool.video.folder import write_video_folder

# simulate_positions' push without a radius: on the free drivers within this fraction of the
# object's longest side of its point
PUSH_RADIUS_FRACTION = 0.3


@dataclass
class ReferenceTruth:
    """What made a synthetic video: per-driver E (Pa) and v0 (m/s), per-Gaussian E (Pa)."""

    driver_E: np.ndarray
    driver_v0: np.ndarray
    gaussian_E: np.ndarray  # [F] over prep.foreground


def push_velocity(points_sim: np.ndarray, static: np.ndarray, direction=(1.0, 0.0, 0.0), speed: float = 0.5) -> np.ndarray:
    """An initial push [N, 3] m/s: `speed` along `direction` (simulation axes), growing
    linearly with height above the lowest free point, zero on static particles."""
    d = np.asarray(direction, np.float64)
    d = d / np.linalg.norm(d)
    free = ~static
    z = points_sim[:, 2]
    z0 = z[free].min() if free.any() else 0.0
    h = max(float(z[free].max() - z0), 1e-9) if free.any() else 1.0
    v = speed * np.clip((z - z0) / h, 0.0, 1.0)[:, None] * d[None, :]
    v[static] = 0.0
    return v


def simulate_reference(
    scene: GaussianScene,
    prep: PreparedScene,
    drivers,
    driver_E: np.ndarray,
    driver_v0: np.ndarray,
    camera: Camera,
    *,
    n_frames: int = 14,
    fps: float = 30.0,
    nu: float = 0.3,
    damping: float = 0.0,
    cfl_safety: float = 0.5,
    substeps: int | None = None,
    device: str = "cpu",
    background=(1.0, 1.0, 1.0),
    displacement: np.ndarray | None = None,
) -> np.ndarray:
    """Simulate and render `n_frames` frames (frame 0 = rest): uint8 [T, H, W, 3].
    substeps: per frame, or None for the CFL choice. displacement: when given, an [N]
    array (one per Gaussian) raised in place to each Gaussian's largest displacement from
    rest in scene units."""

    cfg = SimConfig(grid_res=max(prep.grid_dims), domain=prep.domain, nu=nu, gravity=(0.0, 0.0, 0.0),
                    damping=damping, cfl_safety=cfl_safety, substeps=substeps)
    solver = MPMSolver(drivers.positions.double().cpu().numpy(), drivers.volume.cpu().numpy(),
                       drivers.mass.cpu().numpy(), driver_E, drivers.static.cpu().numpy(), cfg, device=device)
    solver.set_velocity(driver_v0)
    animator = GaussianAnimator(scene, prep, drivers, device=scene.device)
    frames = [render_image(scene, camera, background=background)]
    rest = scene.positions.detach() if displacement is not None else None
    for _ in range(1, n_frames):
        solver.step_frame(1.0 / fps)
        with torch.no_grad():
            pos, quats = animator(solver.positions())
        if rest is not None:
            np.maximum(displacement, (pos - rest).norm(dim=1).cpu().numpy(), out=displacement)
        frames.append(render_image(scene, camera, background=background, positions=pos, quats=quats))
    return np.stack(frames)


def plant_reference_video(
    out: str | Path,
    scene: GaussianScene,
    camera: Camera,
    *,
    prepare_options: PrepareOptions,
    region_E: dict[str, float],
    driver_ratio: float,
    min_per_cell: float = 0.0,
    n_frames: int = 14,
    fps: float = 30.0,
    nu: float = 0.3,
    push_speed: float = 0.6,
    push_direction: tuple[float, float, float] = (1.0, 0.0, 0.0),
    cfl_safety: float = 0.5,
    substeps: int | None = None,
    seed: int = 0,
    device: str = "cpu",
) -> tuple[Path, ReferenceTruth, PreparedScene]:
    """A reference video of a labelled scene (the synthetic plant) with E per region.

    Each driver takes the E of the majority region of its Gaussians. Returns the folder,
    the truth and the preparation.
    """

    if scene.labels is None:
        raise ValueError("plant_reference_video needs a scene with region labels")
    prep = prepare_scene(scene, prepare_options)
    drivers = prep.build_drivers(ratio=driver_ratio, seed=seed, device=device, min_per_cell=min_per_cell)
    labels = scene.labels[prep.foreground]

    names = scene.label_names or REGIONS
    table = np.array([region_E[name] for name in names], np.float64)
    gaussian_E = table[labels]
    member = drivers.labels.cpu().numpy()[: prep.count]  # Gaussians only; filled particles follow
    q = len(drivers.positions)
    votes = np.zeros((q, len(table)))
    np.add.at(votes, (member, labels), 1.0)
    driver_E = table[votes.argmax(axis=1)]
    d_rest = drivers.positions.double().cpu().numpy()
    d_static = drivers.static.cpu().numpy().astype(bool)
    driver_v0 = push_velocity(d_rest, d_static, direction=push_direction, speed=push_speed)
    frames = simulate_reference(scene, prep, drivers, driver_E, driver_v0, camera, n_frames=n_frames, fps=fps,
                                nu=nu, cfl_safety=cfl_safety, substeps=substeps, device=device)
    folder = write_video_folder(out, frames, camera, fps, overwrite=True)
    return folder, ReferenceTruth(driver_E, driver_v0, gaussian_E), prep


def plant_reference_for_fit(
    out: str | Path,
    scene: GaussianScene,
    camera: Camera,
    quality: str | Path,
    **kwargs,
) -> tuple[Path, ReferenceTruth, PreparedScene]:
    """plant_reference_video of the synthetic plant (pot static, REGION_TRUTH_E) simulated
    with the fit's grid, CFL safety and driver ratio of a quality preset, so that a fit at
    that quality sees the same discretisation as the video. kwargs: n_frames, fps,
    push_speed, push_direction, device, ..."""

    q = load_preset("quality", quality)
    grid, cfl, ratio = fit_simulation(q)
    return plant_reference_video(out, scene, camera, prepare_options=PrepareOptions(static_below=POT_TOP, grid_res=grid),
                                 region_E=REGION_TRUTH_E, driver_ratio=ratio, min_per_cell=fit_min_per_cell(q),
                                 cfl_safety=cfl, **kwargs)


def reference_height(width: int) -> int:
    """Height (px) of a synthetic reference video `width` px wide, as the demo-scale
    benchmarks and tests render the plant: 16:9 from 512 px up, square below (small CPU
    runs, where a 9/16 crop would leave the plant a few pixels tall)."""
    return width * 9 // 16 if width >= 512 else width


def write_plant_with_video(folder: str | Path, n: int, *, size: int = 64, frames: int = 4) -> Path:
    """The synthetic plant of n Gaussians (make_plant(n, seed=0, thin=False)) as `folder`/plant.ply and
    a reference video of it as the video folder `folder`/video: REGION_TRUTH_E pushed
    sideways, `frames` frames at 30 fps of `size` x `size` px from the scene camera, on a
    coarse discretisation (24 cells, driver ratio 0.1, CFL safety 0.6) that keeps it quick
    at any n. Deterministic; the CPU is used. Returns `folder`."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    save_splats(make_plant(n, seed=0, thin=False), folder / "plant.ply")
    scene = load_splats(folder / "plant.ply")  # as a fit reads it back
    plant_reference_video(folder / "video", scene, scene_camera(scene, width=size, height=size),
                          prepare_options=PrepareOptions(static_below=POT_TOP, grid_res=24),
                          region_E=REGION_TRUTH_E, driver_ratio=0.1, n_frames=frames, cfl_safety=0.6)
    return folder


def simulate_positions(scene: GaussianScene, prep: PreparedScene, drivers, driver_E: np.ndarray, *, nu: float,
                       seconds: float, fps: float, accel, device: str, cfl_safety: float,
                       substeps: int | None = None, stats: dict | None = None, duration: float = 0.5,
                       at: tuple[float, float, float] | str = "top", radius: float | None = None) -> np.ndarray:
    """Every Gaussian's position [T, N, 3] (scene units, T = round(seconds * fps) + 1, frame 0
    = rest) of `scene` moved by its drivers with per-driver E `driver_E` [Q] (Pa), no
    gravity, under a drag: `accel` (3,) scene units / s^2 for the first `duration` s on the
    free drivers within `radius` scene units (default: 0.3 of the object's longest side) of
    `at` (a point in scene units, or "top"). The truth that a fitted material's motion
    under a new force is compared with, through the bake's own force, simulator and
    interpolation.

    substeps: a floor on the substeps per frame (a stiffer E still gets its CFL count);
    None: the CFL count. stats, when given, receives "substeps": the most substeps a
    frame took."""
    cfg = SimConfig(grid_res=max(prep.grid_dims), domain=prep.domain, nu=nu, gravity=(0.0, 0.0, 0.0),
                    cfl_safety=cfl_safety, min_substeps=substeps)
    d_rest = drivers.positions.double().cpu().numpy()
    d_static = drivers.static.cpu().numpy().astype(bool)
    solver = MPMSolver(d_rest, drivers.volume.cpu().numpy(), drivers.mass.cpu().numpy(), driver_E, d_static, cfg,
                       device=device)
    spec = ForceSpec(accel=accel, at=at, radius=radius, radius_fraction=PUSH_RADIUS_FRACTION, start=0.0,
                     duration=duration)
    solver.add_force(force_mask(prep, d_rest, d_static, spec), prep.transform.vector_to_sim(np.asarray(accel)), 0.0,
                     duration)
    anim = GaussianAnimator(scene, prep, drivers, device=scene.device)
    out = [scene.positions.detach().cpu().numpy()]
    most = 0
    for _ in range(int(round(seconds * fps))):
        most = max(most, solver.step_frame(1.0 / fps))
        with torch.no_grad():
            out.append(anim(solver.positions())[0].cpu().numpy())
    if stats is not None:
        stats["substeps"] = most
    return np.stack(out)
