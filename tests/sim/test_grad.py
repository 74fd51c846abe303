"""Differentiable MPM: gradients vs the float64 twin and finite differences, in-place
hazard, gradient horizon, and memory of the checkpointed backward."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
import warp as wp

from pd_tool.sim import DiffSim, Force, SimConfig, simulate_frames
from pd_tool.sim import _ref
from pd_tool.sim.solver import GridArrays, ParticleState, launch_substep

GRAD_REL = 2e-3  # float32 warp adjoint vs float64 twin over several substeps, relative to max


def rel_err(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-30))


def scene(dx=1 / 8, seed=0):
    h = dx / 2
    axes = [np.arange(3 * dx + 0.5 * h, 5 * dx, h)] * 3
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    n = len(x)
    rng = np.random.default_rng(seed)
    static = x[:, 2] < 3.5 * dx  # bottom layer clamped
    vol = np.full(n, h**3)
    return x, static, vol, rng


def random_state(x, static, rng, near_rest: bool):
    n = len(x)
    xt = torch.tensor(x, dtype=torch.float32)
    v = torch.tensor(rng.normal(0, 0.3, (n, 3)), dtype=torch.float32)
    v[torch.tensor(static)] = 0
    if near_rest:
        C = torch.zeros(n, 3, 3)
        F = torch.eye(3).expand(n, 3, 3).clone()
    else:
        C = torch.tensor(rng.normal(0, 0.5, (n, 3, 3)), dtype=torch.float32)
        F = torch.eye(3) + torch.tensor(rng.normal(0, 0.05, (n, 3, 3)), dtype=torch.float32)
    E = torch.tensor(rng.uniform(1e4, 3e4, n), dtype=torch.float32)
    return xt, v, C, F, E


@pytest.mark.parametrize("backward", ["adjoint", "adjoint-binned", "adjoint-kept", "tape"])
@pytest.mark.parametrize("near_rest", [True, False])
def test_frame_gradients_match_float64_twin(device, near_rest, backward):
    """All five gradients of one frame (7 substeps, segments of 3: two checkpoints plus a
    remainder) against torch autograd through the float64 twin, same random cotangents, for
    the hand-written adjoint (atomics, or cell lists as on CUDA; or over the substeps the
    forward stored, without a recompute) and the taped replay.
    This also catches in-place updates under the tape, which corrupt later substeps."""
    if device != "cpu":
        pytest.skip("the differentiable path takes torch tensors; the CPU torch build is installed")
    x, static, vol, rng = scene()
    n = len(x)
    kept = backward == "adjoint-kept"
    cfg = SimConfig(grid_res=8, gravity=(0, 0, -9.81), damping=1.0, segment=None if kept else 3,
                    keep_budget_mb=None if kept else 0, backward="tape" if backward == "tape" else "adjoint")
    sim = DiffSim(vol, vol * 1000, static, cfg, device="cpu")
    sim.binned = backward == "adjoint-binned"
    frame_dt, substeps = 7e-3, 7
    push = Force(mask=x[:, 0] > 4 * 0.125, accel=(5.0, 0.0, 3.0), t_start=2e-3, t_end=5e-3)
    ins = [t.requires_grad_() for t in random_state(x, static, rng, near_rest)]
    out = sim.frame(tuple(ins[:4]), ins[4], frame_dt, substeps, [push])
    cot = [torch.randn_like(t) for t in out]
    grads = torch.autograd.grad(sum((o * c).sum() for o, c in zip(out, cot)), ins)
    assert len(sim._kept) == int(kept)

    ins64 = [t.detach().double().requires_grad_() for t in ins]

    def accel(t):
        a = torch.zeros(n, 3, dtype=torch.float64)
        if 2e-3 <= t < 5e-3:
            a[torch.tensor(push.mask)] = torch.tensor(push.accel, dtype=torch.float64)
        return a

    m32 = lambda a: torch.tensor(a.astype(np.float32), dtype=torch.float64)  # noqa: E731
    out64 = _ref.substeps_ref(*ins64, m32(vol), m32(vol * 1000), torch.tensor(static), nu=0.3,
                              dx=sim.geo.dx, nodes=sim.geo.nodes, dt=frame_dt / substeps,
                              n_substeps=substeps, gravity=(0, 0, -9.81), damping=1.0, pad=3,
                              accel_fn=accel)
    for o, r in zip(out, out64):
        assert rel_err(o.detach(), r.detach()) < 1e-4
    grads64 = torch.autograd.grad(sum((o * c.double()).sum() for o, c in zip(out64, cot)), ins64)
    for name, g, r in zip(("x", "v", "C", "F", "E"), grads, grads64):
        assert torch.all(torch.isfinite(g)), name
        assert rel_err(g, r) < GRAD_REL, name


def test_inplace_update_under_tape_gives_wrong_gradient():
    """The hazard the separate per-substep arrays avoid: the same substeps taped with the
    state updated in place give a gradient that disagrees with the twin (so the test above
    would catch it), while separate arrays agree."""
    x, static, vol, rng = scene(seed=1)
    n = len(x)
    cfg = SimConfig(grid_res=8, gravity=(0, 0, 0))
    sim = DiffSim(vol, vol * 1000, static, cfg, device="cpu")
    xt, v, C, F, E = random_state(x, static, rng, near_rest=False)
    dt, steps = 4e-3, 6
    cot = np.random.default_rng(2).standard_normal((n, 3)).astype(np.float32)

    def grad_v0(inplace: bool) -> np.ndarray:
        base = wp.array(xt.numpy(), dtype=wp.vec3, requires_grad=True)
        Ew = wp.array(E.numpy(), dtype=float, requires_grad=True)
        order, fixed = sim._order_fixed(base)
        ctx = sim._context(base, Ew, order, fixed, sim.forces([]), 0.0)
        s0 = ParticleState(wp.zeros(n, dtype=wp.vec3, requires_grad=True),
                           wp.array(v.numpy(), dtype=wp.vec3, requires_grad=True),
                           wp.array(C.numpy(), dtype=wp.mat33, requires_grad=True),
                           wp.array(F.numpy() - np.eye(3, dtype=np.float32), dtype=wp.mat33, requires_grad=True))
        states = [s0] + [s0 if inplace else ParticleState.zeros(n, "cpu", requires_grad=True) for _ in range(steps)]
        tape = wp.Tape()
        with tape:
            for s in range(steps):
                launch_substep(ctx, dt, s * dt, states[s], states[s + 1],
                               GridArrays.alloc(sim.geo, "cpu", requires_grad=True))
        tape.backward(grads={states[-1].u: wp.array(cot, dtype=wp.vec3)})
        return s0.v.grad.numpy().copy()

    ins64 = [t.detach().double() for t in (xt, v, C, F, E)]
    ins64[1].requires_grad_()
    out64 = _ref.substeps_ref(*ins64, torch.tensor(vol), torch.tensor(vol * 1000), torch.tensor(static),
                              nu=0.3, dx=sim.geo.dx, nodes=sim.geo.nodes, dt=dt, n_substeps=steps,
                              gravity=(0, 0, 0), damping=0.0, pad=3)
    (ref,) = torch.autograd.grad(((out64[0] - ins64[0]) * torch.tensor(cot, dtype=torch.float64)).sum(), [ins64[1]])
    assert rel_err(grad_v0(inplace=False), ref) < GRAD_REL
    assert rel_err(grad_v0(inplace=True), ref) > 10 * GRAD_REL


def test_directional_finite_differences_near_rest():
    """Warp path alone, at rest (F = I, C = 0): autograd directional derivative of a loss on
    the displacement vs central differences, for E (log-space direction), v0 and x0."""
    x, static, vol, rng = scene(seed=3)
    cfg = SimConfig(grid_res=8, gravity=(0, 0, -9.81), segment=4)
    sim = DiffSim(vol, vol * 1000, static, cfg, device="cpu")
    xt, v, C, F, E = random_state(x, static, rng, near_rest=True)
    v = v * 3.0  # a clear deformation within the frame, so E matters
    w = torch.tensor(rng.standard_normal(x.shape), dtype=torch.float32)

    def loss(xi, vi, Ei):
        states = simulate_frames(sim, (xi, vi, C, F), Ei, 0.02, 10, n_frames=2)
        return ((states[-1][0] - xi) * w).sum()

    xi, vi, Ei = (t.clone().requires_grad_() for t in (xt, v, E))
    gx, gv, gE = torch.autograd.grad(loss(xi, vi, Ei), [xi, vi, Ei])
    dirs = {"E": torch.tensor(rng.standard_normal(len(x)), dtype=torch.float32) * E,  # dlogE * E
            "v": torch.tensor(rng.standard_normal(x.shape), dtype=torch.float32),
            "x": torch.tensor(rng.standard_normal(x.shape), dtype=torch.float32)}
    steps = {"E": 2e-2, "v": 2e-2, "x": 1e-4}
    for name, grad in (("E", gE), ("v", gv), ("x", gx)):
        d, h = dirs[name], steps[name]
        if name == "v" or name == "x":
            d = d.clone()
            d[torch.tensor(static)] = 0
        args_p = [xt, v, E]
        args_m = [xt, v, E]
        k = "xvE".index(name)
        args_p[k] = args_p[k] + h * d
        args_m[k] = args_m[k] - h * d
        with torch.no_grad():
            fd = (loss(*args_p) - loss(*args_m)).item() / (2 * h)
        ad = (grad * d).sum().item()
        assert abs(ad - fd) <= 0.03 * abs(fd) + 1e-7, (name, ad, fd)


def test_gradient_horizon_truncates():
    x, static, vol, rng = scene(seed=4)
    cfg = SimConfig(grid_res=8, gravity=(0, 0, 0))
    sim = DiffSim(vol, vol * 1000, static, cfg, device="cpu")
    xt, v, C, F, E = random_state(x, static, rng, near_rest=True)
    grads = {}
    for horizon in (None, 1):
        vi, Ei = v.clone().requires_grad_(), E.clone().requires_grad_()
        states = simulate_frames(sim, (xt, vi, C, F), Ei, 0.005, 4, n_frames=3, horizon=horizon)
        loss = (states[-1][0] ** 2).sum()
        grads[horizon] = torch.autograd.grad(loss, [vi, Ei], allow_unused=True)
    assert grads[None][0].abs().max() > 0
    assert grads[1][0] is None or grads[1][0].abs().max() == 0  # v0 is 3 frames back
    assert grads[1][1].abs().max() > 0  # E still trains from the last frame


MEMORY_SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np, torch
    from pd_tool.sim import DiffSim, SimConfig, initial_state, simulate_frames

    def status(key):
        for line in open("/proc/self/status"):
            if line.startswith(key):
                return int(line.split()[1]) * 1024
    n_frames = int(sys.argv[1])
    dx = 1 / 24
    h = dx / 2
    axes = [np.arange(10 * dx + 0.5 * h, 13 * dx, h)] * 3
    x = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    static = x[:, 2] < 10.5 * dx
    vol = np.full(len(x), h ** 3)
    sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=24, gravity=(0, 0, -9.81), segment=30,
                                                     keep_budget_mb=float(sys.argv[2])))
    E = torch.full((len(x),), 2e4, requires_grad=True)
    v0 = torch.zeros(len(x), 3, requires_grad=True)

    def run(frames, backward=True):
        states = simulate_frames(sim, initial_state(torch.tensor(x, dtype=torch.float32), v0), E,
                                 1 / 300, 30, n_frames=frames)
        if backward:
            sum(s[0].sum() for s in states).backward()

    run(1, backward=False)  # warm-up: kernels loaded, forward grid allocated
    base = status("VmRSS")
    open("/proc/self/clear_refs", "w").write("5")  # reset the peak (VmHWM) to now
    run(n_frames)
    print(json.dumps({"peak_bytes": status("VmHWM") - base, "frames": n_frames}))
""")


@pytest.mark.skipif(not Path("/proc/self/clear_refs").exists(), reason="needs Linux /proc peak RSS reset")
def test_backward_memory_does_not_grow_with_frames(tmp_path):
    """Peak resident memory above the warmed-up baseline of a 20-frame full-BPTT backward is
    within 1.5x of a 2-frame one (each in a fresh process) when the forward stores no
    substeps (keep_budget_mb 0). Without checkpointing the stored substeps (30 per frame, a
    25^3 grid each, ~0.9 MB) would grow it ~10x. With a budget of 60 MB for stored frames
    (two frames' substeps) the 20-frame peak grows by at most that budget."""
    script = tmp_path / "mem.py"
    script.write_text(MEMORY_SCRIPT)
    root = Path(__file__).resolve().parents[2]
    peaks = {}
    for frames, budget in ((2, 0), (20, 0), (20, 60)):
        # A fixed mmap threshold makes glibc return freed blocks to the OS, so the warm-up
        # frame's freed tape does not hide the measured run's allocations.
        env = dict(os.environ, MALLOC_MMAP_THRESHOLD_="65536")
        res = subprocess.run([sys.executable, str(script), str(frames), str(budget)], capture_output=True,
                             text=True, cwd=root, timeout=600, env=env)
        assert res.returncode == 0, res.stderr[-2000:]
        peaks[frames, budget] = json.loads(res.stdout.strip().splitlines()[-1])["peak_bytes"]
    assert peaks[2, 0] > 5e6  # the measurement sees the stored segment's arrays (~27 MB)
    print(peaks)
    assert peaks[20, 0] <= 1.5 * peaks[2, 0], peaks
    assert peaks[20, 60] <= 1.5 * peaks[2, 0] + 60 * 2**20, peaks


def test_frame_rejects_wrong_inputs():
    x, static, vol, rng = scene(seed=5)
    sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=8), device="cpu")
    xt, v, C, F, E = random_state(x, static, rng, near_rest=True)
    from pd_tool.sim import SimConfigError

    with pytest.raises(SimConfigError, match="E is"):
        sim.frame((xt, v, C, F), E.double(), 0.01, 4)
    with pytest.raises(SimConfigError, match="v is"):
        sim.frame((xt, v[:-1], C, F), E, 0.01, 4)


def test_cfl_substeps_for_uses_stiffest_moving_particle():
    from pd_tool.sim import cfl_substeps_for
    from pd_tool.sim.cfl import cfl_substeps, wave_speed

    x, static, vol, rng = scene(seed=6)
    sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=8, cfl_safety=0.3), device="cpu")
    E = torch.full((len(x),), 1e5)
    E[torch.tensor(static)] = 1e9  # static particles do not limit the substep
    E[np.nonzero(~static)[0][0]] = 4e5
    c = wave_speed(np.array([4e5]), np.array([1000.0]), 0.3)
    assert cfl_substeps_for(E, sim, 1 / 30) == cfl_substeps(1 / 30, sim.geo.dx, c, 0.0, 0.3)


def test_cfl_quantile_lets_a_few_stiff_particles_not_set_the_count():
    from pd_tool.sim import cfl_substeps_for
    from pd_tool.sim.cfl import cfl_substeps, wave_speed

    x, static, vol, rng = scene(seed=6)
    sim = DiffSim(vol, vol * 1000, static, SimConfig(grid_res=8, cfl_safety=0.3), device="cpu")
    moving = np.nonzero(~static)[0]
    assert len(moving) >= 20
    E = torch.full((len(x),), 1e5)
    E[moving[0]] = 4e7  # one outlier among the moving particles
    soft = cfl_substeps(1 / 30, sim.geo.dx, wave_speed(np.array([1e5]), np.array([1000.0]), 0.3), 0.0, 0.3)
    stiff = cfl_substeps(1 / 30, sim.geo.dx, wave_speed(np.array([4e7]), np.array([1000.0]), 0.3), 0.0, 0.3)
    assert stiff > soft
    assert cfl_substeps_for(E, sim, 1 / 30) == stiff  # the default: the fastest particle
    assert cfl_substeps_for(E, sim, 1 / 30, quantile=1.0) == stiff
    assert cfl_substeps_for(E, sim, 1 / 30, quantile=0.9) == soft  # the outlier is above the 90th percentile
    # a quantile is monotone: never more substeps than the maximum's
    assert soft <= cfl_substeps_for(E, sim, 1 / 30, quantile=0.999) <= stiff


def test_bridge_on_cuda_with_graphs_matches_plain_launches_and_cpu():
    """The torch bridge on CUDA: torch runs on its legacy default stream, on which CUDA
    cannot capture a graph, so the captured path runs on the simulator's own stream,
    ordered with torch's by events. Two chained frames and their gradients, replayed, must
    equal plain launches on torch's stream and agree with the CPU."""
    if not torch.cuda.is_available() or not wp.is_cuda_available():
        pytest.skip("needs CUDA torch and warp: the bridge's CUDA stream handling")
    x, static, vol, rng = scene()
    cfg = SimConfig(grid_res=8, gravity=(0, 0, -9.81), damping=1.0)
    base = random_state(x, static, rng, near_rest=False)
    frame_dt, substeps = 7e-3, 7
    results = {}
    for name, device, graphs in (("graph", "cuda:0", True), ("plain", "cuda:0", False), ("cpu", "cpu", False)):
        sim = DiffSim(vol, vol * 1000, static, cfg, device=device)
        sim.cuda_graph = graphs
        for _ in range(3):  # the first pass launches directly, the second captures, the third replays
            ins = [t.to(device).clone().requires_grad_() for t in base]
            state = tuple(ins[:4])
            for k in range(2):
                state = sim.frame(state, ins[4], frame_dt, substeps, frame_index=k + 1)
            loss = (state[0] ** 2).sum() + (state[1] ** 2).sum() + state[3].sum()
            grads = torch.autograd.grad(loss, ins)
        results[name] = [t.detach().cpu() for t in (*state, *grads)]
    for a, b in zip(results["graph"], results["plain"]):
        assert torch.all(torch.isfinite(a))
        assert rel_err(a, b) < 1e-5
    for a, b in zip(results["graph"], results["cpu"]):
        assert rel_err(a, b) < 1e-3


def test_fit_settings_refuse_a_cfl_quantile_outside_0_1() -> None:
    from pd_tool.fit.settings import FitSettings

    for q in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="cfl_quantile"):
            FitSettings(quality="draft", cfl_quantile=q).resolved()
    assert FitSettings(quality="draft", cfl_quantile=0.99).resolved().cfl_quantile == 0.99
