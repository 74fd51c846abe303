"""pd_tool.render against its dense float64 twin (_ref.py) and finite differences.

The reference evaluates every Gaussian at every pixel in one global depth order and applies
the 3DGS cut-offs the kernels apply (tile rectangle of the 3-sigma bound, alpha clamp 0.99,
skip alpha < 1/255, stop before T < 1e-4; see _ref.py), so the tiled float32 rasteriser must
agree with it to float32 rounding.
"""
from __future__ import annotations


import numpy as np
import pytest
import torch

from pd_tool.core.cameras import Camera, auto_camera, look_at
from pd_tool.render import RenderInputError, render
from pd_tool.render._ref import render_ref
from pd_tool.render.rasterize import RasterSettings, rasterize

FWD_ATOL = 1e-4  # float32 kernel vs float64 reference, per pixel and channel (the brief)
GRAD_RTOL = 1e-4  # relative L2 error of float32 gradients vs float64 autograd (seen: ~1e-6)
FD_RTOL = 2e-2  # float32 central differences are noisy: ~1e-5 loss rounding / 2h


def make_scene(n: int, seed: int, k: int = 16):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.5
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.03
    opacities = torch.rand(n, generator=g) * 0.8 + 0.1
    sh = torch.randn(n, k, 3, generator=g) * 0.3
    return [means, quats, scales, opacities, sh]


# 40x36 px: not a multiple of the 16 px tile, so partial tiles are exercised.
CAM = Camera(40, 36, 48.0, 50.0, 19.0, 18.5, look_at([0.3, -3.5, 0.8], [0, 0, 0], [0, 0, 1]))


def settings(cam: Camera, bg=(0.0, 0.0, 0.0), degree=3, near=0.01) -> RasterSettings:
    return RasterSettings(cam, tuple(bg), degree, near)


@pytest.mark.parametrize("degree,seed", [(0, 0), (1, 1), (2, 2), (3, 3)])
def test_forward_matches_dense_reference(device, degree, seed):
    scene = make_scene(60, seed, k=(degree + 1) ** 2)
    bg = (0.2, 0.3, 0.4)
    out = render(*[t.to(device) for t in scene], CAM, background=bg, return_depth=True)
    rgb, alpha, depth_sum = render_ref(*[t.double() for t in scene], settings(CAM, bg, degree))
    assert out.alpha.min() < 0.05 < 0.5 < out.alpha.max()  # some empty and some covered pixels
    assert (out.rgb.cpu().double() - rgb).abs().max() < FWD_ATOL
    assert (out.alpha.cpu().double() - alpha).abs().max() < FWD_ATOL
    ref_depth = torch.where(alpha > 0, depth_sum / alpha.clamp_min(1e-12), torch.zeros_like(alpha))
    covered = alpha > 0.1  # expected depth divides by alpha; compare where it is well defined
    assert (out.depth.cpu().double() - ref_depth)[covered].abs().max() < 1e-3  # depth ~3.5 units


def test_culling_near_plane_and_offscreen(device):
    means, quats, scales, opacities, sh = make_scene(30, 7)
    # Half the Gaussians behind the camera or beyond the image: they must not contribute.
    means[:10] = torch.tensor([0.3, -4.5, 0.8]) + 0.1 * torch.randn(10, 3)  # behind
    means[10:15] += torch.tensor([30.0, 0.0, 0.0])  # far off-screen to the side
    scene = [means, quats, scales, opacities, sh]
    out = render(*[t.to(device) for t in scene], CAM, background=(1.0, 1.0, 1.0))
    rgb, alpha, _ = render_ref(*[t.double() for t in scene], settings(CAM, (1.0, 1.0, 1.0)))
    assert (out.rgb.cpu().double() - rgb).abs().max() < FWD_ATOL
    empty = render(*[t[:15].to(device) for t in scene], CAM, background=(1.0, 0.5, 0.0))
    assert torch.equal(empty.alpha.cpu(), torch.zeros(36, 40, 1))
    assert torch.equal(empty.rgb.cpu(), torch.tensor([1.0, 0.5, 0.0]).expand(36, 40, 3))


def _loss_grads(fn, inputs, cot):
    rgb, alpha, depth = fn(inputs)
    loss = (rgb * cot[0]).sum() + (alpha * cot[1]).sum() + (depth * cot[2]).sum()
    return torch.autograd.grad(loss, inputs)


def test_backward_matches_reference_autograd(device):
    """Same random cotangent on rgb, alpha and depth into the op and the float64 reference."""
    scene = make_scene(50, 11)
    bg = (0.2, 0.3, 0.4)
    s = settings(CAM, bg)
    g = torch.Generator().manual_seed(5)
    cot = [torch.randn(36, 40, c, generator=g) for c in (3, 1, 1)]
    ours = _loss_grads(lambda x: rasterize(*x, s), [t.to(device).requires_grad_() for t in scene],
                       [c.to(device) for c in cot])
    ref = _loss_grads(lambda x: render_ref(*x, s), [t.double().requires_grad_() for t in scene],
                      [c.double() for c in cot])
    for name, a, b in zip(("means", "quats", "scales", "opacities", "sh"), ours, ref):
        err = (a.cpu().double() - b).norm() / b.norm()
        assert b.norm() > 0, name
        assert err < GRAD_RTOL, f"{name}: relative error {err:.2e}"


def test_reference_gradients_match_finite_differences():
    """The reference's autograd gradients against float64 central differences (gradcheck)."""
    scene = [t.double() for t in make_scene(6, 21)]
    cam = Camera(20, 18, 24.0, 25.0, 9.5, 9.0, CAM.world_to_camera)
    s = settings(cam, (0.2, 0.3, 0.4))
    inputs = [t.clone().requires_grad_() for t in scene]
    # fast_mode checks random projections of the Jacobian: seconds instead of minutes.
    assert torch.autograd.gradcheck(lambda *x: render_ref(*x, s), inputs, eps=1e-6, atol=1e-5,
                                    rtol=1e-4, fast_mode=True)


def smooth_scene():
    """Six large, faint Gaussians well apart in depth: every one reaches every pixel with
    alpha > 1/255, its 3-sigma rectangle covers all tiles, T never nears 1e-4 and no depth
    order can swap, so the image is smooth in all inputs and finite differences apply."""
    g = torch.Generator().manual_seed(31)
    n = 6
    means = torch.zeros(n, 3)
    means[:, 1] = torch.linspace(-0.8, 0.8, n)  # along the view axis (camera looks along +y)
    means[:, 0] = 0.1 * torch.randn(n, generator=g)
    means[:, 2] = 0.1 * torch.randn(n, generator=g)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.4 + 0.9
    opacities = torch.rand(n, generator=g) * 0.3 + 0.2
    sh = torch.randn(n, 16, 3, generator=g) * 0.3
    return [means, quats, scales, opacities, sh]


def test_backward_matches_finite_differences_of_the_kernels():
    """Directional derivatives of the float32 renderer itself, central differences."""
    scene = smooth_scene()
    cam = Camera(40, 36, 48.0, 50.0, 19.0, 18.5, look_at([0.0, -3.5, 0.0], [0, 0, 0], [0, 0, 1]))
    s = settings(cam, (0.2, 0.3, 0.4))
    g = torch.Generator().manual_seed(9)
    w = torch.randn(36, 40, 3, generator=g)

    def loss(x):
        rgb, alpha, depth = rasterize(*x, s)
        return (rgb * w).sum() + alpha.sum() + 0.1 * depth.sum()

    inputs = [t.clone().requires_grad_() for t in scene]
    grads = torch.autograd.grad(loss(inputs), inputs)
    h = 1e-3
    for i, name in enumerate(("means", "quats", "scales", "opacities", "sh")):
        v = torch.randn(scene[i].shape, generator=g)
        plus = [t.clone() for t in scene]
        minus = [t.clone() for t in scene]
        plus[i] = plus[i] + h * v
        minus[i] = minus[i] - h * v
        with torch.no_grad():
            fd = (loss(plus) - loss(minus)).item() / (2 * h)
        analytic = (grads[i] * v).sum().item()
        assert abs(fd - analytic) <= FD_RTOL * max(abs(analytic), 1.0), f"{name}: fd {fd} vs {analytic}"


def test_cpu_and_cuda_agree(device):
    if device == "cpu":
        pytest.skip("needs cuda: compares a cuda render with the cpu one")
    scene = make_scene(60, 3)
    a = render(*scene, CAM).rgb
    b = render(*[t.cuda() for t in scene], CAM).rgb.cpu()
    assert (a - b).abs().max() < FWD_ATOL


def test_input_validation():
    scene = make_scene(4, 0)
    with pytest.raises(RenderInputError, match=r"quats must be \[N, 4\]"):
        render(scene[0], scene[1][:, :3], *scene[2:], CAM)
    with pytest.raises(RenderInputError, match="K=5"):
        render(*scene[:4], torch.zeros(4, 5, 3), CAM)
    with pytest.raises(RenderInputError, match="sh_degree=3"):
        render(*scene[:4], scene[4][:, :4], CAM, sh_degree=3)
    with pytest.raises(RenderInputError, match="Camera"):
        render(*scene, "cam")


def load_udon(path):
    from pd_tool.io import load_splats

    return load_splats(path)


def test_udon_from_auto_camera(shared_data, tmp_path, device):
    scene = load_udon(shared_data / "udon.ply")
    cam = auto_camera(scene.positions.numpy(), 96, 80, up_axis="-y")
    t = [x.to(device) for x in (scene.positions, scene.quats, scene.scales, scene.opacities, scene.sh)]
    out = render(*t, cam, background=(1.0, 1.0, 1.0), return_depth=True)
    rgb = out.rgb.cpu()
    assert torch.isfinite(rgb).all() and torch.isfinite(out.alpha).all()
    covered = (out.alpha.cpu() > 0.5).float().mean().item()
    assert 0.02 < covered < 0.9  # the object fills part of the frame, not nothing / everything
    assert out.alpha.cpu()[0].max() < 0.5 and out.alpha.cpu()[:, 0].max() < 0.5  # framed with margin
    assert rgb[out.alpha.cpu()[..., 0] > 0.5].std(0).min() > 0.02  # textured, not flat
    d = out.depth.cpu()[out.alpha.cpu() > 0.5]
    dist = np.linalg.norm(cam.center - np.percentile(scene.positions.numpy(), 50, axis=0))
    assert abs(d.median().item() - dist) < 0.5 * dist  # depth is the distance to the object


def test_lower_sh_degree_than_stored_and_empty_scene():
    scene = make_scene(40, 13)  # K = 16 coefficients stored
    out = render(*scene, CAM, sh_degree=1)
    rgb, _, _ = render_ref(*[t.double() for t in scene[:4]], scene[4][:, :4].double(), settings(CAM, degree=1))
    assert (out.rgb.double() - rgb).abs().max() < FWD_ATOL
    empty = [t[:0].requires_grad_() for t in scene]
    out = render(*empty, CAM, background=(0.1, 0.2, 0.3))
    assert torch.allclose(out.rgb, torch.tensor([0.1, 0.2, 0.3]).expand(36, 40, 3))
    out.rgb.sum().backward()
    assert empty[0].grad.shape == (0, 3)
