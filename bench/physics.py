"""Validate the MPM simulator against beam theory.

(a) Fixed-free elastic bar, first axial mode:      f = sqrt(E / rho) / (4 L)
(b) Clamped cantilever, first bending mode:        f = 1.875^2 / (2 pi) sqrt(E I / (rho A L^4))

Both with Poisson's ratio 0 and gravity off. The object starts at rest in its rest shape
with the velocity of the mode shape; the frequency is measured from the tip displacement by
counting whole periods between the first zero crossing about the rest position and the last
crossing in the same direction (linear interpolation between samples), never from the mean
of a partial period.

    python bench/physics.py --quick --json out.json        # CPU, under a minute
    python bench/physics.py --json out.json                # convergence table (slower)
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pd_tool.sim import MPMSolver, SimConfig  # noqa: E402

E_PA = 1.0e6  # Young's modulus, Pa
RHO = 1000.0  # density, kg/m^3
DX = 0.01  # grid spacing, m (frequencies scale; relative errors do not)
PPC_AXIS = 2  # particles per cell along each axis (8 per cell)
CLAMP_CELLS = 3  # length of the static block that clamps the beam, cells
MARGIN_CELLS = 2  # free cells between the object and the wall padding
BETA1 = 1.8751040687  # first root of 1 + cos(b) cosh(b) = 0


def lattice(lo: np.ndarray, hi: np.ndarray, dx: float, ppc: int = PPC_AXIS) -> np.ndarray:
    """Particles at the centres of a regular ppc^3-per-cell lattice in the box [lo, hi] (m)."""
    h = dx / ppc
    axes = [np.arange(lo[d] + 0.5 * h, hi[d] - 0.25 * h, h) for d in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def beam_setup(n_thick: int, slender: float, transverse_margin: int, pad: int):
    """A beam along x, clamped at x0 by a static block; returns geometry in metres."""
    h = n_thick * DX
    L = round(slender * n_thick) * DX
    off = (pad + MARGIN_CELLS) * DX
    x0 = off + CLAMP_CELLS * DX  # clamp plane, on a node
    side = 2 * off + h + 2 * transverse_margin * DX
    y0 = off + transverse_margin * DX
    clamp = lattice(np.array([off, y0, y0]), np.array([x0, y0 + h, y0 + h]), DX)
    beam = lattice(np.array([x0, y0, y0]), np.array([x0 + L, y0 + h, y0 + h]), DX)
    x = np.concatenate([clamp, beam])
    static = np.zeros(len(x), bool)
    static[: len(clamp)] = True
    domain = (x0 + L + off, side, side)
    return x, static, domain, x0, L, h


def zero_crossings(t: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Times (s, linearly interpolated) and directions (+1 up, -1 down) where d changes sign."""
    s = np.sign(d)
    idx = np.nonzero((s[:-1] != 0) & (s[1:] != s[:-1]))[0]  # a sample at exactly 0 starts none
    times = t[idx] - d[idx] * (t[idx + 1] - t[idx]) / (d[idx + 1] - d[idx])
    return times, np.where(d[idx] < 0, 1, -1)


def measure_frequency(t: np.ndarray, d: np.ndarray) -> float:
    """Whole periods between the first zero crossing and the last one in the same direction
    -> frequency, Hz. (d starts at exactly 0 at t = 0; that start is not counted.)"""
    times, dirs = zero_crossings(t, d)
    if len(times) == 0:
        return float("nan")
    same = times[dirs == dirs[0]]
    if len(same) < 2:
        return float("nan")
    return (len(same) - 1) / (same[-1] - same[0])


def run_mode(x, static, domain, shape_v, tip_mask, axis, f_theory, periods, samples_per_period,
             safety, pad, device):
    n = len(x)
    vol = np.full(n, (DX / PPC_AXIS) ** 3)
    cfg = SimConfig(grid_res=int(round(max(domain) / DX)), domain=domain, nu=0.0,
                    gravity=(0.0, 0.0, 0.0), cfl_safety=safety, boundary_pad=pad)
    sim = MPMSolver(x, vol, vol * RHO, np.full(n, E_PA), static, cfg, device=device)
    sim.set_velocity(shape_v)
    frame_dt = 1.0 / (f_theory * samples_per_period)
    # the first crossing comes half a period in; keep a margin after the last one
    n_frames = int(math.ceil((periods + 0.65) * samples_per_period))
    t = np.zeros(n_frames + 1)
    d = np.zeros(n_frames + 1)
    t0 = time.perf_counter()
    substeps = sim.substeps_per_frame(frame_dt)
    for k in range(n_frames):
        sim.step_frame(frame_dt)
        t[k + 1] = sim.time
        d[k + 1] = sim.displacements()[tip_mask, axis].mean()
    wall = time.perf_counter() - t0
    f = measure_frequency(t, d)
    return {
        "f_theory_hz": f_theory, "f_measured_hz": f, "rel_error": (f - f_theory) / f_theory,
        "particles": n, "grid_res": cfg.grid_res, "cfl_safety": safety,
        "substeps_per_frame": substeps, "total_substeps": substeps * n_frames,
        "amplitude_m": float(np.abs(d).max()), "periods": periods, "wall_s": wall,
    }


def cantilever(n_thick: int, safety: float, periods: float = 1.0, slender: float = 10.0,
               pad: int = 3, device: str = "cpu") -> dict:
    """Clamped cantilever with a square n_thick-cell cross-section and length slender * h."""
    amp_cells = 1  # room for the tip amplitude
    x, static, domain, x0, L, h = beam_setup(n_thick, slender, amp_cells + 1, pad)
    I, A = h**4 / 12.0, h * h
    f = BETA1**2 / (2 * math.pi) * math.sqrt(E_PA * I / (RHO * A * L**4))
    xi = np.clip((x[:, 0] - x0) / L, 0.0, 1.0)
    b = BETA1 * xi
    sig = (math.cosh(BETA1) + math.cos(BETA1)) / (math.sinh(BETA1) + math.sin(BETA1))
    phi = np.cosh(b) - np.cos(b) - sig * (np.sinh(b) - np.sin(b))
    phi /= phi.max()
    amp = 0.05 * h  # tip amplitude, m: small, linear regime
    v = np.zeros_like(x)
    v[:, 2] = amp * 2 * math.pi * f * phi
    v[static] = 0
    tip = (~static) & (x[:, 0] > x0 + L - DX)
    r = run_mode(x, static, domain, v, tip, 2, f, periods, 48, safety, pad, device)
    r.update(case="cantilever", cells_thick=n_thick, slender=slender)
    return r


def bar(n_thick: int, safety: float, periods: float = 3.0, slender: float = 10.0,
        pad: int = 3, device: str = "cpu") -> dict:
    """Fixed-free bar along x with an n_thick-cell square cross-section, length slender * h."""
    x, static, domain, x0, L, h = beam_setup(n_thick, slender, 1, pad)
    c = math.sqrt(E_PA / RHO)
    f = c / (4 * L)
    xi = np.clip((x[:, 0] - x0) / L, 0.0, 1.0)
    amp = 0.01 * L
    v = np.zeros_like(x)
    v[:, 0] = amp * 2 * math.pi * f * np.sin(0.5 * math.pi * xi)
    v[static] = 0
    tip = (~static) & (x[:, 0] > x0 + L - DX)
    r = run_mode(x, static, domain, v, tip, 0, f, periods, 48, safety, pad, device)
    r.update(case="bar", cells_thick=n_thick, slender=slender)
    return r


DEFAULT = {"bar": dict(n_thick=2, safety=0.5, slender=20.0),
           "cantilever": dict(n_thick=4, safety=0.5, slender=10.0)}
# Convergence table of the full run: resolution across the thickness, then the CFL number.
FULL_SWEEP = {"bar": [dict(n_thick=3, safety=0.5), dict(n_thick=4, safety=0.5),
                      dict(n_thick=2, safety=0.25), dict(n_thick=2, safety=0.9)],
              "cantilever": [dict(n_thick=6, safety=0.5), dict(n_thick=8, safety=0.5),
                             dict(n_thick=4, safety=0.25), dict(n_thick=4, safety=0.9)]}
FINEST = {"bar": 4, "cantilever": 8}  # cells across the thickness of the full run's finest beam
# Whole periods measured: the quick run takes one bending period; the full run averages more
# (the first period carries a little of the higher modes the initial velocity excites).
PERIODS = {"quick": {"bar": 3.0, "cantilever": 1.0}, "full": {"bar": 5.0, "cantilever": 3.0}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="default settings only (CPU, < 60 s)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda")
    ap.add_argument("--json", type=Path, help="write results here")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = []
    per = PERIODS["quick" if args.quick else "full"]
    bar_d = bar(device=args.device, periods=per["bar"], **DEFAULT["bar"])
    cant_d = cantilever(device=args.device, periods=per["cantilever"], **DEFAULT["cantilever"])
    rows += [bar_d, cant_d]
    if not args.quick:
        for case, fn in (("bar", bar), ("cantilever", cantilever)):
            for kw in FULL_SWEEP[case]:
                rows.append(fn(slender=DEFAULT[case]["slender"], periods=per[case], device=args.device, **kw))
                r = rows[-1]
                print(f"  {case} thick={r['cells_thick']} safety={r['cfl_safety']} err={100 * r['rel_error']:+.2f}%", flush=True)
    for r in rows:
        print(f"{r['case']:10s} thick={r['cells_thick']} cells grid={r['grid_res']:4d} safety={r['cfl_safety']:.2f} "
              f"substeps={r['total_substeps']:7d} f_theory={r['f_theory_hz']:.4f} Hz f={r['f_measured_hz']:.4f} Hz "
              f"err={100 * r['rel_error']:+.2f}% ({r['wall_s']:.1f} s)")
    out = {"bar_freq_rel_error": abs(bar_d["rel_error"]),
           "cantilever_freq_rel_error": abs(cant_d["rel_error"]),
           "rows": rows, "quick": args.quick, "device": args.device,
           "wall_s": time.perf_counter() - t0}
    if not args.quick:
        for case in ("bar", "cantilever"):
            fine = [r for r in rows if r["case"] == case and r["cells_thick"] == FINEST[case]]
            out[f"full_{case}_freq_rel_error"] = abs(fine[0]["rel_error"])
    print(f"bar_freq_rel_error={out['bar_freq_rel_error']:.4f} cantilever_freq_rel_error="
          f"{out['cantilever_freq_rel_error']:.4f} total {out['wall_s']:.1f} s")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
