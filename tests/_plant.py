"""A tiny synthetic plant and its reference video, for the fit tests: the plant's
regions at their true E (synthetic.REGION_TRUTH_E) with the default push, simulated on
a 24-cell fit grid with one driver per ten Gaussians."""
from __future__ import annotations

from pathlib import Path


def tiny_plant_video(folder: Path, gaussians: int, seed: int, size: int, n_frames: int = 4, thin: bool = True):
    """Write folder/plant.ply and the reference video folder/video (size x size px, frame
    0 at rest); returns the scene as loaded back from the .ply. thin: 3 mm leaves and
    petals (make_plant's default), else 2 and 4 cm."""
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_video
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, make_plant
    from pd_tool.render.views import scene_camera

    save_splats(make_plant(gaussians, seed=seed, thin=thin), folder / "plant.ply")
    scene = load_splats(folder / "plant.ply")
    plant_reference_video(folder / "video", scene, scene_camera(scene, width=size, height=size),
                          prepare_options=PrepareOptions(static_below=POT_TOP, grid_res=24),
                          region_E=REGION_TRUTH_E, driver_ratio=0.1, n_frames=n_frames, cfl_safety=0.6)
    return scene


def tiny_plant_inputs(folder: Path):
    """tiny_plant_video of the fit tests' size (600 Gaussians, seed 1, 24 px), loaded as
    `run_fit` takes it: (folder, scene, [reference video])."""
    from pd_tool.video.folder import load_reference_video

    scene = tiny_plant_video(folder, 600, seed=1, size=24)
    return folder, scene, [load_reference_video(folder / "video", working_size=24)]


def tiny_plant_problem(folder: Path, gaussians: int, seed: int, size: int, n_frames: int = 4, thin: bool = True,
                       **settings):
    """tiny_plant_video, then the draft-quality FitProblem over it (FitSettings overridden by
    `settings`) and the video's true initial velocity at its drivers ([Q, 3] m/s; the fit's
    drivers are the video's). Returns (scene, problem, v0)."""
    import torch

    from pd_tool.fit.problem import FitProblem
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import push_velocity
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(folder, gaussians, seed=seed, size=size, n_frames=n_frames, thin=thin)
    refs = [load_reference_video(folder / "video", working_size=size)]
    pb = FitProblem(scene, refs, PrepareOptions(static_below=POT_TOP),
                    FitSettings(quality="draft", working_long_side=size, **settings).resolved())
    v0 = torch.tensor(push_velocity(pb.x_rest.double().numpy(), pb.static.numpy(), speed=0.6), dtype=torch.float32)
    return scene, pb, v0
