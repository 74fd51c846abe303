"""Does `pdtool register` find a known camera? Cases with a known answer on the captures.

For each capture and case: a random camera (azimuth 0-360 degrees, elevation -10 to 60 above
the scene's up axis, vertical field of view 30-65 degrees, a roll of up to 8 degrees, the
object spanning 45-90% of the frame's shorter side and off the image centre by up to 8% of
the frame), the capture rendered from it over a cluttered background (random ellipses and
boxes of random colours, slightly blurred), a per-channel exposure change of up to 10% and
pixel noise of sigma 2/255. Then `register_frame` from its default start, without the
answer, and its errors: the rotation (degrees), the camera centre's distance from the true
one as a fraction of the object's size (the diagonal of its 1st-99th percentile box) and
the focal length (%). The principal point sits at the image centre, as the solve assumes.

    python bench/register_accuracy.py [--quick] [--device cuda] [--cases 50] [--known-focal] [--json F]

Target: under 1 degree, 2% and 2% on at least 95% of the cases of every capture.
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pd_tool.core.cameras import Camera, _UP, look_at  # noqa: E402
from pd_tool.core.scene import GaussianScene  # noqa: E402
from pd_tool.register.solve import RegisterSettings, object_bounds, register_frame, render_over  # noqa: E402

TARGETS = {"rotation_deg": 1.0, "translation": 0.02, "focal": 0.02}
CAPTURES = ("udon.ply", "donut_fused.ply", "tree_100k.splat")


def clutter(h: int, w: int, rng: np.random.Generator, shapes: int = 40) -> np.ndarray:
    """[h, w, 3] float32: random ellipses and boxes of random colours on a random gradient."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    c0, c1 = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    g = (xx / w)[..., None]
    img = (c0 * (1 - g) + c1 * g).astype(np.float32)
    for _ in range(shapes):
        col = rng.uniform(0, 1, 3).astype(np.float32)
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        rx, ry = rng.uniform(0.02, 0.2) * w, rng.uniform(0.02, 0.2) * h
        if rng.uniform() < 0.5:
            m = ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1.0
        else:
            m = (np.abs(xx - cx) <= rx) & (np.abs(yy - cy) <= ry)
        img[m] = col
    t = torch.from_numpy(img).permute(2, 0, 1)[None]
    k = torch.tensor([1.0, 2.0, 1.0]) / 4.0
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (1, 1, 0, 0), mode="replicate"),
                                   k.view(1, 1, 1, 3).repeat(3, 1, 1, 1), groups=3)
    t = torch.nn.functional.conv2d(torch.nn.functional.pad(t, (0, 0, 1, 1), mode="replicate"),
                                   k.view(1, 1, 3, 1).repeat(3, 1, 1, 1), groups=3)
    return t[0].permute(1, 2, 0).numpy()


def random_camera(center: np.ndarray, radius: float, up: np.ndarray, width: int, height: int,
                  rng: np.random.Generator) -> Camera:
    """A random handheld-like view of the object (see the module docstring)."""
    h1 = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    h1 /= np.linalg.norm(h1)
    h2 = np.cross(up, h1)
    az, el = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(-10, 60))
    d = math.cos(el) * (math.cos(az) * h1 + math.sin(az) * h2) + math.sin(el) * up
    fov = math.radians(rng.uniform(30, 65))
    f = 0.5 * height / math.tan(0.5 * fov)
    fill = rng.uniform(0.45, 0.9)
    dist = 2.0 * radius * f / (fill * min(width, height))
    w2c = look_at(center + dist * d, center, up)
    roll = math.radians(rng.uniform(-8, 8))
    rz = np.eye(4)
    rz[:2, :2] = [[math.cos(roll), -math.sin(roll)], [math.sin(roll), math.cos(roll)]]
    # the object off the image centre: turn the camera a little about its own x and y axes
    ox, oy = rng.uniform(-0.08, 0.08, 2)
    ry, rx = math.atan(ox * width / f), math.atan(oy * height / f)
    tilt = np.eye(4)
    cy_, sy_, cx_, sx_ = math.cos(ry), math.sin(ry), math.cos(rx), math.sin(rx)
    tilt[:3, :3] = np.array([[cy_, 0, sy_], [0, 1, 0], [-sy_, 0, cy_]]) @ np.array([[1, 0, 0], [0, cx_, -sx_], [0, sx_, cx_]])
    return Camera(width, height, f, f, width / 2.0, height / 2.0, tilt @ rz @ w2c)


def make_case(scene: GaussianScene, up: np.ndarray, width: int, height: int, seed: int,
              backdrop: tuple[float, float, float] | None = None) -> tuple[torch.Tensor, Camera]:
    """(frame [H, W, 3] float32 0-1, the true camera) for one case: over clutter, or over
    a plain `backdrop` colour (a render's background; the same camera as over clutter)."""
    rng = np.random.default_rng(seed)
    center, radius = object_bounds(scene.positions.detach().cpu().numpy())
    cam = random_camera(center, radius, up, width, height, rng)
    bg = torch.from_numpy(clutter(height, width, rng)).to(scene.positions.device)
    if backdrop is not None:
        bg = torch.tensor(backdrop, dtype=torch.float32, device=bg.device).expand_as(bg).contiguous()
    over, _ = render_over(scene, cam, bg)
    gain = torch.tensor(rng.uniform(0.9, 1.1, 3), dtype=torch.float32, device=over.device)
    noise = torch.from_numpy(rng.normal(0.0, 2.0 / 255.0, over.shape).astype(np.float32)).to(over.device)
    return (over * gain + noise).clamp(0.0, 1.0), cam


def camera_errors(found: Camera, truth: Camera, size: float) -> dict[str, float]:
    """Rotation (degrees), centre distance over the object's size, relative focal error."""
    r = found.world_to_camera[:3, :3] @ truth.world_to_camera[:3, :3].T
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(r) - 1.0) / 2.0))))
    return {"rotation_deg": angle,
            "translation": float(np.linalg.norm(found.center - truth.center)) / size,
            "focal": abs(found.fx / truth.fx - 1.0)}


def up_vector(scene: GaussianScene, up_axis: str) -> tuple[str, np.ndarray]:
    from pd_tool.render.views import auto_up

    axis = auto_up(scene, up_axis)[0].lstrip("+")
    return axis, np.asarray(_UP[axis], dtype=np.float64)


def near_start(truth: Camera, degrees: float, focal: float, seed: int) -> Camera:
    """The true camera turned by `degrees` about a random axis, its focal length off by `focal`."""
    from pd_tool.register.solve import _rodrigues

    rng = np.random.default_rng(seed + 99)
    axis = rng.normal(0.0, 1.0, 3)
    turn = np.eye(4)
    turn[:3, :3] = _rodrigues(torch.tensor(axis / np.linalg.norm(axis) * math.radians(degrees))).numpy()
    return Camera(truth.width, truth.height, truth.fx * (1 + focal), truth.fy * (1 + focal), truth.cx, truth.cy,
                  turn @ truth.world_to_camera)


def run_capture(path: Path, cases: int, width: int, height: int, device: str, seed: int,
                settings: RegisterSettings, max_gaussians: int | None, start: tuple[float, float] | None = None,
                known_focal: bool = False, backdrop: tuple[float, float, float] | None = None) -> dict:
    from pd_tool.io import load_splats

    scene = load_splats(path, device=device)
    if max_gaussians and scene.positions.shape[0] > max_gaussians:
        idx = torch.randperm(scene.positions.shape[0], generator=torch.Generator().manual_seed(seed))[:max_gaussians]
        scene = GaussianScene(scene.positions[idx.to(device)], scene.quats[idx.to(device)], scene.scales[idx.to(device)],
                              scene.opacities[idx.to(device)], scene.sh[idx.to(device)])
    axis, up = up_vector(scene, "auto")
    center, radius = object_bounds(scene.positions.detach().cpu().numpy())
    size = 2.0 * radius
    s = RegisterSettings(**{**settings.__dict__, "up_axis": axis})
    rows = []
    for k in range(cases):
        frame, truth = make_case(scene, up, width, height, seed * 1000 + k, backdrop)
        begin = None if start is None else near_start(truth, start[0], start[1], seed * 1000 + k)
        reg = register_frame(scene, frame, settings=s, start=begin, focal=truth.fx if known_focal else None)
        err = camera_errors(reg.camera, truth, size)
        ok = all(err[m] < TARGETS[m] for m in TARGETS)
        rows.append({"case": k, **err, "met": ok, "residual": reg.residual, "seconds": reg.seconds})
        print(f"{path.name} case {k}: rotation {err['rotation_deg']:.3f} deg, translation {100 * err['translation']:.2f}%, "
              f"focal {100 * err['focal']:.2f}%, residual {reg.residual:.4f}, {reg.seconds:.1f} s{'' if ok else '  MISSED'}",
              flush=True)
    met = sum(r["met"] for r in rows)
    return {"capture": path.name, "gaussians": int(scene.positions.shape[0]), "up": axis, "cases": rows,
            "met": met, "share_met": met / max(len(rows), 1),
            "median": {m: float(np.median([r[m] for r in rows])) for m in TARGETS},
            "p95": {m: float(np.percentile([r[m] for r in rows], 95)) for m in TARGETS},
            "seconds_median": float(np.median([r["seconds"] for r in rows]))}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--captures", default=",".join(CAPTURES))
    ap.add_argument("--cases", type=int, default=50)
    ap.add_argument("--size", default="640x480", help="frame WxH (px)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-gaussians", type=int, default=0, help="render at most this many of each capture (0: all)")
    ap.add_argument("--start", default="", help="DEG,FOCAL: refine from the truth turned DEG degrees with its "
                    "focal length off by FOCAL (0.1 = 10%%) instead of searching")
    ap.add_argument("--known-focal", action="store_true", help="give the solve the true focal length, as "
                    "`--focal-mm` does (a phone's 35 mm-equivalent focal length)")
    ap.add_argument("--backdrop", default="clutter", help="clutter, or R,G,B (0-1): a plain background, as "
                    "a render or a generated video has")
    ap.add_argument("--quick", action="store_true", help="CI scale: udon, 3 cases at 240x180")
    ap.add_argument("--json", default="")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="a RegisterSettings field, e.g. azimuths=36 or elevations=-10,0,10")
    a = ap.parse_args(argv)
    if a.quick:
        a.captures, a.cases, a.size = "udon.ply", 3, "240x180"
    w, h = (int(v) for v in a.size.split("x"))
    t0 = time.perf_counter()
    out = {"device": a.device, "gpu": torch.cuda.get_device_name() if a.device.startswith("cuda") else None,
           "settings": {k: getattr(a, k) for k in ("captures", "cases", "size", "seed", "max_gaussians", "quick", "start",
                                                          "known_focal", "backdrop")},
           "targets": TARGETS, "captures": []}
    for name in a.captures.split(","):
        rs = RegisterSettings()
        for item in a.set:
            key, value = item.split("=", 1)
            old = getattr(rs, key)
            setattr(rs, key, tuple(float(v) for v in value.split(",")) if isinstance(old, tuple)
                    else value.lower() in ("1", "true") if isinstance(old, bool) else type(old)(value))
        out["captures"].append(run_capture(Path(a.data) / name, a.cases, w, h, a.device, a.seed, rs,
                                           a.max_gaussians or None,
                                           tuple(float(v) for v in a.start.split(",")) if a.start else None,
                                           a.known_focal,
                                           None if a.backdrop == "clutter" else tuple(float(v) for v in a.backdrop.split(","))))
    out["seconds"] = time.perf_counter() - t0
    for c in out["captures"]:
        print(f"{c['capture']}: {c['met']}/{len(c['cases'])} within the targets; median rotation "
              f"{c['median']['rotation_deg']:.3f} deg, translation {100 * c['median']['translation']:.2f}%, focal "
              f"{100 * c['median']['focal']:.2f}%; 95th percentile {c['p95']['rotation_deg']:.3f} deg, "
              f"{100 * c['p95']['translation']:.2f}%, {100 * c['p95']['focal']:.2f}%; {c['seconds_median']:.1f} s a case")
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
