"""Benchmark UsdBakeWriter: time, peak memory and file size per frame.

Each configuration runs in its own subprocess so that its peak RSS
(ru_maxrss) is its own. The baseline is the RSS after imports and the
synthetic data (one rest frame plus per-frame offsets) exist, just before the
writer opens; "writer peak" is peak RSS minus that baseline.

    python bench/usd_write.py --device cpu --json usd_write.json
    python bench/usd_write.py --points 300000 --frames 10,30,90 --fmt both --flush-mb 64,0

The write time includes close(), which by default validates (all registered
UsdValidation validators + our checks at the end samples), as a bake does.
--threaded 0,1 --sim-ms 30 compares writing in the caller's thread with the
background writer while a 30 ms GIL-releasing wait per frame stands in for
the GPU simulation (the wall time is what a bake would see).

--floor adds what usd-core writes at its fastest on the same data: each frame's host
arrays (orientations already half floats) through Vt's FromNumpy, SetTimeSample on a bare
Sdf layer and Save; no checks, extents, colour points or validation. MB/s beside the
writer's.

--flush-mb 0 means "never flush before close" (the whole bake in memory): the
comparison that shows what streaming buys.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _rss_peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def run_one(points: int, frames: int, fmt: str, flush_mb: float, device: str,
            validate: bool, out_dir: str, close_validate: bool = True,
            threaded: bool = False, sim_ms: float = 0.0) -> dict:
    import torch

    from usd_export import UsdBakeWriter, validate_usd

    gen = torch.Generator(device=device).manual_seed(0)
    x0 = torch.randn(points, 3, generator=gen, device=device)
    q0 = torch.nn.functional.normalize(torch.randn(points, 4, generator=gen, device=device), dim=1)
    s0 = torch.rand(points, 3, generator=gen, device=device) * 0.01 + 0.001
    sh = torch.randn(points, 16, 3, generator=gen, device=device) * 0.3
    rgb = torch.rand(points, 3, generator=gen, device=device)
    opac = torch.rand(points, generator=gen, device=device)
    vel = torch.randn(points, 3, generator=gen, device=device) * 0.01
    spin = torch.randn(points, 4, generator=gen, device=device) * 0.01
    path = Path(out_dir) / f"bench_{points}_{frames}_{fmt}.usd"
    baseline = _rss_peak_mb()

    t0 = time.perf_counter()
    flush = int(flush_mb * 2**20) if flush_mb > 0 else 1 << 62
    w = UsdBakeWriter(path, n_points=points, fps=30, fmt=fmt, colors=rgb.cpu().numpy(),
                      opacities=opac.cpu().numpy(), sh=sh.cpu().numpy(), flush_bytes=flush,
                      threaded=threaded)
    t_open = time.perf_counter() - t0
    t_frames = 0.0
    t_loop = time.perf_counter()
    for f in range(frames):
        if sim_ms:
            # stand-in for the simulation's GPU time: a wait that releases the GIL,
            # like a CUDA synchronize
            time.sleep(sim_ms / 1e3)
        pos = (x0 + f * vel).cpu().numpy()  # what the bake hands over: host arrays
        # every array changes every frame, as in a real bake (the crate file would
        # otherwise store a repeated array once and flatter the size per frame)
        q = torch.nn.functional.normalize(q0 + f * spin, dim=1).cpu().numpy()
        s = (s0 * (1 + 0.01 * f)).cpu().numpy()
        t1 = time.perf_counter()
        w.write_frame(f, pos, q, s)
        t_frames += time.perf_counter() - t1
    t1 = time.perf_counter()
    w.close(validate=close_validate)  # default bake path: validators + end-sample checks
    t_close = time.perf_counter() - t1
    t_wall = time.perf_counter() - t_loop  # frames loop (with sim stand-in) + close
    peak = _rss_peak_mb()
    t_validate = None
    if validate:
        t1 = time.perf_counter()
        validate_usd(path)
        t_validate = time.perf_counter() - t1
    size = path.stat().st_size
    path.unlink()
    return {
        "points": points, "frames": frames, "fmt": fmt, "flush_mb": flush_mb, "device": device,
        "threaded": threaded, "sim_ms": sim_ms, "wall_s": t_wall,
        "write_s": t_open + t_frames + t_close, "per_frame_ms": 1e3 * t_frames / frames,
        "close_s": t_close, "close_validates": close_validate, "full_validate_s": t_validate,
        "baseline_rss_mb": baseline, "peak_rss_mb": peak, "writer_peak_mb": peak - baseline,
        "file_mb": size / 2**20, "mb_per_frame": size / 2**20 / frames,
        "bytes_per_point_frame": size / (points * frames),
    }


def usd_core_floor(points: int, frames: int, out_dir: str, seed: int = 0) -> dict:
    """Seconds and MB/s of usd-core's own floor on one instancer's positions, quath
    orientations and scales per frame (every array changes every frame, as in a bake)."""
    import numpy as np
    from pxr import Sdf, Vt

    rng = np.random.default_rng(seed)
    x0 = rng.normal(size=(points, 3)).astype(np.float32)
    q0 = rng.normal(size=(points, 4)).astype(np.float32)
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    s0 = (rng.random((points, 3)) * 0.01 + 0.001).astype(np.float32)
    vel = (rng.normal(size=(points, 3)) * 0.01).astype(np.float32)
    host = [(x0 + f * vel, q0.astype(np.float16), s0 * np.float32(1 + 0.01 * f)) for f in range(frames)]
    path = Path(out_dir) / f"floor_{points}_{frames}.usdc"
    layer = Sdf.Layer.CreateNew(str(path))
    prim = Sdf.PrimSpec(layer, "Instancer", Sdf.SpecifierDef, "PointInstancer")
    attrs = [Sdf.AttributeSpec(prim, name, t).path for name, t in
             (("positions", Sdf.ValueTypeNames.Point3fArray), ("orientations", Sdf.ValueTypeNames.QuathArray),
              ("scales", Sdf.ValueTypeNames.Float3Array))]
    kinds = (Vt.Vec3fArray, Vt.QuathArray, Vt.Vec3fArray)
    t0 = time.perf_counter()
    for f, arrays in enumerate(host):
        for a, kind, v in zip(attrs, kinds, arrays):
            layer.SetTimeSample(a, f, kind.FromNumpy(v))
    layer.Save()
    seconds = time.perf_counter() - t0
    size = path.stat().st_size
    del layer
    path.unlink()
    return {"points": points, "frames": frames, "seconds": seconds, "file_mb": size / 2**20,
            "mb_per_s": size / 2**20 / seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--points", default="300000")
    ap.add_argument("--frames", default="30")
    ap.add_argument("--fmt", default="instancer,splat,both")
    ap.add_argument("--flush-mb", default="64")
    ap.add_argument("--validate", action="store_true",
                    help="also time a full validate_usd (every sample) after close")
    ap.add_argument("--threaded", default="0",
                    help="0, 1 or 0,1: UsdBakeWriter(threaded=...)")
    ap.add_argument("--sim-ms", type=float, default=0.0,
                    help="per-frame GIL-releasing wait standing in for GPU simulation time")
    ap.add_argument("--no-close-validate", action="store_true",
                    help="close(validate=False): time the write alone")
    ap.add_argument("--repeat", type=int, default=1,
                    help="run each configuration R times, keep the fastest (shared CPUs)")
    ap.add_argument("--dir", default=None, help="where to write (default: a temp dir)")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 20,000 points, 5 frames, instancer only")
    ap.add_argument("--floor", action="store_true", help="also time usd-core's floor on the same data (above)")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--_one", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.quick:
        a.points, a.frames, a.fmt = "20000", "5", "instancer"
    if a._one:  # child: one configuration, result as JSON on stdout
        p, f, fmt, fl, th = a._one.split(":")
        res = run_one(int(p), int(f), fmt, float(fl), a.device, a.validate, a.dir,
                      close_validate=not a.no_close_validate, threaded=th == "1", sim_ms=a.sim_ms)
        print("RESULT" + json.dumps(res))
        return
    results = []
    with tempfile.TemporaryDirectory(dir=a.dir) as d:
        for p in a.points.split(","):
            for f in a.frames.split(","):
                for fmt in a.fmt.split(","):
                    for fl, th in [(x, y) for x in a.flush_mb.split(",") for y in a.threaded.split(",")]:
                        cmd = [sys.executable, __file__, "--device", a.device, "--dir", d,
                               "--sim-ms", str(a.sim_ms),
                               "--_one", f"{p}:{f}:{fmt}:{fl}:{th}"] + (["--validate"] if a.validate else [])
                        cmd += ["--no-close-validate"] if a.no_close_validate else []
                        runs = []
                        for _ in range(a.repeat):
                            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
                            runs.append(json.loads(next(l for l in out.splitlines()
                                                        if l.startswith("RESULT"))[6:]))
                        r = min(runs, key=lambda x: x["write_s"])
                        r["repeats"] = a.repeat
                        results.append(r)
                        print(f"N={r['points']} frames={r['frames']} fmt={r['fmt']} flush={fl}MB "
                              f"threaded={th} sim={a.sim_ms:g}ms: wall {r['wall_s']:.2f}s, "
                              f"write {r['write_s']:.2f}s ({r['per_frame_ms']:.0f} ms/frame, "
                              f"close {r['close_s']:.2f}s)"
                              + (f", full validate {r['full_validate_s']:.2f}s" if r["full_validate_s"] is not None else "")
                              + f", writer peak +{r['writer_peak_mb']:.0f} MB "
                              f"(RSS {r['peak_rss_mb']:.0f} MB), file {r['file_mb']:.1f} MB "
                              f"= {r['mb_per_frame']:.2f} MB/frame", flush=True)
        floors = []
        for p in a.points.split(",") if a.floor else []:
            for f in a.frames.split(","):
                fl = min((usd_core_floor(int(p), int(f), d) for _ in range(a.repeat)), key=lambda x: x["seconds"])
                floors.append(fl)
                print(f"usd-core floor N={p} frames={f}: {fl['seconds']:.2f}s, file {fl['file_mb']:.1f} MB = "
                      f"{fl['mb_per_s']:.0f} MB/s", flush=True)
    for r in results:  # threaded, the caller's write_s leaves out what the thread does behind the waits
        busy = r["wall_s"] - r["frames"] * r["sim_ms"] / 1e3 if r["threaded"] else r["write_s"]
        r["mb_per_s"] = r["file_mb"] / max(busy, 1e-9)
    if a.json:
        Path(a.json).write_text(json.dumps({"host": os.uname().nodename, "results": results, "usd_core_floor": floors},
                                           indent=1))


if __name__ == "__main__":
    main()
