"""How much the discretisation alone changes a simulated motion, next to what changing E
does, on the synthetic plant with its true E.

Part "substeps": the recovery benchmark's push, simulated with the CFL choice of substeps,
with fewer and more, and with a softer stem and a stiffer flower. MPM loses energy in
every particle-grid transfer, so its damping depends on the substep count; a fit whose
count follows its current E compares the video with a model that changes as E moves.
Reports the RMS driver position difference against the CFL run over the first 14 frames
(the reference video's length) and over 2 s. Every case but the last runs at a fixed count.

Part "grid": the recovery benchmark's new force (a sideways drag at the top), simulated
with the true E on the default fit's discretisation (32 cells, 0.1 driving particles per
Gaussian) and on others, among them the default bake preset's (16 cells, 0.5); and the
uniform 1e6 Pa baseline on the fit's. Reports the RMS Gaussian position difference over
2 s against the fit's discretisation. This is why a bake of a fitted material simulates as
the fit did (pd_tool/bake/baker.py).

Both as a fraction of the object's size.

    python bench/discretisation_sensitivity.py --gaussians 3000 --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--part", choices=["substeps", "grid", "both"], default="both")
    ap.add_argument("--grid", type=int, default=48, help="part substeps: grid cells along the longest side")
    ap.add_argument("--cfl", type=float, default=0.6, help="CFL safety of the reference run")
    ap.add_argument("--ratio", type=float, default=0.1, help="drivers per Gaussian")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.io.synthetic import make_plant

    init_warp_quietly()
    scene = make_plant(args.gaussians, seed=0)
    out = {"gaussians": args.gaussians}
    if args.part in ("substeps", "both"):
        out["substeps"] = substep_part(args, scene)
    if args.part in ("grid", "both"):
        out["grid"] = grid_part(args, scene)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


def grid_part(args, scene) -> dict:
    import numpy as np

    from fit_recovery import simulate_positions
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.io.synthetic import POT_TOP, driver_truth_E

    runs, baseline = {}, None
    for grid, ratio in ((32, 0.1), (16, 0.5), (16, 0.1), (32, 0.5), (24, 0.1)):
        prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=grid))
        drivers = prep.build_drivers(ratio=ratio, seed=0)
        E = driver_truth_E(scene, prep, drivers)
        sim = dict(nu=0.3, seconds=2.0, fps=30.0, accel=(0.0, 6.0, 0.0), device=args.device, cfl_safety=0.5)
        runs[(grid, ratio)] = simulate_positions(scene, prep, drivers, E, **sim), prep.foreground
        if (grid, ratio) == (32, 0.1):
            baseline = simulate_positions(scene, prep, drivers, np.full(len(E), 1e6), **sim)
    ref, fg = runs[(32, 0.1)]
    size = float(np.ptp(ref[0][fg], axis=0).max())

    def rms(a):
        return float(np.sqrt(((a[:, fg] - ref[:, fg]) ** 2).sum(-1).mean()) / size)

    rows = {"uniform 1e6 Pa on the fit's discretisation (the recovery baseline)": rms(baseline)}
    for (grid, ratio), (x, _) in runs.items():
        if (grid, ratio) != (32, 0.1):
            rows[f"true E, {grid} cells, {ratio:g} drivers per Gaussian"] = rms(x)
    for name, v in rows.items():
        print(f"{name:70s} RMS vs true E on 32 cells / 0.1: {v:.4f} (of object size)")
    return rows


def substep_part(args, scene) -> dict:
    import numpy as np

    from fit_recovery import PUSH_SPEED, push_direction
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.fit.reference import push_velocity
    from pd_tool.sim import MPMSolver, SimConfig
    from pd_tool.io.synthetic import POT_TOP, REGIONS, driver_regions, driver_truth_E

    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=args.grid))
    drivers = prep.build_drivers(ratio=args.ratio, seed=0)
    E = driver_truth_E(scene, prep, drivers)
    x0 = drivers.positions.double().cpu().numpy()
    static = drivers.static.cpu().numpy().astype(bool)
    v0 = push_velocity(x0, static, direction=push_direction(0), speed=PUSH_SPEED)
    frames = int(round(2.0 * args.fps))

    def run(driver_E, substeps=None):
        cfg = SimConfig(grid_res=max(prep.grid_dims), domain=prep.domain, nu=0.3, gravity=(0.0, 0.0, 0.0),
                        cfl_safety=args.cfl, substeps=substeps)
        s = MPMSolver(x0, drivers.volume.cpu().numpy(), drivers.mass.cpu().numpy(), driver_E, static, cfg,
                      device=args.device)
        s.set_velocity(v0)
        used, out = [], []
        for _ in range(frames):
            used.append(s.step_frame(1.0 / args.fps))
            out.append(np.array(s.positions()))
        return np.stack(out), max(used)

    ref, n = run(E)
    size = float(np.ptp(x0[~static], axis=0).max())

    def rms(a, k):
        return float(np.sqrt(((a[:k] - ref[:k]) ** 2).sum(-1).mean()) / size)

    reg = driver_regions(scene, prep, drivers)
    stem, flower = REGIONS.index("stem"), REGIONS.index("flower")
    cases = {
        f"substeps x0.85 ({int(round(0.85 * n))})": (E, int(round(0.85 * n))),
        f"substeps x2 ({2 * n})": (E, 2 * n),
        # were the difference time-stepping error, finer steps would converge (x4, x8 would
        # differ from the CFL run little more than x2 does); MPM's transfer damping keeps
        # adding with every doubling instead
        f"substeps x4 ({4 * n})": (E, 4 * n),
        f"substeps x8 ({8 * n})": (E, 8 * n),
        "stem E x0.67": (np.where(reg == stem, 0.67 * E, E), n),
        # the stem is the stiffest moving region, so under CFL its E also sets the substeps
        "stem E x0.67, CFL substeps": (np.where(reg == stem, 0.67 * E, E), None),
        "flower E x2": (np.where(reg == flower, 2.0 * E, E), n),
    }
    out = {"grid": args.grid, "drivers": int(len(E)), "cfl_substeps": n, "cases": {}}
    for name, (driver_E, sub) in cases.items():
        a, used = run(driver_E, sub)
        out["cases"][name] = {"substeps": used, "rms_14_frames": rms(a, 14), "rms_2s": rms(a, frames)}
        print(f"{name:26s} RMS vs CFL run: 14 frames {rms(a, 14):.4f}, 2 s {rms(a, frames):.4f} (of object size)")
    return out


if __name__ == "__main__":
    main()
