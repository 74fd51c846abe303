"""How well `pdtool fit` undoes a handheld camera's shake, on the real captures.

Each case films a capture (udon, donut, tree) turning slowly in front of a textured room
(a multi-scale random texture, the clutter a phone sees), then shakes the whole picture
by a known similarity per frame, as a hand does: a shift of up to `--shift` of the long
side, a zoom of up to `--zoom` and a roll of up to `--roll` degrees, plus pixel noise and
8-bit rounding. `pd_tool.video.clip.stabilise` measures the shake against frame 0
outside the object's footprint, as `pdtool fit` does, and warps the frames back. Reported per capture over the cases' frames:

- the motion error: the largest distance between where the measured and the true shake
  put a corner of the frame, % of the long side (median, 95th percentile, worst);
- the frames' error after stabilising, against the same frames filmed without shake, mean
  absolute grey difference over the pixels the shaken frame saw, next to the shaken
  frames' own error (what the fit would compare without stabilising).

    python bench/stabilise_accuracy.py --device cpu                 # 3 captures x 6 cases x 8 frames
    python bench/stabilise_accuracy.py --scenes udon --cases 2 --size 160 --json out.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CAPTURES = {"udon": ("udon.ply", "-y"), "donut": ("donut_fused.ply", "-y"), "tree": ("tree_100k.splat", "-y")}
TURN_DEG = 1.5  # the object's own turn a frame (azimuth), the motion the shake must not be confused with
MARGIN = 2.2  # the object spans about 1 / MARGIN of the frame: the room shows around it
NOISE = 2.0 / 255.0


def room(h: int, w: int, seed: int) -> torch.Tensor:
    """A textured backdrop [H, W, 3] in 0-1: smooth colour blobs with finer detail on top."""
    g = torch.Generator().manual_seed(seed)
    out = torch.zeros(1, 3, h, w)
    for cells, amp in ((4, 1.0), (12, 0.5), (40, 0.25)):
        noise = torch.rand(1, 3, max(2, h * cells // w), cells, generator=g)
        out += amp * F.interpolate(noise, size=(h, w), mode="bicubic", align_corners=False)
    out = (out - out.amin()) / (out.amax() - out.amin())
    return (0.15 + 0.7 * out)[0].permute(1, 2, 0)


def film(scene, up: str, size: tuple[int, int], frames: int, backdrop: torch.Tensor):
    """The capture turning TURN_DEG a frame before a still camera, over `backdrop`: frames
    [T, H, W, 3] and frame 0's camera."""
    from pd_tool.core.cameras import auto_camera
    from pd_tool.render.views import render_image

    pos = scene.positions.detach().cpu().numpy()
    out = []
    for k in range(frames):
        cam = auto_camera(pos, size[0], size[1], up_axis=up.lstrip("+"), azimuth_deg=45.0 + TURN_DEG * k,
                          margin=MARGIN)
        black = torch.from_numpy(render_image(scene, cam, background=(0.0, 0.0, 0.0))).float() / 255.0
        white = torch.from_numpy(render_image(scene, cam, background=(1.0, 1.0, 1.0))).float() / 255.0
        alpha = (1.0 - (white - black).mean(-1, keepdim=True)).clamp(0, 1)  # 1 - background's share
        out.append((black + (1.0 - alpha) * backdrop).clamp(0, 1))
        first = cam if k == 0 else first
    return torch.stack(out), first


def shake(frames: torch.Tensor, rng: np.random.Generator, shift: float, zoom: float, roll_deg: float):
    """The frames moved by a random similarity each (frame 0 kept): (shaken frames, the
    CameraMotion that describes the shake, as pd_tool.video.camera_motion measures it)."""
    from pd_tool.video.camera_motion import CameraMotion, undo_motion

    t, h, w, _ = frames.shape
    long_side = max(h, w)
    shifts = np.vstack([[0.0, 0.0], rng.uniform(-shift, shift, (t - 1, 2)) * long_side])
    zooms = np.concatenate([[1.0], 1.0 + rng.uniform(-zoom, zoom, t - 1)])
    rolls = np.concatenate([[0.0], np.radians(rng.uniform(-roll_deg, roll_deg, t - 1))])
    truth = CameraMotion(shifts, zooms, rolls, np.zeros(t), long_side)
    # the content moves by the shake: sample each still frame where the inverse shake puts it
    c, s = np.cos(rolls), np.sin(rolls)
    inv_shift = -np.stack([c * shifts[:, 0] + s * shifts[:, 1], -s * shifts[:, 0] + c * shifts[:, 1]], 1) / zooms[:, None]
    inverse = CameraMotion(inv_shift, 1.0 / zooms, -rolls, np.zeros(t), long_side)
    shaken, _ = undo_motion(frames, inverse)
    return shaken, truth


def corner_error(est, truth, h: int, w: int) -> np.ndarray:
    """Per frame, the largest distance (px) between where the two motions put a corner."""
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    corners = np.array([[-cx, -cy], [cx, -cy], [-cx, cy], [cx, cy]])

    def place(m, k):
        c, s = math.cos(m.rolls[k]), math.sin(m.rolls[k])
        rot = corners @ np.array([[c, s], [-s, c]]) * m.zooms[k]
        return rot + m.shifts[k]

    return np.array([np.linalg.norm(place(est, k) - place(truth, k), axis=1).max() for k in range(len(truth.zooms))])


def run_case(scene, up: str, args, seed: int) -> dict:
    from pd_tool.video.camera_motion import CameraMotion
    from pd_tool.video.clip import footprint, outside_object, stabilise

    w, h = args.size, round(args.size * 3 / 4)
    rng = np.random.default_rng(seed)
    still, cam = film(scene, up, (w, h), args.frames, room(h, w, seed))
    shaken, truth = shake(still, rng, args.shift, args.zoom, args.roll)
    noisy = ((shaken + torch.from_numpy(rng.normal(0, NOISE, shaken.shape)).float()).clamp(0, 1) * 255 + 0.5).floor() / 255
    t0 = time.perf_counter()
    # as `pdtool fit` measures it: outside the object's footprint at rest, widened
    frames, masks, motion, warped = stabilise(noisy, None, outside_object(footprint(scene, cam)))
    seconds = time.perf_counter() - t0
    if motion is None:
        return {"seed": seed, "warped": False, "seconds": seconds}
    err = corner_error(motion, truth, h, w)[1:] / max(h, w) * 100.0
    grey = torch.tensor([0.299, 0.587, 0.114])
    after, before = [], []
    for k in range(1, args.frames):
        m = masks[k] if masks is not None else torch.ones(h, w)
        after.append(float((((frames[k] - still[k]) @ grey).abs() * m).sum() / m.sum()))
        before.append(float(((noisy[k] - still[k]) @ grey).abs().mean()))
    still_camera = CameraMotion(np.zeros_like(truth.shifts), np.ones_like(truth.zooms), np.zeros_like(truth.rolls),
                                truth.displacement, truth.long_side)
    shake_pct = corner_error(truth, still_camera, h, w)[1:] / max(h, w) * 100.0
    return {"seed": seed, "warped": bool(warped), "seconds": seconds, "corner_error_pct": err.tolist(),
            "shake_pct": shake_pct.tolist(), "grey_error_after": after, "grey_error_shaken": before}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="udon,donut,tree")
    ap.add_argument("--cases", type=int, default=6, help="random shakes per capture")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--size", type=int, default=320, help="frames' long side, px (4:3)")
    ap.add_argument("--gaussians", type=int, default=100000, help="at most this many of each capture")
    ap.add_argument("--shift", type=float, default=0.02, help="largest shift, share of the long side")
    ap.add_argument("--zoom", type=float, default=0.015, help="largest zoom change")
    ap.add_argument("--roll", type=float, default=1.0, help="largest roll, degrees")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from pd_tool.io import load_splats

    rows = []
    print(f"{'scene':<6} {'cases':>5}  corner error % of long side: median  95%  worst   grey error after / shaken   s a clip")
    for name in args.scenes.split(","):
        if name not in CAPTURES:
            print(f"unknown scene {name!r}; choose from {', '.join(CAPTURES)}", file=sys.stderr)
            return 2
        path, up = CAPTURES[name]
        scene = load_splats(args.data / path, device=args.device)
        if scene.count > args.gaussians:
            scene = scene.subset(np.sort(np.random.default_rng(0).choice(scene.count, args.gaussians, replace=False)))
        cases = [run_case(scene, up, args, seed) for seed in range(args.cases)]
        errs = np.concatenate([c.get("corner_error_pct", []) for c in cases])
        after = np.concatenate([c.get("grey_error_after", []) for c in cases])
        before = np.concatenate([c.get("grey_error_shaken", []) for c in cases])
        row = {"scene": name, "cases": cases, "warped": sum(c["warped"] for c in cases),
               "corner_error_pct": {"median": float(np.median(errs)), "p95": float(np.percentile(errs, 95)),
                                    "max": float(errs.max())} if len(errs) else None,
               "grey_error_after": float(after.mean()) if len(after) else None,
               "grey_error_shaken": float(before.mean()) if len(before) else None,
               "seconds": float(np.mean([c["seconds"] for c in cases]))}
        rows.append(row)
        ce = row["corner_error_pct"] or {"median": float("nan"), "p95": float("nan"), "max": float("nan")}
        print(f"{name:<6} {len(cases):>5}  {ce['median']:.3f}  {ce['p95']:.3f}  {ce['max']:.3f}   "
              f"{row['grey_error_after'] or float('nan'):.4f} / {row['grey_error_shaken'] or float('nan'):.4f}   "
              f"{row['seconds']:.1f}  (warped {row['warped']} of {len(cases)})")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
