"""Recovery benchmark: fit the synthetic plant's known E field from a rendered reference
video, then compare motion under a NEW force (never in the video) with the truth.

    python bench/fit_recovery.py --device cuda --gaussians 100000 --json recovery.json
    python bench/fit_recovery.py --quick            # CPU scale: 3000 Gaussians, draft

Reports, per region, the recovered E (median over the region's Gaussians) against the
truth, as |ln(E_fit / E_true)|, as the relative error in log space
|ln E_fit - ln E_true| / ln E_true (E in Pa) and as a plain relative error; and the RMS Gaussian position
error over `--seconds` of a sideways drag at the flower, as a fraction of the object
size, for the fitted field and for the uniform starting value (what a tool without
estimation uses, as PhysGaussian does), both against the truth.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


PUSH_SPEED = 0.6  # m/s at the top of each reference video's initial push


def true_push(x_sim, static, k: int):
    """View k's true initial velocity [N, 3] m/s at points x_sim (simulation axes, m), as
    plant_reference_for_fit gives it below."""
    from pd_tool.fit.reference import push_velocity

    return push_velocity(x_sim, static, direction=push_direction(k), speed=PUSH_SPEED)


def record_residual_gradients() -> dict:
    """Make every fit in this process record, each stage-2 iteration, the per-driver
    gradient of the video loss with respect to the log-E residuals (the regulariser's
    part left out). Returns the dict it fills: "data" -> list of [Q] arrays.

    The fit's own step runs unchanged: FitProblem.residual_penalty, called once per stage-2
    step, also takes its own gradient and hooks the residuals, whose hook then sees the
    step's whole gradient and keeps it less the penalty's."""
    import torch

    from pd_tool.fit.problem import FitProblem

    rec = {"data": []}
    penalty = FitProblem.residual_penalty

    def residual_penalty(pb):
        value = penalty(pb)
        (own,) = torch.autograd.grad(value, pb.log_e_residual, retain_graph=True)
        handle = None

        def record(total):
            rec["data"].append((total - own).detach().cpu().numpy())
            handle.remove()  # one step's gradient: the next step hooks again

        handle = pb.log_e_residual.register_hook(record)
        return value

    FitProblem.residual_penalty = residual_penalty
    return rec


def gradient_summary(grads: list, regions, moving, names) -> dict:
    """Per region (moving drivers): quantiles (10/50/90%) of each driver's RMS residual
    gradient over stage 2, and the mean |mean sign| of its gradient (1: always one way)."""
    import numpy as np

    g = np.stack(grads)  # [iterations, Q]
    rms = np.sqrt((g ** 2).mean(0))
    sign = np.abs(np.sign(g).mean(0))
    out = {"iterations": int(len(g))}
    for i, name in enumerate(names):
        sel = (regions == i) & moving
        if sel.any():
            out[name] = {"rms_q10_q50_q90": np.quantile(rms[sel], [0.1, 0.5, 0.9]).tolist(),
                         "sign_consistency": float(sign[sel].mean())}
    return out


def true_pushes(pb, views: int) -> list:
    """Every view's true initial velocity at a FitProblem's drivers: [Q, 3] m/s tensors."""
    import torch

    x = pb.x_rest.double().cpu().numpy()
    static = pb.static.cpu().numpy().astype(bool)
    return [torch.tensor(true_push(x, static, k), dtype=torch.float32, device=pb.device) for k in range(views)]


def plant_references(folder, scene, *, views: int, size: int, quality, frames: int, fps: float,
                     substeps: int | None, device: str) -> list:
    """The benchmark's reference videos, loaded: view k pushed along push_direction(k) and
    seen from 45 + 90 k degrees azimuth (view 0 from the scene camera), `size` px on the
    long side (16:9 from 512 px up), written under `folder`."""
    from pd_tool.core.cameras import auto_camera
    from pd_tool.video.folder import load_reference_video
    from pd_tool.fit.reference import plant_reference_for_fit, reference_height
    from pd_tool.render.views import scene_camera

    h = reference_height(size)
    refs = []
    for k in range(views):
        cam = scene_camera(scene, width=size, height=h) if k == 0 else auto_camera(
            scene.positions.detach().cpu().numpy(), size, h, azimuth_deg=45.0 + 90.0 * k)
        video, _, _ = plant_reference_for_fit(
            Path(folder) / f"video{k}", scene, cam, quality, n_frames=frames, fps=fps,
            push_speed=PUSH_SPEED, push_direction=push_direction(k), substeps=substeps, device=device)
        refs.append(load_reference_video(video, working_size=size, device=device))
    return refs


def truth_substeps(scene, quality: dict, fps: float, nu: float) -> int:
    """The substeps per frame the CFL condition gives the reference under the true E and
    the push's top speed (what --substeps truth fixes for every simulation)."""
    from pd_tool.prepare.preparation import PrepareOptions, prepare_scene
    from pd_tool.materials.presets import fit_simulation
    from pd_tool.sim.cfl import cfl_substeps, wave_speed
    from pd_tool.io.synthetic import POT_TOP, driver_truth_E

    grid, cfl, ratio = fit_simulation(quality)
    prep = prepare_scene(scene, PrepareOptions(static_below=POT_TOP, grid_res=grid))
    drivers = prep.build_drivers(ratio=ratio, seed=0)
    moving = ~drivers.static.cpu().numpy().astype(bool)
    rho = (drivers.mass / drivers.volume).cpu().numpy()
    c = wave_speed(driver_truth_E(scene, prep, drivers)[moving], rho[moving], nu)
    return cfl_substeps(1.0 / fps, max(prep.domain) / max(prep.grid_dims), c, PUSH_SPEED, cfl)


def objective_at(scene, refs, settings, res, views: int) -> dict:
    """The fit's loss (mean over every frame of every video) at the fitted E and v0s, at the
    truth, and with one of the two swapped: a fit whose loss is above the truth's stopped
    short of the objective's minimum; one below it found a different minimum."""
    import torch

    from pd_tool.fit.problem import FitProblem, sequence_loss
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.io.synthetic import POT_TOP, driver_truth_E

    pb = FitProblem(scene, refs, PrepareOptions(static_below=POT_TOP), settings.resolved())
    assert len(pb.x_rest) == len(res.driver_E), "the loss check must see the fit's drivers"
    f32 = dict(dtype=torch.float32, device=pb.device)
    E = {"fitted": torch.tensor(res.driver_E, **f32),
         "truth": torch.tensor(driver_truth_E(scene, pb.prep, pb.drivers), **f32)}
    v0 = {"fitted": [torch.tensor(v, **f32) for v in res.driver_v0s], "truth": true_pushes(pb, views)}
    with torch.no_grad():
        out = {f"E_{e}/v0_{v}": float(sequence_loss(pb, E[e], v0[v], None))
               for e in ("fitted", "truth") for v in ("fitted", "truth")}
    # the first video's substeps per frame under each E (CFL: the stiffest moving driver)
    out["substeps"] = {e: pb.substeps(E[e], v0["truth"][0]) for e in ("fitted", "truth")}
    return out


def push_direction(k: int) -> tuple[float, float, float]:
    """View k's push (simulation axes): along x for even k, along y for odd k."""
    return (1.0, 0.0, 0.0) if k % 2 == 0 else (0.0, 1.0, 0.0)


def setting_overrides(items: list[str]) -> dict:
    """`--set FIELD=VALUE` items as {field: value}; each VALUE is JSON (true, false and null
    in any case)."""
    out = {}
    for item in items:
        key, _, text = item.partition("=")
        out[key] = json.loads(text.lower() if text.lower() in ("true", "false", "null") else text)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--size", type=int, default=1024, help="reference frames' long side, px")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--views", type=int, default=1,
                    help="reference videos: view k is pushed along x (k even) or y (k odd) and seen from "
                         "45 + 90 k degrees azimuth; one shared E is fitted to all (multi-view)")
    ap.add_argument("--fps", type=float, default=30.0, help="reference video frame rate (the fit reads it "
                    "from camera.json); lower = the same frames span more of the oscillation")
    ap.add_argument("--quality", default="default")
    ap.add_argument("--seconds", type=float, default=2.0, help="length of the new-force test")
    ap.add_argument("--quick", action="store_true", help="CPU scale: 3000 Gaussians, 192 px, draft")
    ap.add_argument("--velocity-iters", type=int, default=None)
    ap.add_argument("--material-iters", type=int, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a FitSettings field, e.g. --set refine_velocity=true (repeatable)")
    ap.add_argument("--substeps", default=None, metavar="N|truth",
                    help="diagnostic: at least N substeps per frame in every simulation (reference, fit, "
                         "new-force runs), so that they share one count unless E rises above what N allows; "
                         "'truth': the CFL count of the reference under the true E. Default: each simulation "
                         "picks its own by CFL, as pdtool does")
    ap.add_argument("--thick", action="store_true",
                    help="the plant with 2 cm leaves and petals (make_plant(thin=False)), a control; default: 3 mm")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--save-drivers", type=Path, metavar="NPZ",
                    help="also write each driver's rest position (simulation axes, m), region, static flag, "
                         "true and fitted E (Pa) and first video's fitted v0 (m/s), for offline study")
    ap.add_argument("--no-variants", action="store_true",
                    help="skip the new-force runs of the fitted field's variants (rms_error_with): faster")
    ap.add_argument("--residual-gradients", action="store_true",
                    help="diagnostic: report each region's per-driver stage-2 residual gradients "
                         "(JSON residual_gradients), to compare with Adam's eps (--set residual_eps=...)")
    args = ap.parse_args()
    args.thin = not args.thick
    if args.quick:
        args.gaussians, args.size, args.quality = 3000, 192, "draft"

    import numpy as np
    import torch

    from pd_tool.core.device import init_warp_quietly
    from pd_tool.fit.reference import simulate_positions
    from pd_tool.fit.run import run_fit
    from pd_tool.fit.settings import FitSettings
    from pd_tool.io import load_splats, save_splats
    from pd_tool.prepare.preparation import PrepareOptions
    from pd_tool.materials.presets import fit_simulation, load_preset
    from pd_tool.io.synthetic import POT_TOP, REGION_TRUTH_E, REGIONS, driver_regions, driver_truth_E, make_plant

    init_warp_quietly()
    if args.device == "cpu":
        torch.set_num_threads(1)
    q = load_preset("quality", args.quality)
    overrides = setting_overrides(args.set)
    grads = record_residual_gradients() if args.residual_gradients else None
    substeps = None
    if args.substeps is not None and args.substeps != "truth":
        substeps = int(args.substeps)
    settings = FitSettings(quality=args.quality, device=args.device, working_long_side=args.size,
                           velocity_iters=args.velocity_iters, material_iters=args.material_iters, **overrides)
    if args.residual_gradients and not settings.driver_residual:
        ap.error("--residual-gradients needs the per-driver residuals (driver_residual=true)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        path = save_splats(make_plant(args.gaussians, seed=0, thin=args.thin), tmp / "plant.ply")
        scene = load_splats(path, device=args.device)
        if args.substeps == "truth":
            substeps = truth_substeps(scene, q, args.fps, settings.nu)
        settings.substeps = substeps
        cfl = fit_simulation(q)[1]
        refs = plant_references(tmp, scene, views=args.views, size=args.size, quality=args.quality,
                                frames=args.frames, fps=args.fps, substeps=substeps, device=args.device)
        t0 = time.perf_counter()
        res = run_fit(scene, path, refs, tmp / "plant.pdmat", prepare_options=PrepareOptions(static_below=POT_TOP),
                      settings=settings)
        fit_s = time.perf_counter() - t0
    prep, drivers = res.prep, res.drivers
    labels = scene.labels[prep.foreground]
    truth_E = driver_truth_E(scene, prep, drivers)
    def region_errors(gaussian_E):
        regions = {}
        for i, name in enumerate(REGIONS):
            if name == "pot":
                continue  # static: never seen moving
            rec = float(np.median(gaussian_E[labels == i]))
            regions[name] = {"truth_pa": REGION_TRUTH_E[name], "fitted_pa": rec,
                             "abs_ln_error": abs(float(np.log(rec / REGION_TRUTH_E[name]))),
                             # relative error in log space, as the fit's goal states it: |ln E_fit - ln E| / ln E
                             "log_space_rel_error": abs(float(np.log(rec) - np.log(REGION_TRUTH_E[name])))
                             / float(np.log(REGION_TRUTH_E[name])),
                             "rel_error": rec / REGION_TRUTH_E[name] - 1.0}
        return regions

    regions = region_errors(res.gaussian_E)
    if args.save_drivers:
        np.savez_compressed(args.save_drivers, position=drivers.positions.cpu().numpy(),
                            region=driver_regions(scene, prep, drivers), static=drivers.static.cpu().numpy(),
                            truth_E=truth_E, fitted_E=res.driver_E, fitted_v0=res.driver_v0,
                            region_names=np.array(REGIONS))
    # the first video's fitted v0 against its true push, over the moving drivers
    free = ~drivers.static.cpu().numpy().astype(bool)
    v_true = true_push(drivers.positions.double().cpu().numpy(), ~free, 0)[free]
    v0_rel_error = float(np.linalg.norm(res.driver_v0[free] - v_true) / max(np.linalg.norm(v_true), 1e-12))
    # the same error split by simulation axis (x, y, z): a single camera barely sees motion
    # along its line of sight, so that component is the least constrained
    v0_axis_error = (np.linalg.norm(res.driver_v0[free] - v_true, axis=0)
                     / max(np.linalg.norm(v_true), 1e-12)).tolist()
    objective = objective_at(scene, refs, settings, res, args.views)
    # the fit's result before the slower new-force runs, so that a run cut short by a time
    # limit still reports it
    print(json.dumps({"fit_s": fit_s, "regions": regions, "v0_rel_error": v0_rel_error,
                      "v0_axis_error": v0_axis_error, "objective": objective}), file=sys.stderr,
          flush=True)
    s = settings.resolved()
    # fixed substeps are per frame of the video; the new-force runs step at 30 fps
    sim = dict(nu=s.nu, seconds=args.seconds, fps=30.0, accel=(0.0, 6.0, 0.0), device=args.device,
               cfl_safety=cfl, substeps=None if substeps is None else max(1, round(substeps * args.fps / 30.0)))
    n_true, n_fit = {}, {}
    x_true = simulate_positions(scene, prep, drivers, truth_E, **sim, stats=n_true)
    x_fit = simulate_positions(scene, prep, drivers, res.driver_E, **sim, stats=n_fit)
    x_base = simulate_positions(scene, prep, drivers, np.full(len(truth_E), s.init_E), **sim)
    fg = prep.foreground
    size = float(np.ptp(x_true[0][fg], axis=0).max())

    def rms(a):
        return float(np.sqrt(((a[:, fg] - x_true[:, fg]) ** 2).sum(-1).mean()) / size)

    out = {
        "device": args.device, "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None,
        "gaussians": args.gaussians, "drivers": int(len(res.driver_E)), "size_px": args.size,
        "frames": args.frames, "fps": args.fps, "views": args.views, "quality": args.quality,
        "overrides": overrides, "substeps": substeps,
        "fit_s": fit_s, "regions": regions, "stage1_levels": res.losses.get("stage1_level"),
        # the fit's own record (its material file's metrics): the stage-2 iteration whose state
        # it kept (0: its start), whether stage 2 ran again for keeping its start, the
        # whole-clip losses at stage 2's start and at the end
        "fit_metrics": {k: res.metrics.get(k) for k in ("kept_iteration", "stage2_retried", "loss_start",
                                                        "loss_final")},
        # the loss curves by name (stage 1, stage 2, whole-clip measures; a retried stage 2's first
        # attempt under *_first_try), to see where a fit went
        "losses": {k: [float(x) for x in v] for k, v in res.losses.items()},
        "v0_rel_error": v0_rel_error, "v0_axis_error": v0_axis_error, "objective": objective,
        "new_force": {"accel_scene_units_s2": sim["accel"], "seconds": args.seconds,
                      "rms_error_fitted": rms(x_fit), "rms_error_uniform_baseline": rms(x_base),
                      "peak_motion_truth": float(np.linalg.norm(x_true[:, fg] - x_true[0, fg], axis=-1).max() / size)},
    }
    out["new_force"]["baseline_over_fitted"] = out["new_force"]["rms_error_uniform_baseline"] / max(
        out["new_force"]["rms_error_fitted"], 1e-12)
    if grads is not None:
        out["residual_gradients"] = gradient_summary(grads["data"], driver_regions(scene, prep, drivers), free,
                                                     REGIONS)
    out["new_force"]["substeps"] = {"truth": n_true["substeps"], "fitted": n_fit.pop("substeps")}
    if not args.no_variants:
        # Where the remaining error lives: the fitted E with one region set to the truth, and
        # the fitted E flattened to its median per region (within-region variation removed).
        d_regions = driver_regions(scene, prep, drivers)
        swaps = {}
        flat = res.driver_E.copy()
        for i, name in enumerate(REGIONS):
            sel = d_regions == i
            if name == "pot" or not sel.any():
                continue
            one = res.driver_E.copy()
            one[sel] = truth_E[sel]
            swaps[f"{name}_true"] = rms(simulate_positions(scene, prep, drivers, one, **sim))
            flat[sel] = np.median(res.driver_E[sel])
        swaps["region_medians"] = rms(simulate_positions(scene, prep, drivers, flat, **sim))
        # the truth itself, stepped with as many substeps as the fitted E needed: the part of the
        # fitted error that is MPM's substep-dependent damping, not the field
        n_truth_run = max(out["new_force"]["substeps"]["fitted"], sim["substeps"] or 0)
        swaps["truth_at_fitted_substeps"] = rms(simulate_positions(scene, prep, drivers, truth_E,
                                                                   **{**sim, "substeps": n_truth_run}))
        # the fitted E with its stiffest moving drivers capped at a quantile: fewer substeps, so
        # less damping, at the price of a field the fit did not choose
        moving_E = res.driver_E[free]
        for q in (0.99, 0.95):
            capped = np.minimum(res.driver_E, np.quantile(moving_E, q))
            n_cap = {}
            swaps[f"capped_q{round(q * 100)}"] = rms(simulate_positions(scene, prep, drivers, capped, **sim,
                                                                        stats=n_cap))
            n_fit[f"capped_q{round(q * 100)}"] = n_cap["substeps"]
        out["new_force"]["rms_error_with"] = swaps
        out["new_force"]["substeps"].update(n_fit)
    if res.driver_E_uncalibrated is not None:
        # the same fit before its calibration stage: a paired comparison
        gl = drivers.labels.cpu().numpy()[: prep.count]
        rms_before = rms(simulate_positions(scene, prep, drivers, res.driver_E_uncalibrated, **sim))
        out["calibration"] = {**res.calibration, "before": {
            "regions": region_errors(res.driver_E_uncalibrated[gl]), "rms_error_fitted": rms_before,
            "baseline_over_fitted": out["new_force"]["rms_error_uniform_baseline"] / max(rms_before, 1e-12)}}
    print(json.dumps(out, indent=2))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
