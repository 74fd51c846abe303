"""Speed of the fitting building blocks: frame loss (L1 + D-SSIM) and the two fields.

    python bench/fit_parts_speed.py --device cpu --json fit_parts_cpu.json
    python bench/fit_parts_speed.py --device cuda --json fit_parts_cuda.json

Cases (float32, forward + backward, timed after a warm-up, device synchronised):
- frame_loss on one [H, W, 3] frame with a mask, at 256x256 and 576x1024 (the authors'
  working resolution), 11x11 Gaussian SSIM window;
- MaterialField (resolution 8) and VelocityField (resolution 24) at N query points
  (5k: a typical driver count; 100k: every Gaussian of a large scene), 16 channels,
  hidden width 64, plus the TV term.
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pd_tool.fit.fields import MaterialField, VelocityField  # noqa: E402
from pd_tool.fit.losses import frame_loss  # noqa: E402


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _time(fn, device: str, reps: int) -> float:
    fn()  # warm-up: allocator, kernels
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(reps):
        fn()
    _sync(device)
    return (time.perf_counter() - t0) / reps


def bench_loss(device: str, h: int, w: int, reps: int) -> dict:
    g = torch.Generator(device="cpu").manual_seed(0)
    target = torch.rand(h, w, 3, generator=g).to(device)
    pred = (target + 0.05 * torch.randn(h, w, 3, generator=g).to(device)).clamp(0, 1).requires_grad_(True)
    mask = (torch.rand(h, w, generator=g) > 0.3).float().to(device)

    def fwd():
        with torch.no_grad():
            frame_loss(pred, target, mask)

    def fwd_bwd():
        pred.grad = None
        frame_loss(pred, target, mask).backward()

    return {"case": f"frame_loss {w}x{h}", "forward_ms": 1e3 * _time(fwd, device, reps),
            "forward_backward_ms": 1e3 * _time(fwd_bwd, device, reps)}


def bench_field(device: str, kind: str, n: int, reps: int) -> dict:
    torch.manual_seed(0)
    field = (MaterialField(8) if kind == "material" else VelocityField(24)).to(device)
    x = torch.rand(n, 3, device=device)

    def fwd():
        with torch.no_grad():
            field(x)

    def fwd_bwd():
        field.zero_grad(set_to_none=True)
        (field(x).square().sum() + 1e-4 * field.tv()).backward()

    return {"case": f"{kind} field N={n}", "forward_ms": 1e3 * _time(fwd, device, reps),
            "forward_backward_ms": 1e3 * _time(fwd_bwd, device, reps)}


def hardware(device: str) -> str:
    if device == "cuda":
        return torch.cuda.get_device_name()
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=False).stdout
        name = next((ln.split(":", 1)[1].strip() for ln in out.splitlines() if ln.startswith("Model name")), "")
    except OSError:
        name = ""
    return f"{name or platform.processor()} ({torch.get_num_threads()} torch threads)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--reps", type=int, default=None, help="timed repetitions (default 5 cpu, 50 cuda)")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("CUDA not available in this torch build; run with --device cpu")
    reps = args.reps or (50 if args.device == "cuda" else 5)
    rows = [bench_loss(args.device, 256, 256, reps), bench_loss(args.device, 576, 1024, reps)]
    for kind in ("material", "velocity"):
        for n in (5_000, 100_000):
            rows.append(bench_field(args.device, kind, n, reps))
    hw = hardware(args.device)
    print(f"device: {args.device}, {hw}, torch {torch.__version__}, reps {reps}")
    print(f"{'case':32s} {'fwd ms':>10s} {'fwd+bwd ms':>12s}")
    for r in rows:
        print(f"{r['case']:32s} {r['forward_ms']:10.2f} {r['forward_backward_ms']:12.2f}")
    if args.json:
        args.json.write_text(json.dumps({"device": args.device, "hardware": hw, "torch": torch.__version__,
                                         "reps": reps, "results": rows}, indent=2))


if __name__ == "__main__":
    main()
