"""Differentiable MLS-MPM simulator in warp (fixed-corotated elasticity, SI units).

Fast forward path (bake)::

    from pd_tool.sim import MPMSolver, SimConfig
    cfg = SimConfig(grid_res=64, domain=(1.0, 1.0, 1.0))     # gravity on, nu = 0.3
    sim = MPMSolver(x0, volume, mass, E, static, cfg, device="cuda")
    sim.set_velocity(v0)                                      # [N, 3] m/s
    sim.add_force(mask, (0.0, 0.0, 5.0), t_start=0.0, t_end=0.5)   # m/s^2 on mask [N] bool
    for f in range(90):
        sim.step_frame(1 / 30)          # raises SimulationUnstable naming the frame
        x, F = sim.positions(), sim.deformation_gradients()   # [N, 3] m, [N, 3, 3]
        if sim.kinetic_energy() < 1e-6: break

Differentiable path (fit), torch autograd over warp; each frame's substeps stored for its
backward within SimConfig.keep_budget_mb, recomputed from checkpoints beyond it::

    from pd_tool.sim import DiffSim, initial_state, simulate_frames
    dsim = DiffSim(volume, mass, static, cfg, device="cpu")
    states = simulate_frames(dsim, initial_state(x0, v0), E, frame_dt=1/30, substeps=96,
                             n_frames=3, horizon=None)        # horizon=1: one-frame BPTT
    loss = sum(((s[0] - target[i]) ** 2).sum() for i, s in enumerate(states))
    loss.backward()                      # gradients in x0, v0 and whatever produced E

State tuples are (x [N,3] m, v [N,3] m/s, C [N,3,3] 1/s, F [N,3,3]) float32 torch tensors.
"""
from pd_tool.sim.autograd import DiffSim, cfl_substeps_for, initial_state, simulate_frame, simulate_frames
from pd_tool.sim.solver import Force, MPMSolver, SimConfig, SimConfigError

__all__ = ["DiffSim", "Force", "MPMSolver", "SimConfig", "SimConfigError", "cfl_substeps_for",
           "initial_state", "simulate_frame", "simulate_frames"]
