"""Work that pdtool skips, timed on and off, on the synthetic plant and a real capture.

    python bench/skips.py --device cpu --json skips.json
    python bench/skips.py --device cuda --json skips_gpu.json    # adds CUDA graphs on/off

Skips (each "off" is the plain alternative, same scene, force and material):
  box        grid over the object's box (+ padding) only   vs a cube of the longest side
             at the same dx (how a [0,1]^3 normalised grid, as in PhysDreamer's code, covers it)
  static     static parts as Dirichlet cells               vs simulated as moving particles,
             given 100x E so that they stay roughly put (the CFL step shrinks 10x)
  drivers    driving particles (quality's driver_ratio)    vs every Gaussian a particle
  cfl        CFL substeps                                  vs a fixed 768 per frame (PhysDreamer)
  rest       stop once at rest, hold the remaining frames  vs simulate every frame
  tape       MPMSolver, no tape (bake)                     vs DiffSim forward with autograd on
  graphs     CUDA graph per frame                          vs plain launches (CUDA only)
box, static, tape and graphs time the simulator alone (MPMSolver.step_frame over the
frames); drivers, cfl and rest time the whole `pd_tool.bake.baker.bake` call. Times: CPU seconds
of this process (robust on a shared machine with --threads 1) and wall seconds.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


class Clock:
    """CPU and wall seconds of a block (CUDA synchronised at both ends)."""

    def __init__(self, device: str) -> None:
        self.device = device

    def __enter__(self):
        self._sync()
        self.c0, self.w0 = time.process_time(), time.perf_counter()
        return self

    def __exit__(self, *exc):
        self._sync()
        self.cpu, self.wall = time.process_time() - self.c0, time.perf_counter() - self.w0

    def _sync(self) -> None:
        if self.device == "cuda":
            import warp as wp

            wp.synchronize()


def scenes(args) -> dict:
    """name -> (scene, PrepareOptions kwargs, material preset, force accel, force interaction)."""
    from pd_tool.io import load_splats
    from pd_tool.io.synthetic import POT_TOP, make_plant

    out = {"plant": (make_plant(args.gaussians, seed=0, device=args.device), {"static_below": POT_TOP},
                     "flower", (20.0, 0.0, 0.0), "poke")}
    donut = SHARED / "donut_fused.ply"
    if donut.is_file() and not args.no_donut:
        out["donut_fused"] = (load_splats(donut, device=args.device), {"static_below": 0.005}, "jelly",
                              (0.0, 0.0, -3.0), "poke")
    return out


def timed_bake(spec, args, folder: Path, **settings) -> tuple[Clock, object]:
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import Material

    scene, prep_kw, mat, accel, inter = spec
    s = dict(seconds=args.seconds, quality=args.quality, fmt="instancer", device=args.device, stop_at_rest=False)
    s.update(settings)
    with Clock(args.device) as clk:
        res = bake(scene, folder / "skip.usd", force=ForceSpec.from_interaction(inter, accel),
                   material=Material.from_preset(mat), prepare_options=PrepareOptions(**prep_kw),
                   settings=BakeSettings(**s))
    return clk, res


def sim_setup(spec, args):
    """Prepared scene, drivers and the bake's SimConfig pieces for simulator-only timings."""
    import torch

    from pd_tool.bake.baker import ForceSpec, force_mask
    from pd_tool.drivers import build_drivers
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.materials.presets import Material, load_preset

    scene, prep_kw, mat_name, accel, inter = spec
    q = load_preset("quality", args.quality)
    mat = Material.from_preset(mat_name)
    prep = prepare_scene(scene, PrepareOptions(grid_res=int(q["grid_res"]), density_kg_m3=mat.density, **prep_kw))
    d = build_drivers(torch.as_tensor(prep.positions_sim, dtype=torch.float32),
                      torch.as_tensor(prep.volumes, dtype=torch.float32), torch.as_tensor(prep.masses, dtype=torch.float32),
                      torch.as_tensor(prep.static), prep.dx, ratio=float(q["driver_ratio"]), seed=0)
    x = d.positions.double().cpu().numpy()
    static = d.static.cpu().numpy().astype(bool)
    force = ForceSpec.from_interaction(inter, accel)
    mask = force_mask(prep, x, static, force)
    return dict(prep=prep, x=x, vol=d.volume.cpu().numpy(), mass=d.mass.cpu().numpy(), static=static, mat=mat,
                q=q, mask=mask, accel=prep.transform.vector_to_sim(np.asarray(force.accel)), force=force)


def time_solver(st: dict, args, *, domain=None, shift=None, E_scale_static: float | None = None,
                cuda_graph: bool | None = None) -> tuple[Clock, int, tuple]:
    """Time MPMSolver.step_frame over args.seconds of frames with the bake's settings."""
    from pd_tool.sim import MPMSolver, SimConfig

    prep, mat = st["prep"], st["mat"]
    dom = tuple(domain or prep.domain)
    x = st["x"] + (np.zeros(3) if shift is None else shift)
    static = st["static"].copy()
    E = np.full(len(x), mat.E)
    if E_scale_static is not None:
        E[static] *= E_scale_static
        static[:] = False
    cfg = SimConfig(grid_res=int(round(max(dom) / prep.dx)), domain=dom, nu=mat.nu, gravity=(0.0, 0.0, 0.0),
                    damping=mat.damping, cfl_safety=float(st["q"]["cfl_safety"]))
    sim = MPMSolver(x, st["vol"], st["mass"], E, static, cfg, device=args.device,
                    **({} if cuda_graph is None else {"cuda_graph": cuda_graph}))
    sim.add_force(st["mask"], st["accel"], st["force"].start, st["force"].start + st["force"].duration)
    frames = int(round(args.seconds * 30))
    sim.step_frame(1 / 30)  # first frame: kernel load / graph capture outside the timing
    with Clock(args.device) as clk:
        for _ in range(frames - 1):
            n = sim.step_frame(1 / 30)
    return clk, n, tuple(sim.geo.cells)


def time_tape(st: dict, args) -> tuple[Clock, int]:
    """DiffSim forward over the same frames with autograd recording (E requires grad)."""
    import torch

    from pd_tool.sim import DiffSim, SimConfig, initial_state, simulate_frames
    from pd_tool.sim.solver import Force

    prep, mat = st["prep"], st["mat"]
    cfg = SimConfig(grid_res=max(prep.grid_dims), domain=tuple(prep.domain), nu=mat.nu, gravity=(0.0, 0.0, 0.0),
                    damping=mat.damping, cfl_safety=float(st["q"]["cfl_safety"]))
    dev = args.device
    dsim = DiffSim(st["vol"], st["mass"], st["static"], cfg, device=dev)
    x0 = torch.as_tensor(st["x"], dtype=torch.float32, device=dev)
    E = torch.full((len(x0),), mat.E, dtype=torch.float32, device=dev, requires_grad=True)
    f = Force(st["mask"], tuple(st["accel"]), st["force"].start, st["force"].start + st["force"].duration)
    # the substeps the bake settled on for the same frames (from the no-tape run)
    frames = int(round(args.seconds * 30))
    simulate_frames(dsim, initial_state(x0), E, 1 / 30, st["substeps"], 1, forces=[f])  # load kernels
    with Clock(dev) as clk:
        states = simulate_frames(dsim, initial_state(x0), E, 1 / 30, st["substeps"], frames - 1, forces=[f])
        states[-1][0].sum().item()
    return clk, st["substeps"]


def row(skip: str, scene: str, on: Clock, off: Clock, note: str) -> dict:
    r = {"skip": skip, "scene": scene, "on_cpu_s": on.cpu, "off_cpu_s": off.cpu, "on_wall_s": on.wall,
         "off_wall_s": off.wall, "saving_x_cpu": off.cpu / max(on.cpu, 1e-9),
         "saving_x_wall": off.wall / max(on.wall, 1e-9), "note": note}
    print(f"{skip:8s} {scene:12s} on {on.cpu:8.2f} s  off {off.cpu:8.2f} s  x{r['saving_x_cpu']:.2f} (cpu) "
          f"x{r['saving_x_wall']:.2f} (wall)  {note}", flush=True)
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--seconds", type=float, default=1.0, help="animation length for most skips")
    ap.add_argument("--rest-seconds", type=float, default=5.0, help="animation length for the at-rest skip")
    ap.add_argument("--fixed-seconds", type=float, default=0.5, help="animation length for the fixed-768 run")
    ap.add_argument("--quality", default="default")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--only", default=None, help="comma list of skips to run")
    ap.add_argument("--no-donut", action="store_true")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 1500 Gaussians, short animations, no donut")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.seconds, args.rest_seconds, args.fixed_seconds = 1500, 0.3, 1.0, 0.2
        args.no_donut = True

    import torch

    from pd_tool.core.device import init_warp_quietly

    torch.set_num_threads(args.threads)
    init_warp_quietly()
    only = set(args.only.split(",")) if args.only else None
    want = lambda k: only is None or k in only  # noqa: E731
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, spec in scenes(args).items():
            timed_bake(spec, args, tmp, seconds=0.1)  # warm-up
            if want("drivers"):
                on, r_on = timed_bake(spec, args, tmp)
                off, r_off = timed_bake(spec, args, tmp, driver_ratio=1.0)
                rows.append(row("drivers", name, on, off, f"{r_on.drivers} drivers vs {r_off.drivers} particles, "
                                f"{args.seconds} s bake"))
            if want("cfl"):
                on, r_on = timed_bake(spec, args, tmp, seconds=args.fixed_seconds)
                off, _ = timed_bake(spec, args, tmp, seconds=args.fixed_seconds, substeps=768)
                rows.append(row("cfl", name, on, off, f"{r_on.substeps_per_frame} CFL substeps/frame vs 768, "
                                f"{args.fixed_seconds} s bake"))
            if want("rest"):
                on, r_on = timed_bake(spec, args, tmp, seconds=args.rest_seconds, stop_at_rest=True)
                off, r_off = timed_bake(spec, args, tmp, seconds=args.rest_seconds, stop_at_rest=False)
                rows.append(row("rest", name, on, off, f"{r_on.simulated_frames} of {r_off.simulated_frames} frames "
                                f"simulated, {args.rest_seconds} s bake"))
            if not any(want(k) for k in ("box", "static", "tape", "graphs")):
                continue
            st = sim_setup(spec, args)
            on, n_on, cells_on = time_solver(st, args)
            st["substeps"] = n_on
            if want("box"):
                prep = st["prep"]
                side = max(prep.domain)
                shift = (np.full(3, side) - np.asarray(prep.domain)) / 2
                off, _, cells_off = time_solver(st, args, domain=(side, side, side), shift=shift)
                rows.append(row("box", name, on, off, f"grid {cells_on} vs {cells_off} cells, {n_on} substeps/frame"))
            if want("static") and st["static"].any():
                off, n_off, _ = time_solver(st, args, E_scale_static=100.0)
                rows.append(row("static", name, on, off, f"{int(st['static'].sum())} static particles; "
                                f"{n_on} vs {n_off} substeps/frame"))
            if want("tape"):
                off, _ = time_tape(st, args)
                rows.append(row("tape", name, on, off, f"MPMSolver vs DiffSim with autograd, {n_on} substeps/frame"))
            if want("graphs") and args.device == "cuda":
                off, _, _ = time_solver(st, args, cuda_graph=False)
                rows.append(row("graphs", name, on, off, "CUDA graph per frame vs plain launches"))
    out = {"device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
           "cpu": _cpu_name(), "threads": args.threads, "quality": args.quality, "rows": rows}
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


def _cpu_name() -> str:
    import subprocess

    for line in subprocess.run(["lscpu"], capture_output=True, text=True).stdout.splitlines():
        if line.startswith("Model name"):
            return line.split(":", 1)[1].strip()
    return "unknown CPU"


if __name__ == "__main__":
    main()
