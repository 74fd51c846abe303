"""Filled against hollow: the same solid ball under the same poke.

A ball of radius R scanned as a shell of flat Gaussians, gravity off, held in one of two
ways (--scene):
  clamped: its bottom cap (below centre - 0.7 R) is static; the ball itself is the spring.
  stem:    it sits on an elastic stem (a solid rod of lattice particles, clamped at its
           foot, the same in both runs), like a fruit or a flower head; the stem is the
           spring and the ball mostly the mass.
Two simulations with the same Young's modulus, density and
poke (a constant sideways acceleration on every particle within POKE_RADIUS of the top for
POKE_S seconds, the paper's interaction):
  hollow: the shell Gaussians only;
  filled: the shell plus `fill_interior` particles (mode "auto", so it also shows the
          decision).
Particle volumes follow the preparation step (cell volume / particles in that cell, over all
particles), masses = density * volume. Reported: total mass, peak sideways displacement of
the top shell particles, and the frequency of their free oscillation after the poke
(whole periods between zero crossings about the rest position).

    python bench/fill_motion.py --device cpu --json fill_motion.json          # ~1-2 min CPU
    python bench/fill_motion.py --device cuda --grid 64 --json fill_motion.json
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pd_tool.fill import fill_interior  # noqa: E402
from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402

DOMAIN = 1.0  # m, cube side
RADIUS = 0.25  # m, ball radius
E_PA = 2.0e4  # Young's modulus, Pa (soft, so that the motion is slow and large)
NU = 0.3
RHO = 1000.0  # kg/m^3
CLAMP_BELOW = -0.7  # static: particles below centre + CLAMP_BELOW * R
POKE_ACCEL = 20.0  # m/s^2 along +x
POKE_RADIUS = 0.12  # m, around the top of the ball
POKE_S = 0.1  # s
FPS = 60.0  # output frames per second (samples of the motion)
STEM_RADIUS = 0.05  # m (stem scene)
STEM_FOOT = 0.13  # m, bottom of the stem
STEM_CLAMP = 0.05  # m of the stem's foot that are static


def quat_z_to(n: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz rotations taking +z to the unit normals n."""
    v = np.cross(np.array([0.0, 0.0, 1.0]), n)
    q = np.concatenate([1.0 + n[:, 2:3], v], 1)
    q[(1.0 + n[:, 2]) < 1e-9] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def shell_scan(centre: np.ndarray, dx: float):
    """Flat Gaussians on the sphere, about 3 per surface cell (like a scan's shell)."""
    n = int(3 * 4 * math.pi * RADIUS**2 / dx**2)
    i = np.arange(n) + 0.5
    phi, th = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    d = np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)
    spacing = RADIUS * math.sqrt(4 * math.pi / n)
    scales = np.stack([np.full(n, 0.7 * spacing)] * 2 + [np.full(n, 1e-4)], 1)
    return centre + RADIUS * d, quat_z_to(d), scales, np.full(n, 0.8)


def stem_lattice(centre: np.ndarray, dx: float) -> tuple[np.ndarray, float]:
    """A vertical rod below the ball (particles, 2^3 per cell) and the height of its clamp."""
    h = dx / 2
    r, z0, z1 = STEM_RADIUS, STEM_FOOT, centre[2] - RADIUS + 0.5 * STEM_RADIUS
    ax = np.arange(-r + h / 2, r, h)
    zs = np.arange(z0 + h / 2, z1, h)
    g = np.stack(np.meshgrid(ax, ax, zs, indexing="ij"), -1).reshape(-1, 3)
    g = g[np.hypot(g[:, 0], g[:, 1]) <= r]
    return g + np.array([centre[0], centre[1], 0.0]), z0 + STEM_CLAMP


def particle_volumes(x: np.ndarray, dx: float) -> np.ndarray:
    """The preparation step's rule: a cell's volume divided by the particles in it."""
    keys = np.floor(x / dx).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return dx**3 / counts[inv.reshape(-1)]


def frequency(t: np.ndarray, d: np.ndarray) -> float:
    """Whole periods between the first and the last zero crossing of the same direction."""
    s = np.sign(d)
    idx = np.nonzero((s[:-1] != 0) & (s[1:] != s[:-1]))[0]
    if len(idx) == 0:
        return float("nan")
    times = t[idx] - d[idx] * (t[idx + 1] - t[idx]) / (d[idx + 1] - d[idx])
    dirs = np.where(d[idx] < 0, 1, -1)
    same = times[dirs == dirs[0]]
    return float("nan") if len(same) < 2 else (len(same) - 1) / (same[-1] - same[0])


def simulate(x, n_shell, n_extra, centre, clamp_z, grid, seconds, device, ball_e_factor=1.0) -> dict:
    dx = DOMAIN / grid
    vol = particle_volumes(x, dx)
    mass = RHO * vol
    static = x[:, 2] < clamp_z
    top = centre + np.array([0.0, 0.0, RADIUS])
    poke = np.linalg.norm(x - top, axis=1) < POKE_RADIUS
    watch = poke.copy()
    watch[n_shell:] = False  # what a viewer sees: the shell near the top
    cfg = SimConfig(grid_res=grid, domain=(DOMAIN,) * 3, nu=NU, gravity=(0.0, 0.0, 0.0))
    E = np.full(len(x), E_PA * ball_e_factor)  # the ball: shell and filled particles
    E[n_shell:n_shell + n_extra] = E_PA  # the stem (if any) keeps E_PA
    sim = MPMSolver(x, vol, mass, E, static, cfg, device=device)
    sim.add_force(poke, (POKE_ACCEL, 0.0, 0.0), 0.0, POKE_S)
    sim.step_frame(1.0 / FPS)  # compiles the kernels; part of the run, so keep it
    t_sim = time.perf_counter()
    ts, ds, substeps = [1.0 / FPS], [float(sim.displacements()[watch, 0].mean())], []
    for f in range(1, int(round(seconds * FPS))):
        substeps.append(sim.step_frame(1.0 / FPS))
        ts.append((f + 1) / FPS)
        ds.append(float(sim.displacements()[watch, 0].mean()))
    t_sim = time.perf_counter() - t_sim
    t, d = np.array(ts), np.array(ds)
    after = t >= POKE_S + 1.0 / FPS
    return {
        "particles": int(len(x)), "moving_mass_kg": float(mass[~static].sum()),
        "mass_kg": float(mass.sum()), "peak_displacement_m": float(np.abs(d).max()),
        "time_to_peak_s": float(t[np.argmax(np.abs(d))]),
        "frequency_hz": frequency(t[after], d[after]), "substeps_per_frame": int(max(substeps)),
        "sim_seconds": t_sim, "trace_t": t.tolist(), "trace_dx": d.tolist(),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--grid", type=int, default=32, help="cells per axis of the 1 m box")
    ap.add_argument("--seconds", type=float, default=3.0, help="simulated time, s")
    ap.add_argument("--scene", choices=["clamped", "stem", "both"], default="both")
    ap.add_argument("--ball-e-factor", type=float, default=1.0,
                    help="the ball's Young's modulus over the stem's (stem scene)")
    ap.add_argument("--json", type=Path, help="write the results here")
    a = ap.parse_args(argv)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    dx = DOMAIN / a.grid
    out = {"command": "python bench/fill_motion.py " + " ".join(argv or sys.argv[1:]),
           "device": a.device, "grid": a.grid,
           "platform": platform.processor() or platform.machine(), "E_pa": E_PA, "rho": RHO,
           "ball_volume_m3": 4 / 3 * math.pi * RADIUS**3, "scenes": {},
           "ball_e_factor": a.ball_e_factor}
    for scene in (["clamped", "stem"] if a.scene == "both" else [a.scene]):
        if scene == "clamped":
            centre = np.full(3, DOMAIN / 2)
            extra, clamp_z = np.zeros((0, 3)), centre[2] + CLAMP_BELOW * RADIUS
        else:
            centre = np.array([DOMAIN / 2, DOMAIN / 2, 0.6])
            extra, clamp_z = stem_lattice(centre, dx)
        p, q, s, o = shell_scan(centre, dx)
        t0 = time.perf_counter()
        fill = fill_interior(p, q, s, o, cell=dx, mode="auto")
        t_fill = time.perf_counter() - t0
        print(f"[{scene}] fill ({t_fill:.2f} s): {fill.reason}")
        runs = {}
        for name, x in (("hollow", np.concatenate([p, extra])),
                        ("filled", np.concatenate([p, extra, fill.points]))):
            r = simulate(x.astype(np.float32), len(p), len(extra), centre, clamp_z, a.grid,
                         a.seconds, a.device, a.ball_e_factor if scene == "stem" else 1.0)
            runs[name] = r
            print(f"[{scene}] {name:7s} particles {r['particles']:7,d}  mass {r['mass_kg']:7.2f} kg"
                  f"  peak {1000 * r['peak_displacement_m']:6.1f} mm at {r['time_to_peak_s']:.3f} s"
                  f"  f {r['frequency_hz']:5.2f} Hz  ({r['substeps_per_frame']} substeps/frame, "
                  f"{r['sim_seconds']:.1f} s)")
        out["scenes"][scene] = {
            "fill": {"decision": fill.decision, "closedness": fill.closedness,
                     "interior_volume_m3": fill.interior_volume, "points": int(len(fill.points)),
                     "reason": fill.reason, "seconds": t_fill},
            "runs": runs}
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
