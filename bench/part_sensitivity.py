"""Can a video tell one part's stiffness? The thin plant (3 mm leaves and petals) under the
convergence benchmark's poke (bench/convergence.py: a short push sideways at the top, the
bottom tenth static), simulated on each grid with a uniform E and again with one part's E
divided by --factor. A part whose E changes the motion little cannot be fitted from a video
of it, however good the fit's model.

Reported per grid and part, as fractions of the uniform run's peak (99th percentile
displacement over the moving Gaussians, max over frames):
  all    RMS over frames and moving Gaussians of the position change
  own    the same over the softened part's own Gaussians

    python bench/part_sensitivity.py --quick      # CPU, CI scale, a smoke run
    python bench/part_sensitivity.py --grids 32,64,96 --json out.json
Figures: docs/benchmarks.md, "Fit against a converged truth".
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import convergence as conv  # noqa: E402  (the scene, its poke and peak measure)


def sensitivity(grid: int, parts: list[str], factor: float, gaussians: int, seconds: float, device: str) -> dict:
    """One grid's row: the cell dx_m (m), the uniform run's peak (fraction of the object's
    size) and per part {"all", "own"} (module docstring)."""
    from pd_tool.io.synthetic import REGIONS, driver_regions

    case = replace(conv.CASES["plant"], seconds=seconds)
    scene = conv.load_scene("plant", gaussians).to(device)
    dx: list[float] = []

    def run(part: str | None) -> tuple[np.ndarray, np.ndarray]:
        """Positions [T, N, 3] at 30 fps and the moving mask [N], `part`'s E divided by factor."""
        def driver_E(prep, drivers) -> np.ndarray:
            dx.append(float(prep.dx))
            soft = driver_regions(scene, prep, drivers) == (REGIONS.index(part) if part else -1)
            return np.where(soft, case.E / factor, case.E)

        x, moving, _ = conv.simulate(scene, case, grid, 0.5, 0.5, device, driver_E=driver_E, fps=30.0)
        return x, moving

    t0 = time.perf_counter()
    x0, moving = run(None)
    size = float(np.ptp(x0[0, moving], axis=0).max())
    peak = conv.peak_of(x0, moving, size)
    row: dict = {"grid": grid, "dx_m": dx[0], "peak": peak, "parts": {}}
    for part in parts:
        d = np.linalg.norm(run(part)[0][:, moving] - x0[:, moving], axis=-1) / size / peak
        own = scene.labels[moving] == REGIONS.index(part)
        row["parts"][part] = {"all": float(np.sqrt((d ** 2).mean())), "own": float(np.sqrt((d[:, own] ** 2).mean()))}
    row["seconds"] = time.perf_counter() - t0
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CPU, CI scale: 3000 Gaussians, grids 16,24, half a second")
    ap.add_argument("--grids", default="32,64,96")
    ap.add_argument("--parts", default="leaf,flower", help="the plant's regions to soften, one at a time")
    ap.add_argument("--factor", type=float, default=10.0, help="E of the part divided by this")
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--seconds", type=float, default=conv.CASES["plant"].seconds)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.grids, args.seconds = 3000, "16,24", 0.5

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.io.synthetic import REGIONS

    init_warp_quietly()
    parts = [p for p in args.parts.split(",") if p]
    unknown = [p for p in parts if p not in REGIONS]
    if unknown or not args.factor > 0:
        sys.exit(f"--parts: choose from {', '.join(REGIONS)}; --factor > 0" + (f" (unknown: {unknown})" if unknown else ""))
    rows = []
    print(f"{'grid':>4} {'cell cm':>7} {'peak':>6}  " + "  ".join(f"{p + '/' + format(args.factor, 'g') + ': all / own':>22}"
                                                         for p in parts))
    for g in (int(x) for x in args.grids.split(",")):
        row = sensitivity(g, parts, args.factor, args.gaussians, args.seconds, args.device)
        rows.append(row)
        print(f"{g:4d} {row['dx_m'] * 100:7.2f} {row['peak']:6.1%}  " + "  ".join(
            f"{row['parts'][p]['all']:12.2%} / {row['parts'][p]['own']:7.2%}" for p in parts), flush=True)
    if args.json:
        args.json.write_text(json.dumps({"device": args.device, "gaussians": args.gaussians, "factor": args.factor,
                                         "seconds": args.seconds, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
