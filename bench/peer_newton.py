"""pdtool's MPM beside Newton's (`newton` on PyPI, SolverImplicitMPM) on the same
particles, grid spacing and material, in one run on one device.

The scene is the solver benchmarks' block (pd_tool.io.synthetic.make_block: N particles,
about 8 per occupied cell of a res^3 grid over the unit box, its bottom layer clamped),
E = 1e5 Pa, nu = 0.3, 1000 kg/m^3, no gravity. Both start from the same sway: a sideways
velocity growing linearly with height to `--speed` m/s at the top. Both simulate
`--seconds` at 30 fps.

- pdtool: MPMSolver as a bake runs it (explicit MLS-MPM, CFL substeps at safety 0.5,
  fused kernels, CUDA graphs).
- Newton: SolverImplicitMPM with voxel_size = pdtool's cell, its own defaults otherwise
  (sparse grid, APIC transfer, iterative rheology solve), the clamp as kinematic particles
  (mass 0), `--newton-substeps` implicit steps a frame (no CFL limit), elastic: tensile
  yield ratio 1 and its default yield pressure of 1e15 Pa, so that nothing yields.

The two solve different models. pdtool integrates explicitly, with many small steps whose
cost is each a particle-to-grid-to-particle pass. Newton solves each step implicitly
(several solver iterations on the grid). So the comparison is the time per simulated
second and per step, at each solver's own stable step. The motion is compared where both
model the same elastic body: the 99th percentile displacement of the moving particles at
each frame, and the RMS of the per-particle difference between the two, both as a share of
pdtool's peak. An implicit step damps the sway more as it grows: `--newton-substeps`
shows that trade.

    python bench/peer_newton.py --device cuda --sizes 100000:64 --json peer.json
    python bench/peer_newton.py --quick          # CPU: 4,000 particles on 24 cells
Newton is not a pdtool dependency: `pip install newton` (1.8.0 measured) first.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

E, NU, DENSITY = 1.0e5, 0.3, 1000.0
FPS = 30.0


def sway(x: np.ndarray, static: np.ndarray, speed: float) -> np.ndarray:
    """Initial velocity [N, 3] m/s: along +x, from 0 at the block's base to `speed` at its top."""
    z = x[:, 2].astype(np.float64)
    v = np.zeros((len(x), 3), np.float32)
    v[:, 0] = speed * (z - z.min()) / max(float(np.ptp(z)), 1e-12)
    v[static] = 0.0
    return v


def run_pdtool(x, vol, mass, static, res: int, v0, frames: int, device: str) -> dict:
    """pdtool's forward: seconds per frame after a warm-up, substeps a frame, positions [F+1, N, 3]."""
    import warp as wp

    from pd_tool.sim import MPMSolver, SimConfig

    def make():
        sim = MPMSolver(x, vol, mass, np.full(len(x), E), static,
                        SimConfig(grid_res=res, nu=NU, gravity=(0.0, 0.0, 0.0), cfl_safety=0.5), device=device)
        sim.set_velocity(v0)
        return sim

    warm = make()  # kernels compiled and graphs captured outside the timing
    warm.step_frame(1.0 / FPS)
    sim = make()
    traj = [sim.positions().copy()]
    wp.synchronize_device(device)
    t = time.perf_counter()
    substeps = 0
    for _ in range(frames):
        substeps += sim.step_frame(1.0 / FPS)
        traj.append(sim.positions().copy())  # a host copy each frame, as a bake makes
    seconds = time.perf_counter() - t
    return {"seconds": seconds, "steps": substeps, "traj": np.stack(traj)}


def run_newton(x, vol, mass, static, dx: float, v0, frames: int, substeps: int, device: str) -> dict:
    """Newton's SolverImplicitMPM on the same particles: as run_pdtool."""
    import newton
    import warp as wp
    from newton.solvers import SolverImplicitMPM

    def make():
        b = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        SolverImplicitMPM.register_custom_attributes(b)
        m = np.where(static, 0.0, mass)  # mass 0: a kinematic particle, Newton's clamp
        b.add_particles(pos=[tuple(p) for p in x.astype(float)], vel=[tuple(v) for v in v0.astype(float)],
                        mass=m.tolist(), radius=(0.5 * np.cbrt(vol)).tolist())
        model = b.finalize(device=device)
        model.mpm.young_modulus.fill_(E)
        model.mpm.poisson_ratio.fill_(NU)
        model.mpm.tensile_yield_ratio.fill_(1.0)  # tension as compression: elastic, no fracture
        cfg = SolverImplicitMPM.Config()
        cfg.voxel_size = float(dx)
        solver = SolverImplicitMPM(model, config=cfg)
        return model, solver, model.state(), model.state()

    dt = 1.0 / FPS / substeps
    _, solver, s0, s1 = make()
    solver.step(s0, s1, None, None, dt)  # compile
    model, solver, s0, s1 = make()
    # a copy: on the CPU, numpy() is a view of the state, which later steps overwrite
    traj = [s0.particle_q.numpy().copy()]
    wp.synchronize_device(device)
    t = time.perf_counter()
    for _ in range(frames):
        for _ in range(substeps):
            solver.step(s0, s1, None, None, dt)
            s0, s1 = s1, s0
        traj.append(s0.particle_q.numpy().copy())
    seconds = time.perf_counter() - t
    return {"seconds": seconds, "steps": frames * substeps, "traj": np.stack(traj),
            "version": getattr(newton, "__version__", "?")}


def motion(traj: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """99th percentile displacement [F+1] of the moving particles at each frame, m."""
    d = np.linalg.norm(traj[:, moving] - traj[0, moving], axis=-1)
    return np.quantile(d, 0.99, axis=1)


def against(ours: np.ndarray, theirs: np.ndarray, moving: np.ndarray, peak: float) -> dict:
    """A peer's trajectory [F+1, N, 3] against pdtool's, whose motion peaks at `peak` m: its
    peak over pdtool's, the RMS of the per-particle difference over pdtool's peak, and its
    motion [F+1] (m)."""
    m = motion(theirs, moving)
    diff = np.linalg.norm(theirs[:, moving] - ours[:, moving], axis=-1)
    return {"peak_ratio": float(m.max()) / max(peak, 1e-30),
            "rms_diff_over_peak": float(np.sqrt((diff ** 2).mean())) / max(peak, 1e-30),
            "motion_m": m.tolist()}


def compare(n: int, res: int, seconds: float, speed: float, newton_substeps: list[int], device: str) -> dict:
    from pd_tool.io.synthetic import make_block

    x, vol, mass, _, static = make_block(n, res, E=E, density=DENSITY)
    v0 = sway(x, static, speed)
    frames = int(round(seconds * FPS))
    moving = ~static
    ours = run_pdtool(x, vol, mass, static, res, v0, frames, device)
    m_ours = motion(ours["traj"], moving)
    peak = float(m_ours.max())
    row = {"n": n, "res": res, "dx_m": 1.0 / res, "frames": frames, "speed_m_s": speed,
           "pdtool": {"s_per_sim_s": ours["seconds"] / seconds, "steps_per_frame": ours["steps"] / frames,
                      "ms_per_step": 1e3 * ours["seconds"] / ours["steps"],
                      "particle_steps_per_s": n * ours["steps"] / ours["seconds"], "peak_m": peak},
           "newton": []}
    for k in newton_substeps:
        theirs = run_newton(x, vol, mass, static, 1.0 / res, v0, frames, k, device)
        row["newton"].append({
            "version": theirs["version"], "steps_per_frame": k, "s_per_sim_s": theirs["seconds"] / seconds,
            "ms_per_step": 1e3 * theirs["seconds"] / theirs["steps"],
            "particle_steps_per_s": n * theirs["steps"] / theirs["seconds"],
            "time_ratio": theirs["seconds"] / ours["seconds"],  # Newton's time over pdtool's, same simulated time
            **against(ours["traj"], theirs["traj"], moving, peak)})
    row["pdtool"]["motion_m"] = m_ours.tolist()
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="100000:64", help="N:res pairs, comma separated")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated time")
    ap.add_argument("--speed", type=float, default=0.3, help="the sway's speed at the top, m/s")
    ap.add_argument("--newton-substeps", default="1,4", help="Newton's implicit steps a frame, comma separated")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 4,000 particles on 24 cells, 0.2 s, 1 step a frame")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    try:
        import newton  # noqa: F401
    except ImportError:
        print("bench/peer_newton.py needs Newton: pip install newton", file=sys.stderr)
        sys.exit(2)
    import warp as wp

    wp.config.quiet = True
    if args.quick:
        args.sizes, args.seconds, args.newton_substeps = "4000:24", 0.2, "1"
    rows = []
    for spec in args.sizes.split(","):
        n, res = (int(v) for v in spec.split(":"))
        row = compare(n, res, args.seconds, args.speed, [int(k) for k in args.newton_substeps.split(",")], args.device)
        rows.append(row)
        p = row["pdtool"]
        print(f"N={n:,} res={res}: pdtool {p['s_per_sim_s']:.3f} s per simulated s ({p['steps_per_frame']:.0f} steps a "
              f"frame, {p['ms_per_step']:.3f} ms a step, {p['particle_steps_per_s']:.3g} particle-steps/s), "
              f"peak {p['peak_m'] * 100:.2f} cm", flush=True)
        for r in row["newton"]:
            print(f"  Newton {r['version']}, {r['steps_per_frame']} steps a frame: {r['s_per_sim_s']:.3f} s per simulated "
                  f"s ({r['time_ratio']:.2f}x pdtool's), {r['ms_per_step']:.2f} ms a step; peak {r['peak_ratio']:.2f} of "
                  f"pdtool's, RMS difference {r['rms_diff_over_peak']:.2f} of its peak", flush=True)
    out = {"device": args.device, "gpu": wp.get_device(args.device).name, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
