"""Throughput of `pdtool batch`: a 32-job bake sweep of the synthetic plant at 1, 2, 4 workers.

Each job is a tiny bake (600 Gaussians, --quality draft, 3 frames, instancer) so that the
numbers show the batch machinery (process start, imports, kernel loading, scheduling) as much
as the simulation. Every worker count runs in a fresh folder, through `run_batch`, the
function `pdtool batch` calls.

    python bench/batch_throughput.py --device cpu --workers 1,2,4 --json batch.json
    python bench/batch_throughput.py --device cuda --workers 1,2,4      # GPU workers: one per GPU
    python bench/batch_throughput.py --device cuda --workers 1 --gpus 1,2 --gaussians 100000 --quality default --frames 15
    python bench/batch_throughput.py --ray auto                          # on a running Ray cluster
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LOAD0 = 0.0
PRESETS = ["flower", "leafy-plant", "jelly", "rubber-cord"]
FORCES = ["0,0,1", "0,0,-1", "1,0,0", "-1,0,0", "0,1,0", "0,-1,0", "1,1,0", "-1,-1,0"]


def jobs_toml(device: str, gaussians_file: str, frames: int, quality: str = "draft") -> str:
    args = ["--scene", gaussians_file, "--preset", "{preset}", "--force", "{force}", "--quality", quality,
            "--frames", str(frames), "--format", "instancer", "--device", device, "out/{name}.usd"]
    return ("[[job]]\nname = \"poke\"\ncommand = \"bake\"\nargs = " + json.dumps(args) + "\n"
            "[job.sweep]\npreset = " + json.dumps(PRESETS) + "\nforce = " + json.dumps(FORCES) + "\n")


def cpu_name() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def _gpu_names() -> list[str]:
    import torch

    return [torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count())]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--workers", default="1,2,4", help="comma-separated local worker counts")
    ap.add_argument("--ray", default=None, help="Ray address instead of the local pool (one run)")
    ap.add_argument("--gaussians", type=int, default=600)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--quality", default="draft", help="the bakes' --quality (default: the converged default's cheaper draft)")
    ap.add_argument("--gpus", default=None, help="--device cuda: comma-separated GPU counts for the local pool "
                    "(one GPU worker each; default: every visible GPU)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch threads per CPU job (0: pdtool's default, cores // workers)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 300 Gaussians, 2 frames, 1 and 2 workers")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    a = ap.parse_args()
    if a.quick:
        a.gaussians, a.frames, a.workers = 300, 2, "1,2"

    global LOAD0
    LOAD0 = os.getloadavg()[0]
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from cli import batch_parse, batch_run
    from pd_tool.batch import CommandLines, LocalBackend, RayBackend, load_jobs, run_batch
    from pd_tool.io import save_splats
    from pd_tool.io.synthetic import make_plant

    root = a.keep or Path(tempfile.mkdtemp(prefix="pdtool-batch-bench-"))
    root.mkdir(parents=True, exist_ok=True)
    save_splats(make_plant(a.gaussians, seed=0), root / "plant.ply")
    gpus = [None] if a.gpus is None else [int(g) for g in a.gpus.split(",")]
    runs = [("ray", 0, None)] if a.ray else [("local", int(w), g) for w in a.workers.split(",") for g in gpus]
    rows = []
    for kind, w, g in runs:
        d = root / ("ray" if kind == "ray" else f"w{w}" + ("" if g is None else f"g{g}"))
        d.mkdir(exist_ok=True)
        (d / "jobs.toml").write_text(jobs_toml(a.device, "../plant.ply", a.frames, a.quality))
        jobs = load_jobs(d / "jobs.toml")
        backend = RayBackend(a.ray) if kind == "ray" else LocalBackend(w, gpus=g, threads=a.threads or None)
        t0 = time.perf_counter()
        res = run_batch(jobs, CommandLines(batch_parse, batch_run), workers=w or None, backend=backend,
                        show_progress=False, echo=lambda s: None)
        wall = time.perf_counter() - t0
        secs = sorted(r.seconds for r in res.jobs)
        # Each worker's first job pays the imports and kernel loading; the rest is the
        # steady state a long sweep runs at.
        first: dict[str, float] = {}
        for r in res.jobs:
            first.setdefault(r.worker or "?", r.seconds)
        warm = max(first.values())
        steady = (len(jobs) - len(first)) / max(wall - warm, 1e-9) * 60
        row = {"backend": res.backend, "workers": w, "jobs": len(jobs), "ok": res.counts()["ok"], "wall_s": round(wall, 2),
               "jobs_per_min": round(60 * len(jobs) / wall, 1), "job_s_median": round(statistics.median(secs), 3),
               "job_s_max": round(secs[-1], 2), "workers_used": len(first), "warmup_s": round(warm, 1),
               "steady_jobs_per_min": round(steady, 1)}
        row["load_avg_after"] = round(os.getloadavg()[0], 1)
        rows.append(row)
        print(f"{row['backend']:<40} {row['ok']}/{row['jobs']} ok  wall {row['wall_s']:7.1f} s  "
              f"{row['jobs_per_min']:6.1f} jobs/min  job median {row['job_s_median']:.2f} s, "
              f"warm-up {row['warmup_s']:.1f} s (imports + kernel load), after it {row['steady_jobs_per_min']:.1f} "
              f"jobs/min, load avg {row['load_avg_after']}", flush=True)
    info = {"cpu": cpu_name(), "cores": len(os.sched_getaffinity(0)), "device": a.device,
            "gpu": _gpu_names() if a.device == "cuda" else None, "quality": a.quality,
            "gaussians": a.gaussians, "frames": a.frames, "threads_per_job": a.threads,
            "load_avg_before": LOAD0, "python": platform.python_version(), "runs": rows}
    if a.json:
        a.json.write_text(json.dumps(info, indent=2))
    print(json.dumps({k: v for k, v in info.items() if k != "runs"}))


if __name__ == "__main__":
    main()
