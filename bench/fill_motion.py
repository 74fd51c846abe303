"""Filled against hollow: a thick horizontal rod (a branch) clamped at one end, same poke.

A solid cylinder of radius R and free length L (a cantilever along +x whose first
CLAMP_CELLS cells, x < x0, sit in a clamp) is scanned as a closed shell of flat Gaussians:
the side and two end caps, about 3 Gaussians per surface cell. Two MPM simulations with
the same Young's modulus, Poisson's ratio, density, clamp and poke:
  hollow: the free part of the shell Gaussians only (what simulating a scan as it is gives);
  filled: the same plus the `fill_interior` particles (mode "auto" on the whole closed
          scan, so it also shows the decision).
The clamp (--clamp block, default) is a static solid block of lattice particles over the
root's cross-section, the same in both runs. (--clamp shell: the scan's own particles with
x < x0 are static instead, bake's rule; a hollow rod is then held by a one-node ring of
pinned grid nodes, which hinges, and it creeps back without ringing.)
Particle volumes follow the preparation step (cell volume / particles in that cell, over
all particles), masses = density * volume. Gravity is off, so the straight rest shape is
the equilibrium and the free vibration crosses it. The poke: a downward (-z) acceleration
POKE_ACCEL on every free particle for POKE_S seconds (a short gust; the paper's
interaction with the whole rod as the pushed region).

Measured: mass, linear density of the rod's middle, peak tip displacement and the frequency
of the free vibration after the poke (tip = shell particles in the last cell, what a viewer
sees; whole periods between zero crossings about the rest position, as bench/physics.py).

Beam theory (Euler-Bernoulli cantilever, Rayleigh's tip-mass correction):
f = 1/(2 pi) sqrt(3 E I / (L^3 (0.2427 lambda L + m_tip))), static tip deflection under an
acceleration a: d_s = a (lambda L^4 / (8 E I) + m_tip L^3 / (3 E I)), peak tip displacement
of the one-mode response to the poke: 2 d_s |sin(w POKE_S / 2)|; plus Timoshenko shear
(Dunkerley's sum with the fixed-free shear beam; -2% solid, -5% tube at L = 10 R; see
`cantilever`). Two references:
  theory (per run): A, I = sum(volume * z^2) and lambda = rho A from the run's own particles
          in the middle 60% of the rod (what the MPM integrates), m_tip = free mass - lambda L;
  nominal: a solid rod of the scan's radius R (I/A = R^2/4) against a tube of mid radius R
          (I/A ~ R^2/2) whose wall t = lambda_hollow / (rho 2 pi R) is the one the MPM gives
          the one-cell shell, plus its end cap as tip mass.
A thin tube rings sqrt(2) faster than a solid rod of the same radius; the solid one is
R/(2t) times heavier and deflects 2x further under the same acceleration (statically;
sqrt(2)x for a short poke).

    python bench/fill_motion.py --device cpu --json fill_motion.json         # ~2 min CPU
    python bench/fill_motion.py --device cuda --radius-cells 8 --seconds 2 --json fill_motion.json
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

from pd_tool.prepare.fill import fill_interior  # noqa: E402
from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402

DX = 0.01  # m, grid spacing (a 4-cell radius is a 4 cm thick branch)
E_PA = 1.0e6  # Young's modulus, Pa
NU = 0.3  # Poisson's ratio
RHO = 1000.0  # kg/m^3
PAD = 3  # SimConfig.boundary_pad, cells
MARGIN_CELLS = 2  # free cells between the object and the wall padding
ROOM_CELLS = 1  # extra transverse cells for the tip's swing
CLAMP_CELLS = 3  # length of the rod inside the clamp (static), cells
POKE_ACCEL = 3.0  # m/s^2 along -z on every free particle
POKE_S = 0.05  # s
FPS = 120.0  # samples of the motion per second
SCAN_PER_CELL = 3.0  # Gaussians per surface cell of the scan
BETA1 = 1.8751040687  # first root of 1 + cos(b) cosh(b) = 0
RAYLEIGH_MASS = 0.2427  # effective share of a cantilever's own mass at its tip (3 / BETA1^4)


def quat_z_to(n: np.ndarray) -> np.ndarray:
    """[N, 4] wxyz rotations taking +z to the unit normals n [N, 3]."""
    v = np.cross(np.array([0.0, 0.0, 1.0]), n)
    q = np.concatenate([1.0 + n[:, 2:3], v], 1)
    q[(1.0 + n[:, 2]) < 1e-9] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rod_scan(x_start: float, x_end: float, cy: float, cz: float, radius: float, dx: float,
             per_cell: float = SCAN_PER_CELL):
    """Flat Gaussians on a closed cylinder along x (side and both caps), `per_cell` per
    surface cell.

    Returns positions [N, 3] m, quats [N, 4] wxyz, scales [N, 3] m, opacities [N].
    """
    s = dx / math.sqrt(per_cell)  # spacing between Gaussians, m
    n_th = max(8, int(round(2 * math.pi * radius / s)))
    n_x = int(round((x_end - x_start) / s)) + 1
    xs = np.linspace(x_start, x_end, n_x)
    th = (np.arange(n_th)[None, :] + 0.5 * (np.arange(n_x)[:, None] % 2)) * 2 * math.pi / n_th
    xg = np.broadcast_to(xs[:, None], th.shape)
    side_n = np.stack([np.zeros(th.size), np.cos(th).ravel(), np.sin(th).ravel()], 1)
    side_p = np.stack([xg.ravel(), cy + radius * side_n[:, 1], cz + radius * side_n[:, 2]], 1)
    n_cap = max(8, int(round(per_cell * math.pi * radius**2 / dx**2)))
    i = np.arange(n_cap) + 0.5
    r, a = radius * np.sqrt(i / n_cap), math.pi * (3 - math.sqrt(5)) * i  # sunflower disc
    disc = np.stack([cy + r * np.cos(a), cz + r * np.sin(a)], 1)
    caps_p, caps_n = [], []
    for xc, nx in ((x_start, -1.0), (x_end, 1.0)):
        caps_p.append(np.concatenate([np.full((n_cap, 1), xc), disc], 1))
        caps_n.append(np.tile([nx, 0.0, 0.0], (n_cap, 1)))
    p = np.concatenate([side_p] + caps_p)
    n = np.concatenate([side_n] + caps_n)
    scales = np.stack([np.full(len(p), 0.7 * s)] * 2 + [np.full(len(p), 1e-4)], 1)
    return p, quat_z_to(n), scales, np.full(len(p), 0.8)


def particle_volumes(x: np.ndarray, dx: float) -> np.ndarray:
    """A cell's volume divided by the particles in it: a scanned wall weighs one cell thick
    (this benchmark's model of a hollow scan; preparation weighs a fixed shell instead)."""
    keys = np.floor(x / dx).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    return dx**3 / counts[inv.reshape(-1)]


def frequency(t: np.ndarray, d: np.ndarray) -> float:
    """Whole periods between the first zero crossing and the last one in the same direction
    -> Hz (bench/physics.py's rule; linear interpolation between samples)."""
    s = np.sign(d)
    idx = np.nonzero((s[:-1] != 0) & (s[1:] != s[:-1]))[0]
    if len(idx) == 0:
        return float("nan")
    times = t[idx] - d[idx] * (t[idx + 1] - t[idx]) / (d[idx + 1] - d[idx])
    dirs = np.where(d[idx] < 0, 1, -1)
    same = times[dirs == dirs[0]]
    return float("nan") if len(same) < 2 else (len(same) - 1) / (same[-1] - same[0])


def section(x: np.ndarray, vol: np.ndarray, x0: float, L: float) -> dict:
    """What the MPM integrates: cross-section area A (m^2) and second moment I about the
    horizontal axis (m^4) from the particles' volumes and heights in the middle 60% of the
    free rod (away from clamp and cap), the linear density lam = rho A (kg/m) and the tip
    mass m_tip = free mass - lam L (kg; the end cap, the last cell's overhang)."""
    mid = np.abs(x[:, 0] - (x0 + L / 2)) < 0.3 * L
    v, z = vol[mid], x[mid, 2].astype(np.float64)
    area = float(v.sum()) / (0.6 * L)
    zc = float((v * z).sum() / v.sum())
    inertia = float((v * (z - zc) ** 2).sum()) / (0.6 * L)
    m_free = RHO * float(vol[x[:, 0] >= x0].sum())
    return {"A_m2": area, "I_m4": inertia, "lam_kg_m": RHO * area,
            "tip_mass_kg": max(m_free - RHO * area * L, 0.0)}


def shear_coefficient(kind: str) -> float:
    """Timoshenko shear coefficient: solid circle 6(1+nu)/(7+6nu), thin tube 2(1+nu)/(4+3nu)."""
    return 6 * (1 + NU) / (7 + 6 * NU) if kind == "filled" else 2 * (1 + NU) / (4 + 3 * NU)


def cantilever(inertia: float, lam: float, m_tip: float, L: float, kappa: float) -> dict:
    """Cantilever of second moment I (m^4), linear density lam (kg/m), tip mass m_tip (kg),
    length L (m) and shear coefficient kappa: first frequency (Hz), static tip deflection
    under the poke's acceleration and under gravity (m), peak tip displacement of the
    one-mode response to the poke (m).

    Bending: Euler-Bernoulli with Rayleigh's tip mass. Shear (Timoshenko, L/R = 10 makes it
    a few per cent, more for a tube): Dunkerley's sum 1/w^2 = 1/w_bend^2 + 1/w_shear^2 with
    the fixed-free shear beam w_shear = (pi / 2L) sqrt(kappa G / rho); shear deflection added
    to the static one.
    """
    area, shear_mod = lam / RHO, E_PA / (2 * (1 + NU))
    k = 3 * E_PA * inertia / L**3  # bending tip stiffness, N/m
    w_bend2 = k / (RAYLEIGH_MASS * lam * L + m_tip)
    w_shear2 = (math.pi / (2 * L)) ** 2 * kappa * shear_mod / RHO
    omega = 1 / math.sqrt(1 / w_bend2 + 1 / w_shear2)
    ka = kappa * shear_mod * area
    per_accel = (lam * L**4 / (8 * E_PA * inertia) + m_tip / k  # m per m/s^2: bending
                 + lam * L**2 / (2 * ka) + m_tip * L / ka)  # and shear
    return {"frequency_hz": omega / (2 * math.pi),
            "frequency_bending_only_hz": math.sqrt(w_bend2) / (2 * math.pi),
            "static_deflection_m": POKE_ACCEL * per_accel,
            "peak_displacement_m": 2 * POKE_ACCEL * per_accel * abs(math.sin(omega * POKE_S / 2)),
            "gravity_sag_m": 9.81 * per_accel}


def nominal(kind: str, radius: float, L: float, wall: float) -> dict:
    """Textbook reference: a solid rod of the scan's radius R against a tube of mid radius R
    and wall `wall` (m) with its tip cap (a disc of the same wall), density RHO."""
    if kind == "filled":
        area, inertia, m_tip = math.pi * radius**2, math.pi * radius**4 / 4, 0.0
    else:
        ro, ri = radius + wall / 2, max(radius - wall / 2, 0.0)
        area, inertia = math.pi * (ro**2 - ri**2), math.pi * (ro**4 - ri**4) / 4
        m_tip = RHO * math.pi * radius**2 * wall
    return {"A_m2": area, "I_m4": inertia,
            **cantilever(inertia, RHO * area, m_tip, L, shear_coefficient(kind))}


def setup(radius_cells: int, slender: float):
    """Geometry in metres: domain, clamp plane x0, tip x_end, rod axis (cy, cz), R, L."""
    dx = DX
    radius = radius_cells * dx
    L = round(slender * radius_cells) * dx
    off = (PAD + MARGIN_CELLS) * dx
    x_start = off
    x0 = x_start + CLAMP_CELLS * dx
    x_end = x0 + L
    side = 2 * off + 2 * radius + 2 * ROOM_CELLS * dx
    domain = (x_end + off + dx, side, side)
    return domain, x_start, x0, x_end, side / 2, radius, L


def clamp_block(x_start: float, x0: float, c: float, radius: float) -> np.ndarray:
    """Static particles (2^3 per cell) filling the rod's cross-section, shell band included,
    for x in [x_start, x0): a vice that holds the whole root, the same for both runs."""
    h = DX / 2
    ax = [np.arange(x_start + h / 2, x0, h)] + [np.arange(c - radius - DX, c + radius + DX, h) + h / 2] * 2
    g = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    return g[np.hypot(g[:, 1] - c, g[:, 2] - c) < radius + 0.75 * DX]


def simulate(x: np.ndarray, n_shell: int, x0: float, x_end: float, domain, seconds: float,
             cfl: float, device: str) -> dict:
    """One run; x [N, 3] m holds the shell first (n_shell particles). Particles with x < x0
    are static. Returns masses, section properties, the tip trace, its peak and frequency."""
    vol = particle_volumes(x, DX)
    mass = RHO * vol
    static = x[:, 0] < x0
    free = ~static
    tip = free & (x[:, 0] > x_end - DX)
    tip[n_shell:] = False  # what a viewer sees: the shell at the tip
    cfg = SimConfig(grid_res=int(round(max(domain) / DX)), domain=domain, nu=NU,
                    gravity=(0.0, 0.0, 0.0), cfl_safety=cfl, boundary_pad=PAD)
    sim = MPMSolver(x, vol, mass, np.full(len(x), E_PA), static, cfg, device=device)
    sim.add_force(free, (0.0, 0.0, -POKE_ACCEL), 0.0, POKE_S)
    n_frames = int(round(seconds * FPS))
    t, d = np.zeros(n_frames + 1), np.zeros(n_frames + 1)
    substeps = 0
    t0 = time.perf_counter()
    for f in range(n_frames):
        substeps += sim.step_frame(1.0 / FPS)
        t[f + 1] = sim.time
        d[f + 1] = sim.displacements()[tip, 2].mean()
    wall = time.perf_counter() - t0
    after = t >= POKE_S
    return {
        "particles": int(len(x)), "free_particles": int(free.sum()),
        "free_mass_kg": float(mass[free].sum()), "section": section(x, vol, x0, x_end - x0),
        "peak_displacement_m": float(np.abs(d).max()), "time_to_peak_s": float(t[np.argmax(np.abs(d))]),
        "frequency_hz": frequency(t[after], d[after]), "substeps": int(substeps),
        "sim_seconds": wall, "trace_t": t.tolist(), "trace_dz": d.tolist(),
    }


def run(radius_cells: int = 4, slender: float = 10.0, seconds: float = 1.0, cfl: float = 0.5,
        clamp: str = "block", scan_per_cell: float = SCAN_PER_CELL, device: str = "cpu",
        log=print) -> dict:
    """Scan, fill and simulate both rods; returns the measurements with beam theory."""
    domain, x_start, x0, x_end, c, radius, L = setup(radius_cells, slender)
    p, q, s, o = rod_scan(x_start, x_end, c, c, radius, DX, scan_per_cell)
    t0 = time.perf_counter()
    fill = fill_interior(p, q, s, o, cell=DX, mode="auto", grid_origin=(0.0, 0.0, 0.0))
    t_fill = time.perf_counter() - t0
    log(f"fill ({t_fill:.2f} s): {fill.reason}")
    pts = np.asarray(fill.points)
    if clamp == "block":  # the root is held by the vice, not by the scan's shell ring
        shell, pts = p[p[:, 0] >= x0], pts[pts[:, 0] >= x0]
        held = clamp_block(x_start, x0, c, radius)
    else:  # "shell": whatever of the scan lies in the clamp is static (bake's rule)
        shell, held = p, np.zeros((0, 3))
    out = {"radius_m": radius, "free_length_m": L, "domain_m": list(domain), "clamp": clamp,
           "fill": {"decision": fill.decision, "closedness": fill.closedness,
                    "interior_volume_m3": fill.interior_volume, "points": int(len(fill.points)),
                    "reason": fill.reason, "seconds": t_fill},
           "runs": {}}
    for name, x in (("hollow", np.concatenate([shell, held])),
                    ("filled", np.concatenate([shell, pts, held]))):
        r = simulate(x.astype(np.float32), len(shell), x0, x_end, domain, seconds, cfl, device)
        sec = r["section"]
        r["theory"] = cantilever(sec["I_m4"], sec["lam_kg_m"], sec["tip_mass_kg"], L,
                                 shear_coefficient(name))
        out["runs"][name] = r
        th = r["theory"]
        log(f"{name:7s} particles {r['particles']:6,d}  free mass {r['free_mass_kg']:.3f} kg  "
            f"I/A {sec['I_m4'] / sec['A_m2'] / radius**2:.3f} R^2  "
            f"f {r['frequency_hz']:.3f} Hz (theory {th['frequency_hz']:.3f})  "
            f"peak {1000 * r['peak_displacement_m']:.2f} mm (theory "
            f"{1000 * th['peak_displacement_m']:.2f})  [{r['substeps']} substeps, "
            f"{r['sim_seconds']:.1f} s]")
    h, f = out["runs"]["hollow"], out["runs"]["filled"]
    wall = h["section"]["A_m2"] / (2 * math.pi * radius)  # the one-cell shell's wall, m
    out["shell_wall_m"] = wall
    out["nominal"] = {k: nominal(k, radius, L, wall) for k in ("hollow", "filled")}
    out["ratios_filled_over_hollow"] = {
        "free_mass": f["free_mass_kg"] / h["free_mass_kg"],
        "frequency": f["frequency_hz"] / h["frequency_hz"],
        "frequency_theory": f["theory"]["frequency_hz"] / h["theory"]["frequency_hz"],
        "frequency_nominal": out["nominal"]["filled"]["frequency_hz"] / out["nominal"]["hollow"]["frequency_hz"],
        "peak": f["peak_displacement_m"] / h["peak_displacement_m"],
        "peak_theory": f["theory"]["peak_displacement_m"] / h["theory"]["peak_displacement_m"]}
    log(f"shell wall {1000 * wall:.2f} mm = {wall / DX:.2f} cells; nominal f: solid rod "
        f"{out['nominal']['filled']['frequency_hz']:.3f} Hz, tube {out['nominal']['hollow']['frequency_hz']:.3f} Hz")
    log("filled / hollow: " + ", ".join(f"{k} {v:.3f}" for k, v in out["ratios_filled_over_hollow"].items()))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--radius-cells", type=int, default=4, help="rod radius in grid cells")
    ap.add_argument("--slender", type=float, default=10.0, help="free length / radius")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated time, s (the period grows with R at a fixed L/R: "
                    "about 1 s for 2 filled periods at R = 4 cells, 2 s at R = 8)")
    ap.add_argument("--cfl", type=float, default=0.5, help="SimConfig.cfl_safety")
    ap.add_argument("--clamp", choices=["block", "shell"], default="block",
                    help="block: a static solid vice at the root (both runs); shell: only "
                         "the scan's own particles in the clamp are static")
    ap.add_argument("--scan-per-cell", type=float, default=SCAN_PER_CELL,
                    help="Gaussians per surface cell of the scanned shell")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the fill)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: a 3-cell rod, 0.3 s")
    ap.add_argument("--json", type=Path, help="write the results here")
    a = ap.parse_args(argv)
    if a.quick:
        a.radius_cells, a.seconds = 3, 0.3
    import torch
    import warp as wp

    torch.set_num_threads(a.threads)
    wp.config.quiet = True
    wp.init()
    t0 = time.perf_counter()
    out = run(a.radius_cells, a.slender, a.seconds, a.cfl, a.clamp, a.scan_per_cell, a.device)
    out.update({"command": "python bench/fill_motion.py " + " ".join(sys.argv[1:] if argv is None else argv),
                "device": a.device, "platform": platform.processor() or platform.machine(),
                "E_pa": E_PA, "nu": NU, "rho": RHO, "dx_m": DX, "poke_accel": POKE_ACCEL,
                "poke_s": POKE_S, "gravity": 0.0, "cfl_safety": a.cfl,
                "scan_per_cell": a.scan_per_cell,
                "wall_s": time.perf_counter() - t0})
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
