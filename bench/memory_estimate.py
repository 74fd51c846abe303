"""Measured peak memory of a bake / fit against pd_tool.prepare.memory's estimate.

Each size runs in a fresh subprocess: it imports pdtool, torch, warp and usd_export, makes
the synthetic plant (and, for a fit, loads a reference video rendered beforehand), reads
its RSS (the baseline: a process that imported the same modules and holds the inputs),
resets the peak (/proc/self/clear_refs = 5), runs the bake or fit, and reads VmHWM.
measured = VmHWM - baseline; the estimate is what bake/fit check before starting.
On CUDA the GPU peak is torch.cuda.max_memory_allocated plus warp's pool high-water mark
is not visible, so only the host side is compared there.

    python bench/memory_estimate.py --kind bake --sizes 2000,20000,80000 --json mem.json
    python bench/memory_estimate.py --kind fit --sizes 1000,4000,12000 --device cpu
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BAKE_FRAMES = 4
FIT_FRAMES = 4
FIT_SIZE = 64  # px, reference frames


def _status(field: str) -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    raise RuntimeError(f"no {field} in /proc/self/status")


def child(kind: str, n: int, quality: str, device: str, workdir: str, preview: bool) -> dict:
    """Runs in the fresh subprocess; returns measured and estimated bytes."""
    import gc

    import torch
    import warp as wp

    torch.set_num_threads(1)
    wp.config.quiet = True
    import usd_export  # noqa: F401  (the bake imports it; part of the baseline)
    from pd_tool.bake.baker import BakeSettings, ForceSpec, bake
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats
    from pd_tool.prepare.memory import PREVIEW_PIXELS, estimate_bake_memory, estimate_fit_memory
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.materials.presets import Material, fit_simulation, load_preset
    from pd_tool.io.synthetic import POT_TOP, make_plant

    wd = Path(workdir)
    q = load_preset("quality", quality)
    if kind == "bake":
        scene = make_plant(n, seed=0).to(device)
    else:
        scene = load_splats(wd / "plant.ply", device=device)
        refs = [load_reference_video(wd / "video", working_size=FIT_SIZE, device=device)]
    gc.collect()
    base = _status("VmRSS")
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")  # VmHWM := VmRSS
    t = time.perf_counter()
    if kind == "bake":
        bake(scene, wd / f"bake{n}.usd", force=ForceSpec(accel=(0.0, 0.0, 1.0)), material=Material.from_preset("flower"),
             prepare_options=PrepareOptions(static_below=POT_TOP),
             settings=BakeSettings(seconds=(BAKE_FRAMES - 1) / 30, quality=quality, device=device),
             preview=wd / f"bake{n}.mp4" if preview else None)
    else:
        run_fit(scene, wd / "plant.ply", refs, wd / f"fit{n}.pdmat", prepare_options=PrepareOptions(static_below=POT_TOP),
                settings=FitSettings(quality=quality, velocity_iters=1, material_iters=1, working_long_side=FIT_SIZE,
                                     device=device))
    seconds = time.perf_counter() - t
    peak = _status("VmHWM")
    grid, _, ratio = (int(q["grid_res"]), 0.0, float(q["driver_ratio"])) if kind == "bake" else fit_simulation(q)
    opts = PrepareOptions(static_below=POT_TOP, grid_res=grid)
    prep = prepare_scene(scene, opts)
    if kind == "bake":
        est = estimate_bake_memory(n_gaussians=scene.count, n_simulated=len(prep.positions_sim),
                                   driver_ratio=ratio,
                                   grid_dims=prep.grid_dims, frames=BAKE_FRAMES,
                                   preview_pixels=PREVIEW_PIXELS if preview else 0,
                                   sh_coeffs=int(scene.sh.shape[1]), device=device)
    else:
        est = estimate_fit_memory(n_gaussians=scene.count, n_simulated=len(prep.positions_sim),
                                  driver_ratio=ratio,
                                  grid_dims=prep.grid_dims, frames=[refs[0].num_frames],
                                  image_pixels=int(refs[0].frames[0].numel() // 3), device=device)
    return {"kind": kind, "n": n, "quality": quality, "device": device, "baseline": base, "peak": peak,
            "measured": peak - base, "estimate": est.host, "ratio": est.host / (peak - base),
            "terms": est.terms, "seconds": seconds}


def spawn(kind: str, n: int, quality: str, device: str, workdir: Path, preview: bool = False) -> subprocess.Popen:
    """Start one measurement in a fresh interpreter (collect with collect())."""
    code = (f"import json, sys; sys.path.insert(0, {str(REPO / 'bench')!r}); import memory_estimate as m; "
            f"print('RESULT ' + json.dumps(m.child({kind!r}, {n}, {quality!r}, {device!r}, {str(workdir)!r}, "
            f"{preview!r})))")
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=str(REPO))
    return subprocess.Popen([sys.executable, "-c", code], cwd=workdir, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def collect(p: subprocess.Popen) -> dict:
    out, _ = p.communicate(timeout=1800)
    for line in out.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"measurement failed (exit {p.returncode}):\n{out[-3000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", choices=["bake", "fit"], default="bake")
    ap.add_argument("--sizes", default="2000,20000,80000", help="Gaussians per run, comma-separated")
    ap.add_argument("--quality", default="draft")
    ap.add_argument("--preview", action="store_true", help="bake: also write a preview video")
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--parallel", type=int, default=1, help="measurements at once (each is its own process)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: one 2000-Gaussian bake")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args()
    if a.quick:
        a.sizes = "2000"
    sizes = [int(s) for s in a.sizes.split(",")]
    from pd_tool.fit.reference import write_plant_with_video

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        dirs = {}
        for n in sizes:
            dirs[n] = Path(tmp) / f"n{n}"
            dirs[n].mkdir()
            if a.kind == "fit":
                write_plant_with_video(dirs[n], n, size=FIT_SIZE, frames=FIT_FRAMES)
        pending = list(sizes)
        while pending:
            batch, pending = pending[: a.parallel], pending[a.parallel:]
            procs = [spawn(a.kind, n, a.quality, a.device, dirs[n], a.preview) for n in batch]
            for p in procs:
                r = collect(p)
                rows.append(r)
                print(f"{r['kind']} n={r['n']:>7}: measured {r['measured'] / 2**20:8.1f} MiB, estimate "
                      f"{r['estimate'] / 2**20:8.1f} MiB ({100 * (r['ratio'] - 1):+.0f}%), {r['seconds']:.1f} s", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
