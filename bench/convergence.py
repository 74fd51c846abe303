"""Does a bake's motion depend on its quality? Each scene's poke, baked at the quality
presets, against a converged reference, and the thin strip against plate theory.

Scenes: `strip` (a clamped strip well under a cell thick at the default quality, first
frequency from Kirchhoff plate theory), `plant` (the procedural plant with thin leaves and
petals), and the real captures `udon`, `donut` and `tree` from ../shared/data. Each gets one
uniform material and one poke (a short push sideways at the top, the bottom tenth static),
simulated at draft, default and final (the presets' grid, CFL safety and driver ratio), and
at the reference: `--reference` cells with every Gaussian a particle and CFL safety
`--reference-cfl`. `--check-grid` adds a finer run that shows whether the reference has
converged.

Reported per scene and setting, against the reference (error of the reference itself is
the finer run's):
  peak   largest displacement (99th percentile over the moving Gaussians, max over frames),
         as a ratio to the reference's;
  rms    RMS over frames and moving Gaussians of |x - x_ref|, divided by the reference's peak;
  f1     first oscillation frequency (Hz) of the most moving Gaussians' mean displacement
         along the push, from its crossings of rest after the push, recorded at 120 fps;
         nan when it does not swing a full period. For the strip, against theory too.
  decay  the factor by which that swing shrinks each period (1: undamped; nan as f1).

Targets: default peak within 10 % and rms at most 15 %, draft within 25 %, final within
5 %; the strip's f1 within 5 % of theory at default. Figures: docs/benchmarks.md,
"Convergence against a fine reference".

    python bench/convergence.py --quick          # CPU, CI scale, a smoke run (minutes)
    python bench/convergence.py --device cuda --gaussians 100000 --reference 128 \\
        --check-grid 192 --sweep 32:0.05,48,96 --scenes plant,udon,donut,tree --json out.json
    python bench/convergence.py --device cuda --gaussians 300000 --reference 128 \\
        --check-grid 256 --scenes strip --json strip.json
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data"
QUALITIES = ("draft", "default", "final")
FPS = 120.0  # recorded frames per second: four per 30 fps frame, so that f1 is read to about 1 %


@dataclass(frozen=True)
class Case:
    """One scene's set-up: where it comes from, its up axis, its material and its poke.
    E in Pa, density kg/m^3, accel m/s^2 along `push` (scene axes) for `duration` s."""

    name: str
    up: str
    E: float
    density: float
    accel: float
    push: tuple[float, float, float]
    duration: float = 0.1
    nu: float = 0.3
    seconds: float = 1.0


STRIP = dict(length=0.9, width=0.25, thickness=0.012, base=0.1)
STRIP_F1 = 1.0  # Hz: the strip's E is set so that plate theory gives this first frequency
CASES = {
    # the strip: E from STRIP_F1 and --strip-thickness (default 1.2 cm: 0.46 of a default
    # cell, 1.5 cells at 192); pushed across its thickness (x)
    "strip": Case("strip", "+z", 0.0, 700.0, 6.0, (1.0, 0.0, 0.0), duration=0.1, seconds=2.5),
    "plant": Case("plant", "+z", 2.0e5, 700.0, 1.5, (1.0, 0.0, 0.0)),
    "udon": Case("udon", "-y", 2.0e5, 1000.0, 1.5, (1.0, 0.0, 0.0)),
    "donut": Case("donut", "+z", 5.0e4, 1000.0, 1.5, (1.0, 0.0, 0.0)),
    "tree": Case("tree", "-y", 1.0e6, 700.0, 1.5, (1.0, 0.0, 0.0)),
}


@dataclass
class Run:
    scene: str
    setting: str  # draft | default | final | reference | check
    grid: int
    cfl: float
    ratio: float
    seconds_wall: float = float("nan")
    substeps: int = 0  # most per 30 fps frame
    drivers: int = 0
    per_cell: float = float("nan")  # driving particles per occupied cell
    peak: float = float("nan")  # fraction of the object's size
    peak_ratio: float = float("nan")
    rms: float = float("nan")  # of the reference's peak
    f1: float = float("nan")  # Hz
    extra: dict = field(default_factory=dict)


def load_scene(name: str, gaussians: int, seed: int = 0, data: Path = DATA):
    """The scene as a GaussianScene, subsampled to at most `gaussians` (seeded)."""
    from pd_tool.io.synthetic import make_plant, make_strip

    if name == "strip":
        return make_strip(gaussians, **STRIP, seed=seed)
    if name == "plant":
        return make_plant(gaussians, seed=seed, thin=True)
    from pd_tool.io import load_splats

    path = {"udon": "udon.ply", "donut": "donut_fused.ply", "tree": "tree_100k.splat"}[name]
    scene = load_splats(data / path)
    if scene.count > gaussians:
        keep = np.sort(np.random.default_rng(seed).choice(scene.count, gaussians, replace=False))
        scene = scene.subset(keep)
    return scene


def pinned_below(scene, case: Case) -> float:
    """The case's --static-below height: the strip's block only, else the lowest tenth of
    the scene along its up axis."""
    from pd_tool.prepare.preparation import up_rotation

    if case.name == "strip":
        return 1e-6
    height = scene.positions.detach().cpu().double().numpy() @ up_rotation(case.up)[2]
    lo, hi = float(height.min()), float(height.max())
    return lo + 0.1 * (hi - lo)


def even_strip_weights() -> None:
    """Make the strip's Gaussians (those above its block) share its volume evenly, for every
    later preparation in this process: the volume rule's part in the strip's frequency."""
    from pd_tool.prepare import preparation

    shell = preparation.surface_volumes

    def even(positions, device="cpu"):
        vol = shell(positions, device)
        x = np.asarray(positions, np.float64) - np.asarray(positions, np.float64).min(axis=0)
        strip = x[:, 2] > STRIP["base"] + 1e-9 * STRIP["length"]
        vol[strip] = STRIP["length"] * STRIP["width"] * STRIP["thickness"] / max(int(strip.sum()), 1)
        return vol

    preparation.surface_volumes = even


def simulate(scene, case: Case, grid: int, cfl: float, ratio: float, device: str,
             thin_grid: int | None = None, fill: str = "auto", split: int = 0,
             min_per_cell: float | None = None, driver_E: Callable | None = None,
             fps: float = FPS) -> tuple[np.ndarray, np.ndarray, Run]:
    """Positions of every Gaussian [T, N, 3] (scene units), the moving mask [N] and the
    run's record, for one discretisation, through the product's own steps: with
    `thin_grid`, the grid is raised for thin parts as a bake raises it; with `split` > 0
    every particle is split into sub-particles, `split` a cell along each axis
    (pd_tool.prepare.split.split_particles), instead of clustered into drivers; without,
    the drivers keep a bake's floor a cell (`min_per_cell`, default the product's).
    driver_E(prep, drivers) -> [Q] Pa: each driver's E (default case.E everywhere); fps:
    the frames recorded per second."""
    from pd_tool.fit.reference import simulate_positions
    from pd_tool.prepare.split import split_particles
    from pd_tool.prepare.preparation import MIN_DRIVERS_PER_CELL, PrepareOptions, prepare_scene, refine_for_thin

    prep = prepare_scene(scene, PrepareOptions(grid_res=grid, up_axis=case.up, static_below=pinned_below(scene, case),
                                               density_kg_m3=case.density, fill=fill))
    finer = refine_for_thin(prep, thin_grid) if thin_grid else None
    if finer is not None:  # as a bake does: the finer grid
        prep = finer
    grid = int(prep.options.grid_res)
    t0 = time.perf_counter()
    drivers = (split_particles(scene, prep, per_cell=split, device=device)[0] if split > 0
               else prep.build_drivers(ratio=ratio, seed=0, device=device, min_per_cell=MIN_DRIVERS_PER_CELL if min_per_cell is None else min_per_cell))
    d_rest = drivers.positions.double().cpu().numpy()
    # the push is in m/s^2 whatever the scene's units
    accel = tuple(np.asarray(case.push, float) * case.accel / prep.transform.scale)
    stats: dict = {}
    E = np.full(len(d_rest), case.E) if driver_E is None else driver_E(prep, drivers)
    x = simulate_positions(scene, prep, drivers, E, nu=case.nu, seconds=case.seconds,
                           fps=fps, accel=accel, device=device, cfl_safety=cfl, stats=stats, duration=case.duration)
    moving = np.zeros(scene.count, bool)
    moving[prep.foreground[~prep.static[: prep.count]]] = True
    # substeps per 30 fps frame, the product's frame
    run = Run(case.name, "", grid, cfl, ratio, seconds_wall=time.perf_counter() - t0,
              substeps=stats["substeps"] * round(fps / 30),
              drivers=int(len(d_rest)),
              per_cell=len(d_rest) / len(np.unique(np.floor(d_rest / prep.dx).astype(np.int64), axis=0)),
              extra={"particles_per_cell": prep.n_particles / prep.occupied_cells(),
                     "drivers_per_occupied_cell": len(d_rest) / prep.occupied_cells(),
                     "mass_kg": float(prep.masses.sum()),
                     "filled_m3": float(prep.volumes[prep.count:].sum()), "split": split})
    return x, moving, run


def peak_of(x: np.ndarray, moving: np.ndarray, size: float) -> float:
    """Largest displacement over frames of the 99th percentile over the moving Gaussians,
    as a fraction of `size`. x [T, N, 3]."""
    d = np.linalg.norm(x[:, moving] - x[0, moving], axis=-1)
    return float(np.percentile(d, 99, axis=1).max() / size)


def first_frequency(signal: np.ndarray, fps: float, after: float) -> float:
    """First oscillation frequency (Hz) of `signal` [T] (a displacement from rest) sampled at
    `fps`: the mean spacing of its crossings of rest after time `after` (s), each placed by
    linear interpolation between samples; NaN when it crosses fewer than three times (it
    does not swing a full period)."""
    s = np.asarray(signal, float)[int(np.ceil(after * fps)):]
    k = np.nonzero(np.sign(s[1:]) != np.sign(s[:-1]))[0]
    if len(k) < 3:
        return float("nan")
    t = k + s[k] / (s[k] - s[k + 1])  # sub-sample crossing times, in samples
    return float(fps / (2.0 * np.diff(t).mean()))


def decay_per_period(signal: np.ndarray, fps: float, after: float) -> float:
    """How much a swing shrinks in one period: the ratio of the first half-swing's largest
    |signal| (between its first two crossings of rest after `after` s) to the last whole
    half-swing's, to the power 2 / (half-swings between them). 1: no damping; 2: half the
    amplitude lost each period. NaN with fewer than three crossings (two half-swings)."""
    s = np.asarray(signal, float)[int(np.ceil(after * fps)):]
    k = np.nonzero(np.sign(s[1:]) != np.sign(s[:-1]))[0]
    if len(k) < 3:
        return float("nan")
    amp = [np.abs(s[a + 1: b + 1]).max() for a, b in zip(k[:-1], k[1:])]
    if amp[-1] <= 0:
        return float("inf")
    return float((amp[0] / amp[-1]) ** (2.0 / (len(amp) - 1)))


def strip_beam_peak(E: float, density: float, length: float, width: float, thickness: float, accel: float,
                    duration: float, centre_y: float, radius: float) -> tuple[float, float]:
    """The strip's first swing from Euler-Bernoulli beam theory, five clamped-free modes:
    `accel` (m/s^2) across the thickness for `duration` s on the part of the strip within
    `radius` (m) of its top edge's point at `centre_y` (the push's sphere), then free and
    undamped. Returns (the 99th percentile over the strip's length of |deflection|, max over
    the first swing, as a fraction of `length`; the swing's end, s: the push and half a
    period). Twist from an off-centre push is left out."""
    integrate = getattr(np, "trapezoid", None) or np.trapz  # numpy 2 renamed it; numpy 1 lacks the new name
    z = np.linspace(0.0, length, 2001)
    half = np.sqrt(np.clip(radius ** 2 - (z - length) ** 2, 0.0, None))
    pushed = np.clip(np.minimum(width / 2, centre_y + half) - np.maximum(-width / 2, centre_y - half), 0, None) / width
    from pd_tool.io.synthetic import clamped_strip_frequency

    f1 = clamped_strip_frequency(E, 0.0, density, length, thickness)  # nu = 0: a beam, E t^3 / 12
    end = duration + 0.5 / f1
    t = np.linspace(0.0, end, 1201)[:, None]
    w = np.zeros((t.shape[0], len(z)))
    for bl in (1.8751041, 4.6940911, 7.8547574, 10.9955407, 14.1371684):
        b = bl / length
        sigma = (np.cosh(bl) + np.cos(bl)) / (np.sinh(bl) + np.sin(bl))
        phi = np.cosh(b * z) - np.cos(b * z) - sigma * (np.sinh(b * z) - np.sin(b * z))
        om = 2 * np.pi * f1 * (bl / 1.8751041) ** 2
        load = accel * integrate(pushed * phi, z) / integrate(phi * phi, z)  # modal force per modal mass
        q = np.where(t < duration, 1 - np.cos(om * t), np.cos(om * (t - duration)) - np.cos(om * t)) * load / om ** 2
        w += q * phi
    return float(np.percentile(np.abs(w), 99, axis=1).max() / length), float(end)


def compare(runs: dict[str, tuple[np.ndarray, np.ndarray, Run]], case: Case,
            swing_end: float | None = None) -> list[Run]:
    """Fill each run's peak, peak ratio, rms and f1 against runs['reference']; with
    `swing_end` (s), also its peak over the first swing (extra['first_swing'])."""
    x_ref, moving, ref = runs["reference"]
    size = float(np.ptp(x_ref[0, moving], axis=0).max())
    push = np.asarray(case.push, float) / np.linalg.norm(case.push)
    d_ref = np.linalg.norm(x_ref[:, moving] - x_ref[0, moving], axis=-1).max(axis=0)
    top = np.argsort(d_ref)[-max(1, len(d_ref) // 20):]
    peak_ref = peak_of(x_ref, moving, size)
    step = max(1, round(FPS / 30))
    out = []
    for name, (x, _, run) in runs.items():
        run.setting = name
        err = np.linalg.norm(x[:, moving] - x_ref[:, moving], axis=-1)
        run.rms = float(np.sqrt((err ** 2).mean()) / size / peak_ref)
        sig = ((x[:, moving][:, top] - x[0, moving][top]) @ push).mean(axis=1)
        run.f1 = first_frequency(sig, FPS, case.duration)
        run.extra["decay_per_period"] = decay_per_period(sig, FPS, case.duration)
        # where the peak comes from: when, how many Gaussians reach it, and the motion at
        # 30 fps (the reference's fastest 5 % along the push; the 99th percentile)
        d = np.linalg.norm(x[:, moving] - x[0, moving], axis=-1)
        p99 = np.percentile(d, 99, axis=1)
        run.peak = float(p99.max() / size)  # peak_of, from the displacements this loop needs anyway
        run.peak_ratio = run.peak / peak_ref
        p99 = p99 / size
        run.extra.update(peak_s=float(np.argmax(p99) / FPS), peak_p90=float(np.percentile(d, 90, axis=1).max() / size),
                         peak_max=float(d.max() / size), tip_series=np.round(sig[::step] / size, 5).tolist(),
                         p99_series=np.round(p99[::step], 5).tolist())
        if swing_end is not None:
            run.extra["first_swing"] = float(p99[: int(swing_end * FPS) + 1].max())
        out.append(run)
    return out


def plot(sources: list[Path], png: Path) -> None:
    """Peak against the reference's, by grid, one line per scene: the runs at the default
    CFL safety and driver ratio (0.5 / 0.5), the reference (1) and the finer check, from
    earlier --json files; a later file's scene replaces that scene's whole line (a later run
    of a scene measures it against its own reference)."""
    from pd_tool.render.plots import line_plot

    points: dict[str, dict[int, float]] = {}
    for src in sources:
        lines: dict[str, dict[int, float]] = {}
        for r in json.loads(src.read_text())["runs"]:
            if r["setting"] in ("check", "reference") or (r["cfl"] == 0.5 and r["ratio"] == 0.5):
                lines.setdefault(r["scene"], {})[int(r["grid"])] = float(r["peak_ratio"])
        points.update(lines)
    series = {name: (sorted(p), [p[g] for g in sorted(p)]) for name, p in points.items()}
    line_plot(png, series, title="peak motion against a converged reference", xlabel="grid cells",
              ylabel="peak / reference")
    print(f"wrote {png}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="CPU, CI scale: 3000 Gaussians, reference 48 cells, half the seconds, the 4 cm strip")
    ap.add_argument("--scenes", default=",".join(CASES), help="comma-separated: " + ", ".join(CASES))
    ap.add_argument("--gaussians", type=int, default=20000)
    ap.add_argument("--strip-gaussians", type=int, default=0,
                    help="the strip's Gaussians (default --gaussians): a fine reference needs several per cell")
    ap.add_argument("--strip-thickness", type=float, default=STRIP["thickness"],
                    help="m; 0.012 is under half a cell at the default quality's 64 cells")
    ap.add_argument("--qualities", default=",".join(QUALITIES),
                    help="the quality presets to run, comma-separated ('' for none: the --sweep grids and the "
                         "reference alone)")
    ap.add_argument("--sweep", default="", help="extra grids at the default CFL and driver ratio, e.g. 24,32,48; "
                    "GRID:RATIO for another driver ratio, e.g. 24:0.05")
    ap.add_argument("--reference", type=int, default=128, help="the reference's grid cells")
    ap.add_argument("--reference-cfl", type=float, default=0.25)
    ap.add_argument("--split", type=int, default=0,
                    help="the reference's and the check's sub-particles per cell along each axis (0: every Gaussian "
                         "one particle, which is about one a cell for a scan sparse on the reference's grid)")
    ap.add_argument("--check-grid", type=int, default=0, help="a finer run to show the reference converged (0: none)")
    ap.add_argument("--strip-even-weights", action="store_true",
                    help="the strip's Gaussians share its volume evenly instead of the shell rule's weights "
                         "(a diagnostic of the volume rule; the product has no such option)")
    ap.add_argument("--no-refine-thin", action="store_true",
                    help="the presets' rows on their own grids, as `pdtool bake --no-refine-thin` bakes")
    ap.add_argument("--fill", default="auto", choices=["auto", "on", "off"],
                    help="interior filling for every run, as `pdtool bake --fill`")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--data", type=Path, default=DATA, help="folder of the real captures")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--plot", type=Path, metavar="PNG",
                    help="draw peak / reference against grid cells from the --from JSON files and exit")
    ap.add_argument("--from", dest="sources", type=Path, nargs="+", default=[], metavar="JSON")
    args = ap.parse_args()
    if args.plot:
        plot(args.sources, args.plot)
        return
    if args.quick:
        # CI scale: a smoke run of every scene and quality, not an accuracy figure (too few
        # particles per cell); half the seconds, and the 4 cm strip, whose stiffness needs
        # a third of the thin strip's substeps
        args.gaussians, args.reference, args.strip_thickness = 3000, 48, 0.04

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.materials.presets import load_preset
    from pd_tool.fit.reference import PUSH_RADIUS_FRACTION
    from pd_tool.io.synthetic import clamped_strip_frequency

    init_warp_quietly()
    if args.strip_even_weights:
        even_strip_weights()
    unknown = set(filter(None, args.qualities.split(","))) - set(QUALITIES)
    if unknown:
        sys.exit(f"--qualities: unknown {', '.join(sorted(unknown))}; choose from {', '.join(QUALITIES)}")
    settings = {q: load_preset("quality", q) for q in QUALITIES}
    result = {"device": args.device, "gaussians": args.gaussians, "reference": args.reference,
              "reference_cfl": args.reference_cfl, "check_grid": args.check_grid, "runs": []}
    print(f"{'scene':7} {'setting':10} {'grid':>4} {'cfl':>5} {'ratio':>5} {'peak':>7} {'peak/ref':>8} "
          f"{'rms':>6} {'f1 Hz':>6} {'decay':>6} {'substeps':>8} {'/cell':>5} {'s':>7}")
    for name in args.scenes.split(","):
        case = CASES[name]
        if args.quick:
            case = replace(case, seconds=case.seconds / 2)
        if name == "strip":
            STRIP["thickness"] = args.strip_thickness
            unit = clamped_strip_frequency(1.0, case.nu, case.density, STRIP["length"], STRIP["thickness"])
            case = replace(case, E=(STRIP_F1 / unit) ** 2)
        count = args.strip_gaussians if name == "strip" and args.strip_gaussians else args.gaussians
        scene = load_scene(name, count, data=args.data).to(args.device)
        runs = {}
        for q in filter(None, args.qualities.split(",")):
            s = settings[q]
            runs[q] = simulate(scene, case, int(s["grid_res"]), float(s["cfl_safety"]), float(s["driver_ratio"]),
                               args.device, thin_grid=None if args.no_refine_thin else s.get("thin_grid_res"),
                               fill=args.fill)
        d = settings["default"]
        for item in filter(None, args.sweep.split(",")):
            g, _, r = item.partition(":")
            ratio = float(r) if r else float(d["driver_ratio"])
            runs[f"grid {g}" + (f" r{r}" if r else "")] = simulate(scene, case, int(g), float(d["cfl_safety"]), ratio,
                                                                   args.device, fill=args.fill)
        runs["reference"] = simulate(scene, case, args.reference, args.reference_cfl, 1.0, args.device, fill=args.fill,
                                     split=args.split)
        if args.check_grid:
            runs["check"] = simulate(scene, case, args.check_grid, args.reference_cfl, 1.0, args.device,
                                     fill=args.fill, split=args.split)
        beam = swing_end = None
        if name == "strip":  # the first swing from beam theory: a reference no simulation made
            pos = scene.positions.detach().cpu().double().numpy()
            top = pos[np.argmax(pos[:, 2])]
            beam, swing_end = strip_beam_peak(case.E, case.density, STRIP["length"], STRIP["width"],
                                              STRIP["thickness"], case.accel, case.duration, float(top[1]),
                                              PUSH_RADIUS_FRACTION * float(np.ptp(pos, axis=0).max()))
        for run in compare(runs, case, swing_end):
            if name == "strip":
                run.extra["first_swing_beam"] = beam
                run.extra["f1_theory"] = clamped_strip_frequency(case.E, case.nu, case.density, STRIP["length"],
                                                                 STRIP["thickness"])
                # a strip only a few thicknesses wide bends as a beam (E, not E / (1 - nu^2))
                run.extra["f1_beam"] = run.extra["f1_theory"] * (1.0 - case.nu ** 2) ** 0.5
                run.extra["E"] = case.E
            result["runs"].append(asdict(run))
            print(f"{name:7} {run.setting:10} {run.grid:4d} {run.cfl:5.2f} {run.ratio:5.2f} {run.peak:7.2%} "
                  f"{run.peak_ratio:8.3f} {run.rms:6.1%} {run.f1:6.2f} {run.extra['decay_per_period']:6.2f} "
                  f"{run.substeps:8d} {run.per_cell:5.1f} {run.seconds_wall:7.1f}",
                  flush=True)
        if name == "strip":
            ex = result["runs"][-1]["extra"]
            print(f"strip   theory f1 {ex['f1_theory']:.3f} Hz as a plate, {ex['f1_beam']:.3f} Hz as a beam "
                  f"(thickness {STRIP['thickness']} m, length {STRIP['length']} m, E {case.E:.3g} Pa)")
            print(f"strip   first swing (to {swing_end:.2f} s) against beam theory's {beam:.2%}: " + ", ".join(
                f"{r['setting']} {r['extra']['first_swing'] / beam:.3f}" for r in result["runs"] if r["scene"] == "strip"))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
