"""Speed of pd_tool.render: forward and forward+backward on random splat scenes.

    python bench/render_speed.py --device cpu --json render_cpu.json
    python bench/render_speed.py --device cuda --json render_cuda.json

Scenes (pd_tool.io.synthetic.make_splat_ball): N Gaussians uniform in a ball of radius 1
(scene units), scales log-uniform in [0.005, 0.04], opacities uniform 0.1-0.9, SH degree 3
(16 coefficients); seen from 3 units away with a 50 degree vertical field of view. Warm-up
(warp compile, caches) happens outside the clock and the device is synchronised inside it. With --device cuda the CPU and CUDA images of
the small case are compared too (max abs difference printed and stored).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import subprocess
import sys
import time

import torch

from pd_tool.core.cameras import Camera, look_at
from pd_tool.io.synthetic import make_splat_ball
from pd_tool.render import render

CASES = [  # (name, width, height, n_gaussians)
    ("256x256_20k", 256, 256, 20_000),
    ("1024x576_300k", 1024, 576, 300_000),
]


def make_scene(n: int, device: str) -> list:
    """The case's splats as render()'s first five arguments (means, quats, scales, opacities, sh)."""
    s = make_splat_ball(n, device=device)
    return [s.positions, s.quats, s.scales, s.opacities, s.sh]


def make_camera(width: int, height: int) -> Camera:
    fy = 0.5 * height / math.tan(math.radians(25.0))
    return Camera(width, height, fy, fy, width / 2, height / 2, look_at([2.1, -2.1, 0.6], [0, 0, 0], [0, 0, 1]))


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_case(width: int, height: int, n: int, device: str, reps: int, backward: bool) -> tuple[float, float]:
    """(wall seconds, process CPU seconds) per repetition; CPU time is the fairer number on a
    shared machine (it includes torch's worker threads)."""
    cam = make_camera(width, height)
    scene = make_scene(n, device)
    if backward:
        scene = [t.requires_grad_() for t in scene]

    def step():
        out = render(*scene, cam, background=(1.0, 1.0, 1.0))
        if backward:
            out.rgb.sum().backward()
        return out

    step()  # warp compile + warm-up
    sync(device)
    t0 = time.perf_counter()
    c0 = time.process_time()
    for _ in range(reps):
        step()
    sync(device)
    return (time.perf_counter() - t0) / reps, (time.process_time() - c0) / reps


def cpu_model() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return platform.processor() or "unknown"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument("--quick", action="store_true", help="the 256x256 case, one repetition")
    p.add_argument("--json", dest="json_path", default=None, help="write results to this JSON file")
    p.add_argument("--reps", type=int, default=None,
                   help="timed repetitions (default: cuda 20; cpu 3, and 1 for 300k Gaussians)")
    p.add_argument("--cases", default=",".join(c[0] for c in CASES), help="comma-separated case names")
    a = p.parse_args(argv)
    if a.quick:
        a.cases, a.reps = CASES[0][0], 1
    if a.device == "cuda" and not torch.cuda.is_available():
        print("cuda requested but torch.cuda.is_available() is False", file=sys.stderr)
        return 2
    hw = torch.cuda.get_device_name() if a.device == "cuda" else cpu_model()
    result = {"device": a.device, "hardware": hw, "torch_threads": torch.get_num_threads(), "cases": []}
    wanted = set(a.cases.split(","))
    for name, w, h, n in CASES:
        if name not in wanted:
            continue
        r = a.reps or (20 if a.device == "cuda" else (3 if n <= 50_000 else 1))
        fwd, fwd_cpu = time_case(w, h, n, a.device, r, backward=False)
        fb, fb_cpu = time_case(w, h, n, a.device, r, backward=True)
        row = {"case": name, "width": w, "height": h, "gaussians": n, "reps": r,
               "forward_ms": fwd * 1e3, "forward_backward_ms": fb * 1e3,
               "forward_cpu_time_ms": fwd_cpu * 1e3, "forward_backward_cpu_time_ms": fb_cpu * 1e3}
        result["cases"].append(row)
        print(f"{name:>16}: forward {fwd * 1e3:9.2f} ms   forward+backward {fb * 1e3:9.2f} ms   "
              f"(process CPU time {fwd_cpu * 1e3:.0f} / {fb_cpu * 1e3:.0f} ms; {hw}, {a.device})", flush=True)
    if a.device == "cuda":
        name, w, h, n = CASES[0]
        cam = make_camera(w, h)
        img_cpu = render(*make_scene(n, "cpu"), cam).rgb
        img_gpu = render(*make_scene(n, "cuda"), cam).rgb.cpu()
        diff = float((img_cpu - img_gpu).abs().max())
        result["cpu_vs_cuda_max_abs_diff"] = diff
        print(f"CPU vs CUDA image ({name}): max abs diff {diff:.3g}")
    if a.json_path:
        with open(a.json_path, "w", encoding="utf-8") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
