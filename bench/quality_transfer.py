"""Does a fitted material move the same when it is baked at another quality than its fit?

A fit finds E on its own discretisation (the default quality's fit: 32 cells, 0.1 drivers
per Gaussian). A user fits at default and bakes at final for the shot; that bake runs on
other cells, drivers and CFL safety, and where parts are thin MPM's stiffness depends on
the cell. `pdtool bake --quality Q` therefore matches the fitted E to its own grid first
(pd_tool.bake.transfer, `--match-fit`). This benchmark measures what that gives.

Each scene gets a material file as a fit writes it, holding a smooth hidden E field (6e4 Pa
at the top to 2e6 Pa at the base, 3x stiffer on one side: bench/fit_truth.py's `smooth`) on
the default quality's fit discretisation, and one poke (a 0.1 s sideways push on the top
30%, the bottom tenth static). The reference is that material baked as fitted (no
--quality): the motion the fit's model makes. Then the same bake at each --quality, with
the match (the product's default) and without it (`--no-match-fit`).

Per scene and setting, against the reference (bench/convergence.py's measures):
  peak   99th percentile over the moving Gaussians of the displacement, max over frames,
         as a ratio to the reference's;
  rms    RMS over frames and moving Gaussians of |x - x_ref|, over the reference's peak.
Bounds, as for a material preset against a converged reference: draft within 25%, default
within 10% (rms at most 15%), final within 5%. Figures: docs/benchmarks.md, "Fitted
materials at another quality".

    python bench/quality_transfer.py --quick       # CPU, CI scale: plant and udon at draft
    python bench/quality_transfer.py --device cuda --gaussians 100000 --scenes plant,udon,donut,tree \\
        --qualities draft,default,final --json out.json
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from convergence import peak_of  # noqa: E402
from fit_truth import SCENES, load_scene, truth_field  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
PUSH = (1.0, 0.0, 0.0)  # scene axes; sideways on every scene's up axis (+z or -y)
POKE = dict(magnitude=4.0, radius_fraction=0.3, duration=0.1)  # object sizes/s^2, the top 30%, s


@dataclass
class Row:
    scene: str
    setting: str  # "as fitted" | QUALITY | QUALITY no match
    grid: int = 0
    drivers: int = 0
    peak: float = float("nan")  # of the object's size
    peak_ratio: float = float("nan")
    rms: float = float("nan")  # of the reference's peak
    factor: float = float("nan")  # the match's E factor
    match_ratio: float = float("nan")  # the motion over the fit's that the match ended on
    match_runs: int = 0
    match_seconds: float = float("nan")
    seconds: float = float("nan")  # the whole bake, wall


def material_file(scene, up: str, quality: dict, seed: int = 0):
    """A MaterialFile with the smooth hidden field per Gaussian, on the fit discretisation
    of `quality` (a quality preset's table)."""
    from pd_tool.materials.file import MaterialFile
    from pd_tool.materials.presets import fit_simulation

    grid, cfl, ratio = fit_simulation(quality)
    pos = scene.positions.detach().cpu().double().numpy()
    E = truth_field(scene, up, "smooth", seed)
    return MaterialFile(driver_E=E, driver_v0=np.zeros((len(E), 3), np.float32), driver_rest=pos,
                        meta={"simulation": {"grid_res": grid, "driver_ratio": ratio, "driver_seed": 0,
                                             "cfl_safety": cfl}, "nu": 0.3, "density": 700.0})


def bake_positions(scene, up: str, mf, quality: str | None, match: bool, seconds: float, device: str,
                   out: Path) -> tuple[np.ndarray, np.ndarray, Row]:
    """Every Gaussian's position [T, N, 3] (scene units), the moving mask [N] and a Row,
    through the product's Baker (a USD file is written and thrown away)."""
    from pd_tool.bake import BakeSettings, ForceSpec
    from pd_tool.bake.baker import Baker
    from pd_tool.prepare.preparation import PrepareOptions, up_rotation

    h = scene.positions.detach().cpu().double().numpy() @ up_rotation(up)[2]
    static_below = float(h.min() + 0.1 * np.ptp(h))
    force = ForceSpec(accel=tuple(POKE["magnitude"] * np.asarray(PUSH)), at="top",
                      radius_fraction=POKE["radius_fraction"], duration=POKE["duration"], units="size",
                      magnitude=POKE["magnitude"])
    settings = BakeSettings(seconds=seconds, fps=30.0, quality=quality, fmt="instancer", device=device,
                            stop_at_rest=False, match_fit=match)
    frames: list[np.ndarray] = []

    class Recording(Baker):
        def _frame_arrays(self, d_now):
            pos, q, disp = super()._frame_arrays(d_now)
            frames.append(pos.copy())
            return pos, q, disp

    t0 = time.perf_counter()
    with Recording(scene, out, force=force, material_file=mf, settings=settings,
                   prepare_options=PrepareOptions(up_axis=up, static_below=static_below, density_kg_m3=700.0)) as b:
        while not b.done:
            b.step()
        b.finish()
    moving = np.zeros(scene.count, bool)
    moving[b.prep.foreground[~b.prep.static[: b.prep.count]]] = True
    m = b.match
    row = Row(scene="", setting="", grid=max(b.prep.grid_dims), drivers=b.n_drivers, seconds=time.perf_counter() - t0,
              factor=m.factor if m else float("nan"), match_ratio=m.ratio if m else float("nan"), match_runs=m.runs if m else 0,
              match_seconds=m.seconds if m else float("nan"))
    return np.stack(frames), moving, row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="CPU, CI scale: plant and udon, 3000 Gaussians, draft, "
                                                         "0.6 s")
    ap.add_argument("--scenes", default="plant,udon,donut,tree")
    ap.add_argument("--qualities", default="draft,default,final")
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the real captures")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.scenes, args.qualities, args.gaussians, args.seconds = "plant,udon", "draft", 3000, 0.6

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.materials.presets import load_preset

    init_warp_quietly()
    result = {"device": args.device, "gaussians": args.gaussians, "seconds": args.seconds, "rows": []}
    print(f"{'scene':6} {'setting':18} {'grid':>4} {'drivers':>7} {'peak':>7} {'peak/ref':>8} {'rms':>6} "
          f"{'E x':>6} {'runs':>4} {'match s':>7} {'bake s':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes.split(","):
            up = SCENES[name]
            scene = load_scene(name, args.gaussians, args.data).to(args.device)
            mf = material_file(scene, up, load_preset("quality", "default"))
            x_ref, moving, ref_row = bake_positions(scene, up, mf, None, True, args.seconds, args.device,
                                                    Path(tmp) / "ref.usd")
            size = float(np.ptp(x_ref[0, moving], axis=0).max())
            peak_ref = peak_of(x_ref, moving, size)
            settings = [("as fitted", None, True)] + [(q if match else f"{q} no match", q, match)
                                                      for q in args.qualities.split(",") for match in (True, False)]
            for key, q, match in settings:  # each row as its bake ends, so a run cut short shows its rows
                if q is None:
                    x, row = x_ref, ref_row
                else:
                    x, _, row = bake_positions(scene, up, mf, q, match, args.seconds, args.device,
                                               Path(tmp) / f"{q}{match}.usd")
                row.scene, row.setting = name, key
                row.peak = peak_of(x, moving, size)
                row.peak_ratio = row.peak / peak_ref
                err = np.linalg.norm(x[:, moving] - x_ref[:, moving], axis=-1)
                row.rms = float(np.sqrt((err ** 2).mean()) / size / peak_ref)
                result["rows"].append(asdict(row))
                print(f"{name:6} {key:18} {row.grid:4d} {row.drivers:7d} {row.peak:7.2%} {row.peak_ratio:8.3f} "
                      f"{row.rms:6.1%} {row.factor:6.3g} {row.match_runs:4d} {row.match_seconds:7.1f} "
                      f"{row.seconds:7.1f}", flush=True)
                if args.json:  # after every row, so a run cut short keeps what it measured
                    args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
