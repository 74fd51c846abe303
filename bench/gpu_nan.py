"""Find where a non-finite stage-2 gradient comes from (anomaly mode), after a stage 1.

    python bench/gpu_nan.py --device cuda --gaussians 100000
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
    ap.add_argument("--gaussians", type=int, default=100000)
    ap.add_argument("--velocity-iters", type=int, default=60)
    args = ap.parse_args()
    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.pipeline import FitProblem, FitSettings, _clip_and_step, velocity_iteration
    from pd_tool.fit.schedule import make_optimizer
    from pd_tool.video.folder import load_reference_video
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.fit.reference import plant_reference_video
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, make_plant
    from pd_tool.render.views import scene_camera

    init_warp_quietly()
    dev = args.device
    with tempfile.TemporaryDirectory() as tmp:
        p = save_splats(make_plant(args.gaussians, seed=0), Path(tmp) / "plant.ply")
        sc = load_splats(p, device=dev)
        cam = scene_camera(sc, width=1024, height=576)
        video, _, _ = plant_reference_video(Path(tmp) / "v", sc, cam, prepare_options=PrepareOptions(
            static_below=POT_TOP, grid_res=32), region_E=REGION_TRUTH_E, driver_ratio=0.1, n_frames=14, device=dev)
        refs = [load_reference_video(video, working_size=1024, device=dev)]
        s = FitSettings(quality="default", device=dev, working_long_side=1024).resolved()
        pb = FitProblem(sc, refs, PrepareOptions(static_below=POT_TOP), s)
        opt, sched = make_optimizer(list(pb.velocities), s.lr_velocity, args.velocity_iters, warmup_steps=3)
        for _ in range(args.velocity_iters):
            velocity_iteration(pb)
            _clip_and_step(list(pb.velocities.parameters()), opt, sched, 1.0)
        with torch.no_grad():
            v0 = pb.driver_v0(0)
        print("v0 max m/s", float(v0.norm(dim=1).max()), flush=True)
        E = pb.driver_E()
        sub = pb.substeps(E, v0)
        print("substeps", sub, flush=True)
        state = pb.initial_state(v0)
        for k in range(1, refs[0].num_frames):
            st = tuple(t.detach().requires_grad_(True) for t in state)
            Ek = E.detach().requires_grad_(True)
            new = pb.step(st, Ek, sub, k)
            xk = new[0].detach().requires_grad_(True)
            img = pb.render(0, xk)
            loss = pb.frame_loss(0, k, img)
            gx, = torch.autograd.grad(loss, xk)
            gE, = torch.autograd.grad(new[0], Ek, grad_outputs=gx)
            Fdet = torch.linalg.det(new[3])
            print(f"frame {k}: loss {loss.item():.5f} render-grad finite {bool(torch.isfinite(gx).all())} "
                  f"sim-grad(E) finite {bool(torch.isfinite(gE).all())} detF [{Fdet.min().item():.3f}, {Fdet.max().item():.3f}] "
                  f"|x-x0|max {(new[0]-pb.x_rest).norm(dim=1).max().item():.3f}", flush=True)
            state = tuple(t.detach() for t in new)


if __name__ == "__main__":
    main()
