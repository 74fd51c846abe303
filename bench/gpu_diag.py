"""GPU diagnostics: does a fit's material step get finite gradients on CUDA as on CPU?

    python bench/gpu_diag.py --device cuda
"""
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--gaussians", type=int, default=3000)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--quality", default="draft")
    args = ap.parse_args()
    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitProblem, FitSettings, material_iteration
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_video, push_velocity
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, make_plant
    from pd_tool.render.views import scene_camera

    init_warp_quietly()
    out = {}
    for dev in (["cpu"] if args.gaussians <= 5000 else []) + [args.device]:
        with tempfile.TemporaryDirectory() as tmp:
            p = save_splats(make_plant(args.gaussians, seed=0), Path(tmp) / "plant.ply")
            sc = load_splats(p, device=dev)
            cam = scene_camera(sc, width=args.size, height=args.size * 9 // 16)
            video, _, _ = plant_reference_video(Path(tmp) / "v", sc, cam, prepare_options=PrepareOptions(
                static_below=POT_TOP, grid_res=32), region_E=REGION_TRUTH_E, driver_ratio=0.1, n_frames=6, device=dev)
            refs = [load_reference_video(video, working_size=args.size, device=dev)]
            s = FitSettings(quality=args.quality, device=dev).resolved()
            pb = FitProblem(sc, refs, PrepareOptions(static_below=POT_TOP), s)
            v0 = torch.as_tensor(push_velocity(pb.x_rest.double().cpu().numpy(), pb.static.cpu().numpy(), speed=0.6),
                                 dtype=torch.float32, device=dev)
            loss = material_iteration(pb, [v0], pb.s.material_horizon)
            g_res = pb.log_e_residual.grad
            g_field = [q.grad for q in pb.material.parameters() if q.grad is not None]
            row = {
                "loss": loss,
                "residual_grad_finite": bool(torch.isfinite(g_res).all()) if g_res is not None else None,
                "residual_grad_norm": float(g_res.norm()) if g_res is not None else None,
                "field_grad_finite": all(bool(torch.isfinite(g).all()) for g in g_field),
                "field_grad_norm": float(sum(g.norm() ** 2 for g in g_field) ** 0.5) if g_field else None,
            }
            out[dev] = row
            print(dev, row, flush=True)
    if args.json:
        import json

        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
