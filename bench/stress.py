"""Numerical stability stress matrix for the bake: every case must end stable or with a
clear PdToolError (the stability guard's SimulationUnstable, or a rejected input), quickly.

    python bench/stress.py --quick                 # ~20 cases, what CI runs (tests/integration/test_stress_quick.py)
    python bench/stress.py --json stress.json --markdown stress.md --timeout 120
    python bench/stress.py --device cuda --json stress_gpu.json

Each case bakes a small scene through `pd_tool.bake.baker.bake` (preparation, driving particles,
MPM, Gaussian interpolation, USD writing: the whole user path) and checks the USD it wrote:
  stable    every position finite, inside the simulation box (no escape; 2 cells of slack
            for Gaussians carried rigidly by a driver), and the fastest Gaussian no faster
            than ENERGY_FACTOR x the speed the force alone can give (|a| x duration), so the
            energy stays bounded by the work the force does;
  guard     SimulationUnstable (the stability guard stopped it with its message);
  rejected  another PdToolError before simulating (e.g. no Gaussian left after the opacity
            cut), one line saying what to change;
and the failures: crash (any other exception), nan, escape, energy, hang (over --timeout,
the worker process is killed), slow-guard (the guard fired only after --slow-guard s).

Axes: E 1e2-1e9 Pa; Poisson's ratio 0-0.49; force 0.1-1e6 scene units/s^2; substep factor
(x the CFL substep count) 0.02 (far too large steps) to 4 (tiny steps); geometry (plant,
flat single layer, needle, a few particles, touching the grid edge, far from the origin);
near-singular covariances (scales 1e-8, all or on one axis); opacity-0 Gaussians.
"""
from __future__ import annotations

import argparse
import itertools
import json
import multiprocessing as mp
import sys
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np

from usd_export import instance_positions

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OK = ("stable", "guard", "rejected")
FAILURES = ("crash", "nan", "escape", "energy", "hang", "slow-guard")
ENERGY_FACTOR = 5.0  # fastest Gaussian may reach this multiple of |a| x duration
GEOMETRIES = ("plant", "flat", "needle", "few", "edge", "far")
COVARIANCES = ("normal", "tiny", "flat-axis", "mixed")
OPACITIES = ("normal", "half-zero", "all-zero", "one-visible")

BASE = dict(E=1e5, nu=0.3, force=10.0, factor=1.0, geometry="plant", cov="normal", opacity="normal")


# ----------------------------------------------------------------------------- scenes
def make_scene(geometry: str, cov: str, opacity: str, seed: int = 0):
    """A small GaussianScene and its PrepareOptions keyword arguments for one case."""
    import torch

    from pd_tool.core.scene import GaussianScene, rgb_to_sh
    from pd_tool.io.synthetic import POT_TOP, make_plant

    rng = np.random.default_rng(seed)
    prep_kw: dict = {}
    if geometry in ("plant", "edge", "far"):
        s = make_plant(400, seed=seed, thin=False)
        pos, scales = s.positions.numpy().astype(np.float64), s.scales.numpy().astype(np.float64)
        prep_kw["static_below"] = POT_TOP
        if geometry == "edge":
            prep_kw["padding"] = 0.0  # the object's box is the grid's box (walls aside)
        if geometry == "far":
            pos = pos + 1.0e4  # float32 positions lose ~1e-3 of precision out here
            prep_kw["static_below"] = POT_TOP + 1.0e4
    elif geometry == "flat":  # one layer of Gaussians, zero thickness along z
        g = np.stack(np.meshgrid(np.linspace(0, 1, 20), np.linspace(0, 1, 20), indexing="ij"), -1).reshape(-1, 2)
        pos = np.concatenate([g, np.full((len(g), 1), 0.5)], 1)
        scales = np.full((len(pos), 3), 0.025)
        prep_kw["static_box"] = (-0.1, -0.1, 0.0, 0.06, 1.1, 1.0)  # one clamped edge
    elif geometry == "needle":  # a line of Gaussians along z, clamped at the bottom
        pos = np.zeros((200, 3))
        pos[:, 2] = np.linspace(0.0, 1.0, 200)
        scales = np.full((len(pos), 3), 0.005)
        prep_kw["static_below"] = 0.05
    elif geometry == "few":  # five Gaussians (outlier removal off: it would drop them all)
        pos = rng.uniform(0, 1, (5, 3))
        scales = np.full((len(pos), 3), 0.05)
        prep_kw["remove_outliers"] = False
    else:
        raise ValueError(f"unknown geometry {geometry}")
    n = len(pos)
    if cov == "tiny":
        scales = np.full_like(scales, 1e-8)
    elif cov == "flat-axis":
        scales = scales.copy()
        scales[:, 2] = 1e-8
    elif cov == "mixed":
        scales = scales.copy()
        scales[rng.random(n) < 0.1] = 1e-8
    opac = rng.uniform(0.7, 0.95, n)
    if opacity == "half-zero":
        opac[rng.random(n) < 0.5] = 0.0
    elif opacity == "all-zero":
        opac[:] = 0.0
    elif opacity == "one-visible":
        opac[:] = 0.0
        opac[0] = 0.9
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    colors = rng.uniform(0.2, 0.8, (n, 3))
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    scene = GaussianScene(positions=f32(pos), quats=f32(q), scales=f32(scales), opacities=f32(opac),
                          sh=f32(rgb_to_sh(torch.as_tensor(colors)).numpy()[:, None, :]))
    return scene, prep_kw


# ----------------------------------------------------------------------------- matrix
def _case(**kw) -> dict:
    c = dict(BASE)
    c.update(kw)
    c["name"] = ",".join(f"{k}={c[k]}" for k in ("E", "nu", "force", "factor", "geometry", "cov", "opacity")
                         if c[k] != BASE[k]) or "base"
    return c


def full_matrix() -> list[dict]:
    """Every case of the stress matrix (deduplicated, >= 200)."""
    Es = [1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9]
    nus = [0.0, 0.2, 0.3, 0.4, 0.45, 0.49]
    forces = [0.1, 1.0, 10.0, 100.0, 1e3, 1e4, 1e6]
    factors = [0.02, 0.1, 0.5, 1.0, 2.0, 4.0]
    cases = []
    cases += [_case(E=E, force=f) for E, f in itertools.product(Es, forces)]                       # 56
    cases += [_case(E=E, factor=s) for E, s in itertools.product(Es, factors)]                     # 48
    cases += [_case(nu=nu, E=E, force=f) for nu, E, f in itertools.product(nus, [1e2, 1e5, 1e9], [10.0, 1e4])]  # 36
    cases += [_case(geometry=g, force=f, E=E)
              for g, f, E in itertools.product(GEOMETRIES, [1.0, 100.0, 1e6], [1e3, 1e7])]        # 36
    cases += [_case(geometry=g, cov=c) for g, c in itertools.product(("plant", "flat", "needle", "few"), COVARIANCES)]  # 16
    cases += [_case(geometry=g, opacity=o) for g, o in itertools.product(("plant", "flat", "needle", "few"), OPACITIES)]  # 16
    cases += [_case(cov=c, force=1e6, factor=s) for c, s in itertools.product(("tiny", "mixed"), (0.1, 1.0))]
    cases += [_case(opacity="half-zero", cov="tiny", force=f) for f in (1.0, 1e6)]
    cases += [_case(nu=0.49, factor=s, E=1e7) for s in (0.1, 4.0)]
    cases += [_case(geometry=g, factor=0.02, E=1e8) for g in GEOMETRIES]
    cases += [_case(geometry=g, nu=0.49, force=f) for g, f in itertools.product(GEOMETRIES, (10.0, 1e4))]
    cases += [_case(cov=c, E=E) for c, E in itertools.product(("tiny", "flat-axis"), (1e2, 1e9))]
    seen, out = set(), []
    for c in cases:
        if c["name"] not in seen:
            seen.add(c["name"])
            out.append(c)
    return out


def quick_matrix() -> list[dict]:
    """About 20 cheap cases that still touch every axis (CI)."""
    return [
        _case(), _case(E=1e2), _case(E=1e9, factor=0.5), _case(E=1e7, force=1e4),
        _case(nu=0.0), _case(nu=0.49), _case(force=0.1), _case(force=1e4, E=1e3),
        _case(factor=0.02, E=1e7), _case(factor=4.0), _case(geometry="flat"), _case(geometry="needle", force=100.0),
        _case(geometry="few"), _case(geometry="edge"), _case(geometry="far"), _case(cov="tiny"),
        _case(cov="flat-axis", geometry="flat"), _case(cov="mixed", force=1e3), _case(opacity="half-zero"),
        _case(opacity="all-zero"), _case(opacity="one-visible", geometry="few"),
    ]


# ----------------------------------------------------------------------------- one case
def _cfl_substeps(scene, prep_kw: dict, c: dict, grid: int, cfl: float, fps: float) -> int:
    """The substep count the bake's CFL rule would pick at the first (forced) frame."""
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.sim.cfl import cfl_substeps, wave_speed

    prep = prepare_scene(scene, PrepareOptions(grid_res=grid, **prep_kw))
    c_wave = wave_speed(np.array([c["E"]]), np.array([1000.0]), c["nu"])
    boost = c["force"] * prep.transform.scale / fps
    return cfl_substeps(1.0 / fps, prep.dx, c_wave, boost, cfl)


def run_case(c: dict, *, device: str = "cpu", frames: int = 10, fps: float = 30.0, grid: int = 16,
             cfl: float = 0.5, ratio: float = 0.25, slow_guard: float = 60.0) -> dict:
    """Bake one case and classify it. Returns the case dict plus outcome, message, seconds."""
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.core.errors import PdToolError, SimulationUnstable
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.materials.presets import Material

    r = dict(c)
    t0 = time.perf_counter()
    duration = 0.1
    try:
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            scene, prep_kw = make_scene(c["geometry"], c["cov"], c["opacity"])
            q = tmp / "q.toml"
            q.write_text(f"grid_res = {grid}\ncfl_safety = {cfl}\ndriver_ratio = {ratio}\n"
                         f"fit_velocity_iters = 1\nfit_material_iters = 1\n")
            substeps = None
            if c["factor"] != 1.0:
                substeps = max(1, int(round(_cfl_substeps(scene, prep_kw, c, grid, cfl, fps) * c["factor"])))
            r["substeps"] = substeps
            res = bake(scene, tmp / "out.usd",
                       force=ForceSpec(accel=(c["force"], 0.0, 0.5 * c["force"]), at="top", radius_fraction=0.3,
                                       duration=duration),
                       material=Material(E=c["E"], nu=c["nu"], density=1000.0, damping=1.0),
                       prepare_options=PrepareOptions(**prep_kw),
                       settings=BakeSettings(seconds=(frames - 1) / fps, fps=fps, quality=q, fmt="instancer",
                                             device=device, substeps=substeps, stop_at_rest=False))
            r["substeps"] = res.substeps_per_frame
            r["drivers"] = res.drivers
            from pd_tool.prepare.preparation import PrepareOptions as _PO

            prep = prepare_scene(scene, _PO(grid_res=grid, **prep_kw))
            pos = _read_positions(tmp / "out.usd", res.frames)
            r.update(_classify(pos, prep, c["force"] * 1.118, duration, fps))
    except SimulationUnstable as e:
        r["outcome"], r["message"] = "guard", str(e)
        if time.perf_counter() - t0 > slow_guard:
            r["outcome"] = "slow-guard"
    except PdToolError as e:
        r["outcome"], r["message"] = "rejected", f"{type(e).__name__}: {e}"
    except Exception as e:  # a crash is what this matrix looks for: record it, do not stop
        r["outcome"] = "crash"
        r["message"] = f"{type(e).__name__}: {e} | {traceback.format_exc(limit=-3)!r}"
    r["seconds"] = time.perf_counter() - t0
    return r


def _read_positions(path: Path, frames: int) -> np.ndarray:
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))  # keep the stage alive while reading its prims
    # every instance by id: pinned ones sit on their own prim, written once
    return np.stack([instance_positions(stage, float(f))[1].astype(np.float64) for f in range(frames)])


def _classify(pos: np.ndarray, prep, accel: float, duration: float, fps: float) -> dict:
    """stable / nan / escape / energy from the baked positions [F, N, 3] (scene units)."""
    if not np.all(np.isfinite(pos)):
        return {"outcome": "nan", "message": f"{int((~np.isfinite(pos)).any(axis=2).sum())} non-finite positions"}
    tr = prep.transform
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.float64) * np.array(prep.domain)
    box = tr.to_scene(corners)
    slack = 2 * prep.dx / tr.scale
    lo, hi = box.min(axis=0) - slack, box.max(axis=0) + slack
    out = np.any((pos < lo) | (pos > hi), axis=2)
    speed = np.linalg.norm(np.diff(pos, axis=0), axis=2).max() * fps if len(pos) > 1 else 0.0
    bound = ENERGY_FACTOR * accel * duration
    info = {"max_speed": float(speed), "speed_bound": float(bound),
            "peak_displacement": float(np.linalg.norm(pos - pos[:1], axis=2).max())}
    if out.any():
        return {**info, "outcome": "escape", "message": f"{int(out.sum())} Gaussian-frames outside the box"}
    if speed > bound and speed > 1e-6:
        return {**info, "outcome": "energy", "message": f"fastest Gaussian {speed:.3g} > bound {bound:.3g} units/s"}
    return {**info, "outcome": "stable", "message": ""}


# ----------------------------------------------------------------------------- running
def _worker(conn, kw: dict) -> None:
    import torch

    from pd_tool.core.device import init_warp_quietly

    torch.set_num_threads(1)
    init_warp_quietly()
    run_case(_case(), **{**kw, "frames": 2})  # load the kernels before the first timed case
    conn.send("ready")
    while True:
        c = conn.recv()
        if c is None:
            return
        conn.send(run_case(c, **kw))


def run_matrix(cases: list[dict], *, timeout: float, kw: dict, log=print) -> list[dict]:
    """Run cases in a worker process; a case over `timeout` s is a hang (worker killed, restarted)."""
    ctx = mp.get_context("spawn")
    results = []
    proc = conn = None
    for i, c in enumerate(cases):
        if proc is None:
            conn, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, kw), daemon=True)
            proc.start()
            if not conn.poll(900) or conn.recv() != "ready":
                raise RuntimeError("stress worker did not start within 900 s")
        conn.send(c)
        t0 = time.perf_counter()
        if conn.poll(timeout):
            r = conn.recv()
        else:
            proc.kill()  # our own worker, by its handle
            proc.join()
            proc = None
            r = dict(c, outcome="hang", message=f"no result after {timeout:.0f} s", seconds=time.perf_counter() - t0)
        results.append(r)
        log(f"[{i + 1:3d}/{len(cases)}] {r['outcome']:9s} {r['seconds']:6.1f} s  {r['name']}"
            + (f"  | {r['message'][:150]}" if r.get("message") else ""))
    if proc is not None:
        conn.send(None)
        proc.join(10)
    return results


def summary_markdown(results: list[dict]) -> str:
    """Outcome counts per axis value, then the non-stable cases with their messages."""
    lines = ["| outcome | cases | median s | max s |", "|---|---|---|---|"]
    for o in OK + FAILURES:
        sel = [r["seconds"] for r in results if r["outcome"] == o]
        if sel:
            lines.append(f"| {o} | {len(sel)} | {np.median(sel):.1f} | {max(sel):.1f} |")
    lines += ["", "| axis | value | stable | guard | rejected | failed |", "|---|---|---|---|---|---|"]
    for axis in ("E", "nu", "force", "factor", "geometry", "cov", "opacity"):
        for v in sorted({r[axis] for r in results}, key=lambda x: (isinstance(x, str), x)):
            sel = [r for r in results if r[axis] == v]
            n = {o: sum(r["outcome"] == o for r in sel) for o in OK}
            fail = len(sel) - sum(n.values())
            lines.append(f"| {axis} | {v:g} | {n['stable']} | {n['guard']} | {n['rejected']} | {fail} |"
                         if not isinstance(v, str) else
                         f"| {axis} | {v} | {n['stable']} | {n['guard']} | {n['rejected']} | {fail} |")
    lines += ["", "| case | outcome | s | message |", "|---|---|---|---|"]
    for r in results:
        if r["outcome"] != "stable":
            lines.append(f"| {r['name']} | {r['outcome']} | {r['seconds']:.1f} | {r.get('message', '')[:160]} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--quick", action="store_true", help="the ~20-case CI subset")
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per case before it counts as a hang")
    ap.add_argument("--slow-guard", type=float, default=60.0, help="a guard stop after this many s is a failure")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--grid", type=int, default=16)
    ap.add_argument("--only", default=None, help="run only cases whose name contains this")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--markdown", type=Path)
    args = ap.parse_args()

    cases = quick_matrix() if args.quick else full_matrix()
    if args.only:
        cases = [c for c in cases if args.only in c["name"]]
    print(f"{len(cases)} cases, timeout {args.timeout:.0f} s, device {args.device}", flush=True)
    t0 = time.perf_counter()
    kw = dict(device=args.device, frames=args.frames, grid=args.grid, slow_guard=args.slow_guard)
    results = run_matrix(cases, timeout=args.timeout, kw=kw, log=lambda s: print(s, flush=True))
    wall = time.perf_counter() - t0
    counts = {o: sum(r["outcome"] == o for r in results) for o in OK + FAILURES}
    print(json.dumps({"cases": len(results), "wall_s": round(wall, 1), **counts}))
    if args.json:
        args.json.write_text(json.dumps({"device": args.device, "settings": kw, "timeout_s": args.timeout,
                                         "wall_s": wall, "counts": counts, "results": results}, indent=1, default=str))
    if args.markdown:
        args.markdown.write_text(summary_markdown(results))
    return 1 if any(counts[f] for f in FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
