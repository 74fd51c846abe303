"""The stability guard's messages: one line each, naming what went wrong and the fix to try first."""
from __future__ import annotations

import numpy as np
import pytest

from pd_tool.core.errors import SimulationUnstable
from pd_tool.sim import kernels as K
from pd_tool.sim.guard import check_stats


@pytest.mark.parametrize("stat, first_fix", [(K.STAT_NONFINITE, "raise the substeps"),
                                             (K.STAT_COLLAPSED, "lower the force first"),
                                             (K.STAT_EDGE, "lower the force")])
def test_each_counter_gives_one_line_with_its_fix(stat: int, first_fix: str) -> None:
    stats = np.zeros(K.N_STATS, np.int64)
    stats[stat] = 3
    with pytest.raises(SimulationUnstable) as info:
        check_stats(stats, frame=4, time_s=0.15, substeps=120)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("simulation unstable at frame 4 (t=0.150 s, 120 substeps/frame): 3 ")
    assert first_fix in msg


def test_a_clean_frame_passes() -> None:
    check_stats(np.zeros(K.N_STATS, np.int64), frame=0, time_s=0.03, substeps=10)
