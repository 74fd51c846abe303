"""Resuming a fit from a checkpoint in the middle of a stage.

test_reliability_kill.py resumes a SIGKILLed `pdtool fit` from the checkpoint written when
stage 2 starts. Here, with a checkpoint after every iteration, the fit is interrupted in
the middle of stage 1 and in the middle of stage 2 (an exception from the progress
callback stands in for the kill: the checkpoint on disk is all that survives either way)
and resumed in a new FitProblem; the optimiser moments, schedules, residuals and RNG state
come from the checkpoint, so the material must equal an uninterrupted run's bit for bit.
A checkpoint of another fit is refused with one line.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch


class Interrupt(Exception):
    pass


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    from _plant import tiny_plant_inputs

    return tiny_plant_inputs(tmp_path_factory.mktemp("resume"))


def _fit(inputs, out: Path, stop_at: tuple[str, int] | None = None, resume: bool = False, seed: int = 0,
         rounds: int = 1, level: bool = False, keep: int = 10):
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP

    d, scene, refs = inputs

    def progress(stage: str, it: int, total: int, loss: float) -> None:
        if (stage, it) == stop_at:
            raise Interrupt

    settings = FitSettings(quality="draft", velocity_iters=2, material_iters=2, working_long_side=24,
                           checkpoint_every=1, seed=seed, rounds=rounds, stage1_level=level, keep_best_every=keep)
    return run_fit(scene, d / "plant.ply", refs, out, prepare_options=PrepareOptions(static_below=POT_TOP),
                   settings=settings, progress=progress, resume=resume)


@pytest.mark.parametrize("rounds,stop_at,level,keep", [
    (1, ("velocity", 2), False, 10), (1, ("material", 2), False, 10), (2, ("velocity 2/2", 2), False, 10),
    (2, ("material 2/2", 1), False, 10), (1, ("velocity", 2), True, 10), (2, ("material 2/2", 1), True, 10),
    # a whole-clip measure after every stage-2 iteration: the checkpoint carries a kept state mid-stage
    (1, ("material", 2), False, 1), (2, ("material 2/2", 2), True, 1)])
def test_resume_mid_stage_is_bit_identical(inputs, tmp_path: Path, rounds: int, stop_at, level: bool,
                                           keep: int) -> None:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the promise is for a fixed thread count
    try:
        full = _fit(inputs, tmp_path / "full.pdmat", rounds=rounds, level=level, keep=keep)
        out = tmp_path / "cut.pdmat"
        with pytest.raises(Interrupt):
            _fit(inputs, out, stop_at=stop_at, rounds=rounds, level=level, keep=keep)
        from pd_tool.fit.checkpoint import read_checkpoint

        _, ckpt = read_checkpoint(out.with_name(out.name + ".ckpt"), max_bytes=1 << 30)
        # the checkpoint of the iteration before the interruption, in the same stage and round
        stage, _, tag = stop_at[0].partition(" ")
        assert (ckpt["stage"], ckpt["iteration"], ckpt["round"]) == (stage, stop_at[1] - 1,
                                                                      int(tag.split("/")[0]) - 1 if tag else 0)
        assert not out.exists()
        if stop_at[0] == "velocity":  # a checkpoint of another fit (another seed) is refused, and kept
            from pd_tool.core.errors import PdToolError

            with pytest.raises(PdToolError, match=r"cut.pdmat.ckpt: the checkpoint belongs to another fit "
                                                  r"\(settings differs\); delete it, or fit without --resume$"):
                _fit(inputs, out, resume=True, seed=1, rounds=rounds, level=level, keep=keep)
        resumed = _fit(inputs, out, resume=True, rounds=rounds, level=level, keep=keep)
    finally:
        torch.set_num_threads(threads)
    assert not out.with_name(out.name + ".ckpt").exists()
    assert resumed.losses == full.losses
    if level:  # the level moved, and the resumed fit folded the same one
        assert all(abs(v) > 0 for v in full.losses["stage1_level"])
    assert resumed.driver_E.tobytes() == full.driver_E.tobytes(), np.abs(resumed.driver_E / full.driver_E - 1).max()
    assert resumed.driver_v0.tobytes() == full.driver_v0.tobytes()
    # every round's iterations ran once: none repeated or skipped by the resume
    assert len(resumed.losses["velocity"]) == 2 * rounds and len(resumed.losses["material"]) == 2 * rounds

