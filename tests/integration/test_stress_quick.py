"""The stability stress matrix's CI subset (bench/stress.py --quick, ~20 cases, ~20 s on
2 cores): every case bakes a small scene through the whole bake and must end stable
(finite, inside the box, energy bounded by the force's work) or with a clear PdToolError
(the stability guard's SimulationUnstable, or a rejected input). The full matrix (210
cases, per-case timeout) is `python bench/stress.py`; its outcomes are in the docs.
"""
from __future__ import annotations


import pytest

from _bench import load_bench


def _stress():
    return load_bench("stress")


_CASES = _stress().quick_matrix()


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    import torch

    from pd_tool.core.device import init_warp_quietly

    n = torch.get_num_threads()
    torch.set_num_threads(1)  # 2 shared cores: oversubscription only slows these small bakes
    init_warp_quietly()
    yield
    torch.set_num_threads(n)


@pytest.mark.parametrize("case", _CASES, ids=[c["name"] for c in _CASES])
def test_quick_case_is_stable_or_stopped_clearly(case, device):
    r = _stress().run_case(case, device=device, frames=6)
    assert r["outcome"] in _stress().OK, f"{r['name']}: {r['outcome']}: {r.get('message')}"
    if r["outcome"] == "stable":
        # the check itself measured something: positions moved, and within the bound
        assert r["peak_displacement"] > 0.0
        assert r["max_speed"] <= r["speed_bound"]
    else:
        msg = r["message"]
        assert "\n" not in msg and len(msg) > 20, msg  # one line that says what to change
        if r["outcome"] == "guard":  # the per-frame guard, or the force preflight before simulating
            assert "simulation unstable at frame" in msg or msg.startswith("the force cannot end stable"), msg


def test_quick_matrix_covers_every_axis_and_outcome():
    s = _stress()
    for axis, values in (("geometry", s.GEOMETRIES), ("cov", s.COVARIANCES[1:]), ("opacity", s.OPACITIES[1:])):
        seen = {c[axis] for c in _CASES}
        assert set(values) - {"normal"} <= seen | {"normal"}, (axis, set(values) - seen)
    assert min(c["E"] for c in _CASES) <= 1e2 and max(c["E"] for c in _CASES) >= 1e9
    assert min(c["nu"] for c in _CASES) == 0.0 and max(c["nu"] for c in _CASES) >= 0.49
    assert min(c["force"] for c in _CASES) <= 0.1 and max(c["force"] for c in _CASES) >= 1e4
    assert min(c["factor"] for c in _CASES) <= 0.02 and max(c["factor"] for c in _CASES) >= 4.0
    assert len(s.full_matrix()) >= 200


def test_guard_and_rejection_paths_are_exercised():
    """Cases known to need the guard / a rejection really end that way (not 'stable' by luck)."""
    s = _stress()
    too_large = s.run_case(s._case(E=1e7, factor=0.02), frames=4)  # 1 substep per frame at 1e7 Pa
    assert too_large["outcome"] == "guard", too_large
    invisible = s.run_case(s._case(opacity="all-zero"), frames=4)
    assert invisible["outcome"] == "rejected" and "min-opacity" in invisible["message"], invisible


def test_check_force_stops_only_hopeless_forces():
    """The preflight fires only when a force both flings a free particle out of the box and
    needs > HOPELESS_STRAIN x the stress E can give; its message names the limit."""
    from pd_tool.core.errors import SimulationUnstable
    from pd_tool.sim.guard import HOPELESS_STRAIN, check_force

    # the stress matrix's absurd poke: 1.8e6 m/s^2 for 0.1 s on a 0.3 m region of 1e5 Pa
    with pytest.raises(SimulationUnstable, match="lower --force below about"):
        check_force(1.8e6, 0.1, 0.3, 1000.0, 1e5, 2.4, 1.6)
    check_force(1.8e6, 0.1, 0.3, 1000.0, 1e9, 2.4, 1.6)  # stiff enough to hold it: simulate
    check_force(30.0, 0.1, 0.3, 1000.0, 1e2, 2.4, 1.6)  # soft, but stays in the box: simulate
    check_force(0.0, 0.1, 0.3, 1000.0, 1e2, 2.4, 1.6)
    # right at the boundary of the stress test: strain just over / under the threshold
    a = HOPELESS_STRAIN * 1e5 / (1000.0 * 0.3)
    check_force(a * 0.99, 10.0, 0.3, 1000.0, 1e5, 2.4, 1.0)
    with pytest.raises(SimulationUnstable):
        check_force(a * 1.01, 10.0, 0.3, 1000.0, 1e5, 2.4, 1.0)
