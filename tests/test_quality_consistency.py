"""A material preset moves the same at draft and at default on a real capture: the quality
level changes fidelity, not the material (bench/convergence.py measures it on the GPU
against a converged reference; this is its CI-scale check)."""
from __future__ import annotations

from dataclasses import replace

import pytest

from pd_tool.presets import load_preset
from tests._bench import load_bench

conv = load_bench("convergence")


def test_udon_moves_the_same_at_draft_and_default(shared_data) -> None:
    case = conv.Case("udon", "-y", 2.0e5, 1000.0, 1.5, (1.0, 0.0, 0.0), seconds=0.5)
    scene = conv.load_scene("udon", 10_000, data=shared_data)
    runs = {}
    for name in ("default", "draft"):
        q = load_preset("quality", name)
        runs["reference" if name == "default" else name] = conv.simulate(
            scene, case, int(q["grid_res"]), float(q["cfl_safety"]), float(q["driver_ratio"]), "cpu")
    ref, draft = conv.compare(runs, case)
    assert ref.peak > 0.02, ref  # the poke moves it: a few per cent of its size
    # default is within 10% of the converged reference on the GPU; draft within 25% of that
    assert draft.peak_ratio == pytest.approx(1.0, abs=0.25), draft
    assert draft.rms < 0.25, draft


def test_thin_leaves_move_the_same_at_draft_and_default_because_the_grid_is_raised() -> None:
    """The plant with 3 mm leaves: draft and default each raise their grid for the leaves
    (to 64 and 128 cells) and then agree; on their own grids (32 and 64) both move less.
    On the GPU at 100k Gaussians against a 192-cell reference: draft 0.77 and default 1.05
    raised, 0.51 and 0.80 not. At this scale (10k Gaussians, 0.6 s) draft raised reads
    0.95 of default raised, the own grids 0.78-0.79."""
    case = replace(conv.CASES["plant"], seconds=0.6)
    scene = conv.load_scene("plant", 10_000)
    runs = {}
    for name, refine in (("default", True), ("draft", True), ("draft own", False), ("default own", False)):
        q = load_preset("quality", name.split()[0])
        runs["reference" if name == "default" else name] = conv.simulate(
            scene, case, int(q["grid_res"]), float(q["cfl_safety"]), float(q["driver_ratio"]), "cpu",
            thin_grid=int(q["thin_grid_res"]) if refine else None)
    ref, draft, *own = conv.compare(runs, case)
    assert (ref.grid, draft.grid, *(r.grid for r in own)) == (128, 64, 32, 64)
    assert ref.peak > 0.05, ref
    assert draft.peak_ratio == pytest.approx(1.0, abs=0.10), draft
    assert draft.rms < 0.10, draft
    for r in own:  # the test can fail: without the raise, neither quality moves as far
        assert r.peak_ratio < 0.85, r
