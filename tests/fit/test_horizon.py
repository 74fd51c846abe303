"""Stage 2's gradient horizon (FitSettings.material_horizon, `pdtool fit --horizon`): a
horizon as long as the video is full back-propagation, and a shorter one cuts the graph,
so its E gradient differs."""
from __future__ import annotations

import torch


def _material_grads(tmp_path, horizons):
    from _plant import tiny_plant_problem
    from pd_tool.fit.stages import material_iteration

    _, pb, v0 = tiny_plant_problem(tmp_path, 500, seed=3, size=24)
    grads = {}
    for h in horizons:
        pb.material.zero_grad(set_to_none=True)
        material_iteration(pb, [v0], h)
        grads[h] = torch.cat([p.grad.flatten() for p in pb.material.parameters()])
    return grads


def test_horizon_as_long_as_the_video_is_full_backprop_and_one_frame_differs(tmp_path) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        g = _material_grads(tmp_path, [None, 3, 1])  # 4 frames: 3 simulated frames
    finally:
        torch.set_num_threads(threads)
    scale = float(g[None].abs().max())
    assert scale > 0.0
    assert torch.allclose(g[3], g[None], rtol=1e-5, atol=1e-6 * scale)
    assert float((g[1] - g[None]).abs().max()) > 1e-3 * scale


def test_substeps_setting_is_a_floor_under_the_cfl_choice() -> None:
    from types import SimpleNamespace

    import numpy as np

    from pd_tool.fit.problem import FitProblem
    from pd_tool.fit.settings import FitSettings
    from pd_tool.sim import SimConfig

    n = 4

    def problem(settings: FitSettings) -> SimpleNamespace:
        # what FitProblem.substeps reads of a FitProblem: its DiffSim, built with
        # SimConfig(min_substeps=settings.substeps) as FitProblem.__init__ does, and the
        # range of counts so far, which it widens
        sim = SimpleNamespace(_static=np.zeros(n, bool), n=n, _mass=np.ones(n), _vol=np.full(n, 1e-3),
                              config=SimConfig(nu=0.3, cfl_safety=0.5, min_substeps=settings.substeps),
                              geo=SimpleNamespace(dx=0.05))
        return SimpleNamespace(s=settings, sim=sim, frame_dt=1 / 30, substeps_range=None)

    v0 = torch.zeros(n, 3)
    soft, stiff = torch.full((n,), 1e3), torch.full((n,), 1e9)
    free, floored = problem(FitSettings()), problem(FitSettings(substeps=40))
    cfl_soft, cfl_stiff = FitProblem.substeps(free, soft, v0), FitProblem.substeps(free, stiff, v0)
    assert cfl_soft < 40 < cfl_stiff
    assert FitProblem.substeps(floored, soft, v0) == 40  # the floor holds the count while E is soft
    assert FitProblem.substeps(floored, stiff, v0) == cfl_stiff  # and never undercuts stability
    # the report's substeps per frame: the least and the most counts taken
    assert free.substeps_range == (cfl_soft, cfl_stiff) and floored.substeps_range == (40, cfl_stiff)


def test_polish_iterations_back_propagate_through_every_frame(tmp_path) -> None:
    """polish_iters = N: the last N stage-2 iterations use the full horizon. With N equal
    to every iteration the fit is the full-horizon fit exactly; with N = 0 it is not."""
    import numpy as np

    from _plant import tiny_plant_video
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    scene = tiny_plant_video(tmp_path, 500, seed=3, size=24)
    refs = [load_reference_video(tmp_path / "video", working_size=24)]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        def fitted_E(name, **kw):
            s = FitSettings(quality="draft", working_long_side=24, velocity_iters=1, material_iters=2, **kw)
            return run_fit(scene, tmp_path / "plant.ply", refs, tmp_path / f"{name}.pdmat",
                           prepare_options=PrepareOptions(static_below=POT_TOP), settings=s).driver_E

        full = fitted_E("full", material_horizon=None)
        polished = fitted_E("polished", material_horizon=1, polish_iters=2)
        one = fitted_E("one", material_horizon=1)
    finally:
        torch.set_num_threads(threads)
    np.testing.assert_array_equal(polished, full)
    assert np.abs(np.log(one / full)).max() > 1e-4
