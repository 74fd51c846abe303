"""Memory estimate and check before a bake or fit.

The estimate (pd_tool.prepare.memory) is compared with the peak RSS of a bake in fresh
subprocesses at three sizes (bench/memory_estimate.py does the measuring: the baseline is
the same process after it imported pdtool, torch, warp and usd_export and made the scene).
A run that cannot fit is refused before any heavy work, with one line naming --quality,
the driver ratio and the resolution.
"""
from __future__ import annotations

from pathlib import Path

import pytest
from _bench import load_bench
from click.testing import CliRunner

TOLERANCE = 0.30  # |estimate / measured - 1|


def _bench():
    return load_bench("memory_estimate")


@pytest.mark.slow
def test_bake_estimate_within_30_percent_of_measured_peak(tmp_path: Path) -> None:
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc to measure peak RSS")
    bench = _bench()
    sizes = (1500, 5000, 12000)
    dirs = {n: tmp_path / f"n{n}" for n in sizes}
    for d in dirs.values():
        d.mkdir()
    # the three measurements run at once: each is its own process with its own peak
    procs = {n: bench.spawn("bake", n, "draft", "cpu", dirs[n], preview=(n == 5000)) for n in sizes}
    rows = {n: bench.collect(p) for n, p in procs.items()}
    for n, r in rows.items():
        assert r["measured"] > 0, r
        assert abs(r["ratio"] - 1) <= TOLERANCE, (
            f"n={n}: estimate {r['estimate'] / 2**20:.1f} MiB vs measured {r['measured'] / 2**20:.1f} MiB")
    # more Gaussians, more memory, in the estimate as in the measurement
    assert rows[12000]["estimate"] > rows[1500]["estimate"]
    assert rows[12000]["measured"] > rows[1500]["measured"]


def test_check_memory_refuses_with_one_line() -> None:
    from pd_tool.core.errors import PdToolError
    from pd_tool.prepare.memory import InsufficientMemory, check_memory, estimate_bake_memory

    est = estimate_bake_memory(n_gaussians=100_000, n_simulated=90_000, driver_ratio=0.25, grid_dims=(64, 64, 64),
                               frames=61, preview_pixels=480 * 270)
    check_memory(est, what="bake", quality="final", driver_ratio=0.25, resolution="grid 64x64x64 cells",
                 available=(est.host * 1.01, None))  # fits: no error
    with pytest.raises(InsufficientMemory) as e:
        check_memory(est, what="bake", quality="final", driver_ratio=0.25, resolution="grid 64x64x64 cells",
                     available=(est.host * 0.5, None))
    msg = str(e.value)
    assert isinstance(e.value, PdToolError) and "\n" not in msg
    for word in ("--quality", "final", "driver ratio", "0.25", "grid 64x64x64", "RAM"):
        assert word in msg, (word, msg)
    with pytest.raises(InsufficientMemory, match="GPU memory"):
        check_memory(estimate_bake_memory(n_gaussians=100_000, n_simulated=90_000, driver_ratio=0.25,
                                          grid_dims=(64, 64, 64), frames=61, device="cuda"),
                     what="bake", quality="final", driver_ratio=0.25, resolution="grid",
                     available=(float("inf"), 1e6))


def test_estimates_grow_with_every_input() -> None:
    from pd_tool.prepare.memory import estimate_bake_memory, estimate_fit_memory

    base = dict(n_gaussians=10_000, n_simulated=9_000, driver_ratio=0.1, grid_dims=(24, 24, 24))
    b = estimate_bake_memory(frames=31, **base).host
    assert estimate_bake_memory(frames=31, **{**base, "n_gaussians": 20_000}).host > b
    assert estimate_bake_memory(frames=31, **{**base, "grid_dims": (64, 64, 64)}).host > b
    assert estimate_bake_memory(frames=301, preview_pixels=480 * 270, **base).host > b
    f = estimate_fit_memory(frames=[14], image_pixels=256 * 256, **base).host
    assert estimate_fit_memory(frames=[28], image_pixels=256 * 256, **base).host > f
    assert estimate_fit_memory(frames=[14], image_pixels=512 * 512, **base).host > f
    assert estimate_fit_memory(frames=[14], image_pixels=256 * 256, **{**base, "driver_ratio": 0.5}).host > f
    g = estimate_fit_memory(frames=[14], image_pixels=256 * 256, device="cuda", **base)
    assert g.device > 0 and g.host < f  # on a GPU the graph moves to the device


def test_cli_bake_refuses_a_run_that_cannot_fit(tmp_path: Path) -> None:
    """Real inputs, no mocks: a preview of 600,001 frames (600 s at 1000 fps) keeps ~230 GB of images."""
    from cli import main
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    save_splats(make_plant(600, seed=0), tmp_path / "plant.ply")
    out = tmp_path / "out.usd"
    res = CliRunner().invoke(main, ["bake", str(out), "--scene", str(tmp_path / "plant.ply"), "--preset", "flower",
                                    "--force", "0,0,1", "--seconds", "600", "--fps", "1000", "--quality", "draft",
                                    "--device", "cpu", "--preview", str(tmp_path / "p.mp4")])
    assert res.exit_code == 2, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1 and "--quality (now draft)" in lines[0] and "driver ratio" in lines[0], res.output
    assert not out.exists() and not (tmp_path / "p.mp4").exists()


def test_fit_refuses_a_grid_that_cannot_fit(tmp_path: Path, monkeypatch) -> None:
    """A quality preset with a 256-cell grid (the presets' largest): on this plant the checkpointed tape
    alone needs ~6 GiB, more than the 4 GiB this test says the machine has."""
    import torch

    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.prepare.memory import InsufficientMemory
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import make_plant
    from pd_tool.render.views import scene_camera
    from pd_tool.video.folder import write_video_folder

    import pd_tool.prepare.memory

    monkeypatch.setattr(pd_tool.prepare.memory, "available_memory", lambda device="cpu": (4.0 * 2**30, None))
    (tmp_path / "huge.toml").write_text("grid_res = 256\ncfl_safety = 0.5\ndriver_ratio = 0.1\n"
                                        "fit_velocity_iters = 1\nfit_material_iters = 1\n")
    scene = make_plant(600, seed=0)
    cam = scene_camera(scene, width=16, height=16)
    write_video_folder(tmp_path / "video", torch.full((3, 16, 16, 3), 0.5).numpy(), cam, 30.0)
    refs = [load_reference_video(tmp_path / "video", working_size=16)]
    with pytest.raises(InsufficientMemory, match=r"--quality \(now .*huge.toml\).*--working-size 16"):
        run_fit(scene, tmp_path / "video" / "camera.json", refs, tmp_path / "x.pdmat",
                prepare_options=PrepareOptions(static_below=0.2),
                settings=FitSettings(quality=str(tmp_path / "huge.toml"), working_long_side=16))
    assert not (tmp_path / "x.pdmat").exists()


def test_the_estimate_counts_the_chunk_the_search_holds() -> None:
    # the memory estimate's k-NN terms are the ones pd_tool.drivers.knn holds on each device
    import sys

    from pd_tool.drivers.knn import CUDA_CHUNK, DEFAULT_CHUNK, default_chunk
    from pd_tool.prepare import memory as M

    knn = sys.modules["pd_tool.drivers.knn"]
    assert default_chunk("cpu") == DEFAULT_CHUNK == M.KNN_CHUNK
    assert default_chunk("cuda:0") == CUDA_CHUNK == M.KNN_CHUNK_CUDA
    assert knn._GRID_MAX_CELLS == M.KNN_GRID_CELLS and knn._SAMPLE == M.KNN_SAMPLE
    kw = dict(n_gaussians=300_000, n_simulated=300_000, driver_ratio=0.5, grid_dims=(64, 64, 64), frames=31,
              preview_pixels=0, sh_coeffs=1)
    cpu, gpu = M.estimate_bake_memory(device="cpu", **kw), M.estimate_bake_memory(device="cuda", **kw)
    grid = 12 * 8 * 300_000 + 8 * M.KNN_GRID_CELLS
    assert grid + M.B_PAIR * M.KNN_CHUNK // 4 < cpu.terms["knn"] < 1.1 * (grid + M.B_PAIR * M.KNN_CHUNK // 4)
    assert grid + M.B_PAIR_CUDA * M.KNN_CHUNK_CUDA // 4 < gpu.terms["knn"]
    assert gpu.device >= gpu.terms["knn"]  # counted on the device


def test_stored_frames_take_half_of_what_the_fit_leaves_free() -> None:
    from pd_tool.prepare.memory import MiB, STORED_FRAMES_CPU_MB, MemoryEstimate, stored_frames_budget_mb

    est = MemoryEstimate(host=2000 * MiB, device=3000 * MiB)
    assert stored_frames_budget_mb(est, (2600 * MiB, None)) == pytest.approx(300.0)
    assert stored_frames_budget_mb(est, (64000 * MiB, None)) == STORED_FRAMES_CPU_MB
    assert stored_frames_budget_mb(est, (float("inf"), None)) == STORED_FRAMES_CPU_MB
    assert stored_frames_budget_mb(est, (1000 * MiB, None)) == 0.0  # over: recompute every frame
    assert stored_frames_budget_mb(est, (1000 * MiB, 11000 * MiB)) == pytest.approx(4000.0)  # the GPU's
    assert stored_frames_budget_mb(est, (1e12, 2000 * MiB)) == 0.0
