"""pdtool's MPM beside Genesis's (`genesis-world` on PyPI, its MPM solver) on the same
particles, grid and material.

The scene and the sway are bench/peer_newton.py's: the solver benchmarks' block
(pd_tool.io.synthetic.make_block, about 8 particles per occupied cell of a res^3 grid over
the unit box, its bottom layer clamped), E = 1e5 Pa, nu = 0.3, 1000 kg/m^3, no gravity, a
sideways velocity growing with height to `--speed` m/s at the top, `--seconds` at 30 fps.

Both are explicit MLS-MPM with quadratic B-splines and the fixed-corotated stress
(Genesis's `MPM.Elastic(model="corotation")`), so here the models match: Genesis gets
pdtool's particles (Genesis fills a box of the block's size with k^3 particles, which are
moved onto pdtool's; N is rounded to a cube), their volume (Genesis gives every particle
particle_size^3: the block's particles are equal), pdtool's
cell (grid_density = res over the unit box) and pdtool's CFL substep count. What differs:
the clamp (pdtool fixes the grid nodes nearest its static particles and holds the
particles; Genesis only holds the particles, `set_free(False)`), the SVD Genesis takes for
R where pdtool iterates a polar decomposition, and Genesis's wall padding of 3 cells.
Compared: seconds per simulated second, each with a host copy of the positions every
frame, and the motion (99th-percentile displacement of the moving particles, RMS of the
per-particle difference, as shares of pdtool's peak).

`--free` drops the clamp (no static particles: the block flies and wobbles), which leaves
the two solvers alone in the comparison.

Genesis runs in its own Python (its dependencies are many, and it brings its own
compiler, quadrants): `--genesis-python PATH` names that interpreter, and this file runs
there as a worker that reads the scene from and writes the trajectory to .npz files. With
no path, Genesis must import in this Python.

    python -m venv /tmp/genv && /tmp/genv/bin/pip install genesis-world torch
    python bench/peer_genesis.py --device cpu --sizes 20000:32 --genesis-python /tmp/genv/bin/python
    python bench/peer_genesis.py --quick --genesis-python /tmp/genv/bin/python   # 4,000 particles, 24 cells
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

E, NU, DENSITY = 1.0e5, 0.3, 1000.0
FPS = 30.0


def genesis_worker(scene_npz: Path, out_npz: Path) -> None:
    """Run Genesis on the scene in scene_npz (x [N, 3], v0 [N, 3], static [N], particle_size,
    res, substeps, frames, device) and write its trajectory [F+1, N, 3], the seconds of the
    timed frames and Genesis's version. Imports numpy and genesis only."""
    import genesis as gs

    d = np.load(scene_npz)
    x, v0, static = d["x"].astype(np.float32), d["v0"].astype(np.float32), d["static"].astype(bool)
    res, substeps, frames = int(d["res"]), int(d["substeps"]), int(d["frames"])
    device = str(d["device"])
    gs.init(backend=gs.gpu if device.startswith("cuda") else gs.cpu, precision="32", logging_level="warning")

    k = round(len(x) ** (1.0 / 3.0))
    size = float(d["particle_size"]) * k

    def make():
        scene = gs.Scene(
            sim_options=gs.options.SimOptions(dt=1.0 / FPS, substeps=substeps, gravity=(0.0, 0.0, 0.0)),
            mpm_options=gs.options.MPMOptions(lower_bound=(0.0, 0.0, 0.0), upper_bound=(1.0, 1.0, 1.0),
                                              grid_density=float(res), particle_size=float(d["particle_size"])),
            show_viewer=False)
        # Genesis fills a box with round(size / particle_size)^3 particles; they are then
        # moved onto pdtool's (the block holds k^3)
        body = scene.add_entity(material=gs.materials.MPM.Elastic(E=E, nu=NU, rho=DENSITY, model="corotation",
                                                                          sampler="regular"),
                                morph=gs.morphs.Box(pos=(0.5, 0.5, 0.5), size=(size, size, size)))
        scene.build()
        if body.n_particles != len(x):
            raise SystemExit(f"Genesis sampled {body.n_particles} particles, not {len(x)}")
        body.set_particles_pos(x)
        body.set_particles_vel(v0)
        body.set_free(~static)
        return scene, body

    scene, _ = make()
    scene.step()  # compile
    scene, body = make()
    traj = [body.get_particles_pos().cpu().numpy().reshape(len(x), 3).copy()]
    t = time.perf_counter()
    for _ in range(frames):
        scene.step()
        traj.append(body.get_particles_pos().cpu().numpy().reshape(len(x), 3).copy())
    seconds = time.perf_counter() - t
    np.savez(out_npz, traj=np.stack(traj), seconds=seconds, version=gs.__version__)


def run_genesis(python: str | None, x, v0, static, particle_size: float, res: int, substeps: int, frames: int,
                device: str) -> dict:
    """Genesis's trajectory and time, in `python` (a subprocess running this file as the worker)
    or in this process."""
    with tempfile.TemporaryDirectory() as tmp:
        scene_npz, out_npz = Path(tmp) / "scene.npz", Path(tmp) / "out.npz"
        np.savez(scene_npz, x=x, v0=v0, static=static, particle_size=particle_size, res=res, substeps=substeps,
                 frames=frames, device=device)
        if python:
            proc = subprocess.run([python, str(Path(__file__).resolve()), "--worker", str(scene_npz), str(out_npz)],
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                raise SystemExit(f"Genesis failed ({python}): {proc.stderr.strip()[-3000:]}")
        else:
            genesis_worker(scene_npz, out_npz)
        d = np.load(out_npz)
        return {"traj": d["traj"], "seconds": float(d["seconds"]), "version": str(d["version"])}


def block_scene(n: int, res: int, speed: float, clamp: bool = True) -> dict:
    """The block of about n particles that both solvers get: n rounded to a cube k^3 (Genesis's
    box sampler makes k^3 particles), x [n, 3] m, vol and mass [n], static [n] (none without
    `clamp`), the sway v0 [n, 3] m/s and Genesis's particle_size (m), whose cube is each
    particle's volume."""
    from peer_newton import sway

    from pd_tool.io.synthetic import make_block

    n = round(n ** (1.0 / 3.0)) ** 3
    x, vol, mass, _, static = make_block(n, res, E=E, density=DENSITY)
    if not clamp:
        static = np.zeros_like(static)
    return {"n": n, "x": x, "vol": vol, "mass": mass, "static": static, "v0": sway(x, static, speed),
            "particle_size": float(np.cbrt(vol[0]))}


def compare(n: int, res: int, seconds: float, speed: float, device: str, python: str | None,
            clamp: bool = True) -> dict:
    from peer_newton import against, motion, run_pdtool

    b = block_scene(n, res, speed, clamp)
    n, x, vol, mass, static, v0 = b["n"], b["x"], b["vol"], b["mass"], b["static"], b["v0"]
    frames = int(round(seconds * FPS))
    moving = ~static
    ours = run_pdtool(x, vol, mass, static, res, v0, frames, device)
    substeps = int(round(ours["steps"] / frames))
    theirs = run_genesis(python, x, v0, static, b["particle_size"], res, substeps, frames, device)
    m_ours = motion(ours["traj"], moving)
    peak = float(m_ours.max())
    steps = frames * substeps
    return {
        "n": n, "res": res, "clamp": clamp, "frames": frames, "speed_m_s": speed, "substeps_per_frame": substeps,
        "pdtool": {"s_per_sim_s": ours["seconds"] / seconds, "ms_per_substep": 1e3 * ours["seconds"] / ours["steps"],
                   "particle_substeps_per_s": n * ours["steps"] / ours["seconds"], "peak_m": peak,
                   "motion_m": m_ours.tolist()},
        "genesis": {"version": theirs["version"], "s_per_sim_s": theirs["seconds"] / seconds,
                    "ms_per_substep": 1e3 * theirs["seconds"] / steps,
                    "particle_substeps_per_s": n * steps / theirs["seconds"],
                    "time_ratio": theirs["seconds"] / ours["seconds"],
                    **against(ours["traj"], theirs["traj"], moving, peak)}}


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--worker":
        genesis_worker(Path(sys.argv[2]), Path(sys.argv[3]))
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="20000:32", help="N:res pairs, comma separated")
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated time")
    ap.add_argument("--speed", type=float, default=0.3, help="the sway's speed at the top, m/s")
    ap.add_argument("--genesis-python", default=None, help="the Python with genesis-world installed (default: this one)")
    ap.add_argument("--free", action="store_true", help="no clamp: the block flies and wobbles, so that the "
                    "two clamps' difference leaves the comparison")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 4,000 particles on 24 cells, 0.2 s")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.genesis_python is None:
        try:
            import genesis  # noqa: F401
        except ImportError:
            print("bench/peer_genesis.py needs Genesis: pip install genesis-world, or name its Python with "
                  "--genesis-python", file=sys.stderr)
            sys.exit(2)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import warp as wp

    wp.config.quiet = True
    if args.quick:
        args.sizes, args.seconds = "4000:24", 0.2
    rows = []
    for spec in args.sizes.split(","):
        n, res = (int(v) for v in spec.split(":"))
        row = compare(n, res, args.seconds, args.speed, args.device, args.genesis_python, clamp=not args.free)
        rows.append(row)
        p, g = row["pdtool"], row["genesis"]
        print(f"N={row['n']:,} res={res}, {row['substeps_per_frame']} substeps a frame: pdtool {p['s_per_sim_s']:.3f} s per "
              f"simulated s ({p['ms_per_substep']:.3f} ms a substep), peak {p['peak_m'] * 100:.2f} cm; Genesis "
              f"{g['version']} {g['s_per_sim_s']:.3f} s ({g['time_ratio']:.2f}x pdtool's, {g['ms_per_substep']:.3f} ms "
              f"a substep), peak {g['peak_ratio']:.2f} of pdtool's, RMS difference {g['rms_diff_over_peak']:.2f} of "
              f"its peak", flush=True)
    out = {"device": args.device, "gpu": wp.get_device(args.device).name, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
