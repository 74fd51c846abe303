"""How many drivers a cell does a bake need? The product's drivers against denser ones, all
judged against a converged reference under the fit benchmark's new force.

A scene with few Gaussians for its grid (a small capture, or a thin one whose grid the bake
raises) gets about one driver a cell at the default quality's driver ratio, and MPM
particles a cell apart separate under a push. Per scene and grid, four discretisations,
each with one uniform E:
  ratio     K-Means over the particles at the default quality's driver ratio, no floor;
  split     every particle split into sub-particles, 2 a cell along each axis
            (pd_tool.prepare.split.split_particles);
  k-means   K-Means over that split cloud, `--per-cell` drivers a cell (the paper's 8);
  product   the bake's drivers: the ratio's, or the k-means row's where the ratio gives
            fewer than the floor (pd_tool.prepare.preparation.MIN_DRIVERS_PER_CELL);
against the split simulation on `--reference` cells. Each row gives the drivers a cell,
the peak (the largest displacement over frames and moving Gaussians, / the object's size)
against the reference's, and the RMS error / size over frames and moving Gaussians.

    python bench/driver_density.py --quick          # CPU: the plant, 3,000 Gaussians, 32 / 48 cells
    python bench/driver_density.py --device cuda --gaussians 20000 --grids 64,128 --reference 192
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # fit_truth's scenes and force


def run_scene(name: str, args) -> list[dict]:
    """One scene's rows: the reference, then each grid's three discretisations."""
    from fit_truth import NEW_FORCE, SCENES, Judge, load_scene, new_force, per_cell

    from pd_tool.fit.reference import simulate_positions
    from pd_tool.prepare.split import split_drivers, split_particles
    from pd_tool.materials.presets import load_preset
    from pd_tool.prepare.preparation import MIN_DRIVERS_PER_CELL, PrepareOptions, prepare_scene, up_rotation

    up = SCENES[name]
    scene = load_scene(name, args.gaussians, data=args.data).to(args.device)
    pos = scene.positions.detach().cpu().double().numpy()
    h = pos @ up_rotation(up)[2]
    static_below = float(h.min() + 0.1 * np.ptp(h))
    size = float(np.ptp(pos, axis=0).max())
    force = new_force(scene, up)
    ratio = args.ratio if args.ratio is not None else float(load_preset("quality", "default")["driver_ratio"])

    def prepared(grid: int):
        return prepare_scene(scene, PrepareOptions(grid_res=grid, up_axis=up, static_below=static_below))

    def simulated(prep, drivers) -> tuple:
        """(drivers, positions [T, N, 3], seconds) of one discretisation."""
        return (drivers, *run(prep, drivers))

    def run(prep, drivers) -> tuple[np.ndarray, float]:
        t0 = time.perf_counter()
        x = simulate_positions(scene, prep, drivers, np.full(len(drivers.positions), args.E), nu=0.3,
                               seconds=args.seconds, fps=30.0, accel=force[0], device=args.device, cfl_safety=0.25,
                               duration=NEW_FORCE["duration"], at=force[1], radius=force[2])
        return x, time.perf_counter() - t0

    ref_prep = prepared(args.reference)
    ref_drivers = split_particles(scene, ref_prep, device=args.device)[0]
    x_ref, seconds = run(ref_prep, ref_drivers)
    judge = Judge.of(ref_prep, x_ref, size)

    def row(grid: int, mode: str, prep, drivers, x: np.ndarray, secs: float) -> dict:
        return {"scene": name, "grid": grid, "mode": mode, "drivers": len(drivers.positions),
                "per_cell": per_cell(prep, drivers), "peak": judge.peak(x),
                "peak_ratio": judge.peak(x) / max(judge.peak(x_ref), 1e-12), "rms": judge.off(x), "seconds": secs}

    rows = [row(args.reference, "reference (split)", ref_prep, ref_drivers, x_ref, seconds)]
    for grid in args.grids:
        prep = prepared(grid)
        ratio_row = row(grid, "ratio", prep, *simulated(prep, prep.build_drivers(ratio=ratio, seed=0, device=args.device)))
        km_drivers = split_drivers(scene, prep, per_cell=args.per_cell, device=args.device)
        km_row = row(grid, f"k-means {args.per_cell} a cell", prep, *simulated(prep, km_drivers))
        rows += [ratio_row, row(grid, "split", prep, *simulated(prep, split_particles(scene, prep, device=args.device)[0])),
                 km_row]
        # the product's drivers are one of the rows above: the floor decides which
        rows.append(dict(km_row if prep.splits(ratio, MIN_DRIVERS_PER_CELL) else ratio_row, mode="product"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CPU: the plant, 3000 Gaussians, grids 32,48, reference 64")
    ap.add_argument("--scenes", default="plant,udon,donut,tree")
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--grids", default="64,128", help="comma-separated grid cells")
    ap.add_argument("--reference", type=int, default=192, help="the split reference's grid cells")
    ap.add_argument("--per-cell", type=int, default=8, help="the k-means rows' drivers a cell")
    ap.add_argument("--ratio", type=float, default=None,
                    help="the ratio rows' drivers per Gaussian (default: the default quality's driver_ratio; "
                         "its fit_driver_ratio, 0.1, shows the fit's discretisation)")
    ap.add_argument("--E", type=float, default=3e5, help="uniform Young's modulus, Pa")
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.gaussians, args.grids, args.reference = "plant", 3000, "32,48", 64
    args.grids = [int(g) for g in args.grids.split(",") if g]

    from pd_tool.core.device import init_warp_quietly

    init_warp_quietly()
    rows = []
    print("scene  grid  mode                 drivers  a cell   peak / ref   RMS / size", flush=True)
    for name in args.scenes.split(","):
        for r in run_scene(name, args):
            rows.append(r)
            print(f"{r['scene']:6} {r['grid']:4}  {r['mode']:20} {r['drivers']:8,} {r['per_cell']:6.1f}   "
                  f"{r['peak_ratio']:9.3f}   {r['rms']:9.2%}", flush=True)
            if args.json:
                import torch

                args.json.write_text(json.dumps({
                    "device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
                    "settings": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
                    "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
