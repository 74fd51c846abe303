"""Tests of pd_tool.fit.losses: SSIM against a float64 double-loop reference, gradients by
finite differences, and the masked frame loss against its definition."""
from __future__ import annotations

import math

import pytest
import torch

from pd_tool.fit.losses import SSIM_C1, SSIM_C2, frame_loss, ssim, ssim_map

TOL64 = 1e-12  # float64: the separable convolution only reorders sums
TOL32 = 2e-5  # float32 on 0-1 images: rounding in the variance terms E[x^2] - mu^2


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def ssim_map_ref(a: torch.Tensor, b: torch.Tensor, window: int, sigma: float) -> torch.Tensor:
    """Straightforward SSIM: [H, W, 3] float64 in, [H, W] out; zero padding; channel mean."""
    h, w, _ = a.shape
    r = window // 2
    g = [math.exp(-((i - r) ** 2) / (2 * sigma * sigma)) for i in range(window)]
    s = sum(g)
    g = [v / s for v in g]
    out = torch.zeros(h, w, dtype=torch.float64)
    for ch in range(3):
        for i in range(h):
            for j in range(w):
                mx = my = exx = eyy = exy = 0.0
                for di in range(-r, r + 1):
                    for dj in range(-r, r + 1):
                        ii, jj = i + di, j + dj
                        if 0 <= ii < h and 0 <= jj < w:  # outside: zero padding
                            wt = g[di + r] * g[dj + r]
                            x, y = float(a[ii, jj, ch]), float(b[ii, jj, ch])
                            mx += wt * x
                            my += wt * y
                            exx += wt * x * x
                            eyy += wt * y * y
                            exy += wt * x * y
                vx, vy, cxy = exx - mx * mx, eyy - my * my, exy - mx * my
                out[i, j] += ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)
                              / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))) / 3.0
    return out


def _pair(h: int, w: int, seed: int, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(h, w, 3, generator=g, dtype=dtype)
    b = (a + 0.2 * torch.randn(h, w, 3, generator=g, dtype=dtype)).clamp(0, 1)
    return a, b


@pytest.mark.parametrize("window,sigma", [(11, 1.5), (5, 1.0)])
def test_ssim_map_matches_double_loop_reference(window, sigma):
    a, b = _pair(7, 9, seed=0)
    ref = ssim_map_ref(a, b, window, sigma)
    got = ssim_map(a, b, window, sigma)
    assert got.shape == (7, 9)
    assert torch.allclose(got, ref, atol=TOL64, rtol=0)
    assert abs(float(ssim(a, b, window, sigma)) - float(ref.mean())) < TOL64


def test_ssim_layouts_agree_and_batch():
    a, b = _pair(8, 6, seed=1)
    c, d = _pair(8, 6, seed=2)
    batch1 = torch.stack([a, c]).permute(0, 3, 1, 2)
    batch2 = torch.stack([b, d]).permute(0, 3, 1, 2)
    m = ssim_map(batch1, batch2)
    assert m.shape == (2, 8, 6)
    assert torch.allclose(m[0], ssim_map(a, b), atol=TOL64)
    assert torch.allclose(m[1], ssim_map(c, d), atol=TOL64)


def test_ssim_identity_symmetry_and_float32(device):
    dev = "cuda" if device == "cuda" else "cpu"
    a, b = _pair(16, 20, seed=3, dtype=torch.float32)
    a, b = a.to(dev), b.to(dev)
    assert torch.allclose(ssim_map(a, a), torch.ones(16, 20, device=dev), atol=TOL32)
    assert abs(float(ssim(a, b)) - float(ssim(b, a))) < TOL32
    assert float(ssim(a, b)) < 0.9  # noisy copy is clearly different
    ref = ssim_map_ref(a.cpu().double(), b.cpu().double(), 11, 1.5)
    assert torch.allclose(ssim_map(a, b).cpu().double(), ref, atol=TOL32)


def test_ssim_gradcheck_float64():
    a, b = _pair(6, 7, seed=4)
    a.requires_grad_(True)
    b.requires_grad_(True)
    # a random weighting of the map checks every pixel's gradient with one output
    w = torch.rand(6, 7, dtype=torch.float64, generator=torch.Generator().manual_seed(11))
    assert torch.autograd.gradcheck(lambda x, y: (w * ssim_map(x, y)).sum(), (a, b))
    assert torch.autograd.gradcheck(lambda x, y: ssim(x, y, 5, 1.0), (a, b), fast_mode=True)


def test_frame_loss_unmasked_is_definition():
    a, b = _pair(9, 8, seed=5)
    lam = 0.1
    expect = lam * (a - b).abs().mean() + (1 - lam) * (1 - ssim(a, b))
    assert abs(float(frame_loss(a, b)) - float(expect)) < TOL64
    assert float(frame_loss(a, a)) < 1e-12
    assert torch.allclose(frame_loss(a, b, torch.ones(9, 8, dtype=torch.float64)), frame_loss(a, b), atol=TOL64)


def test_frame_loss_masked_is_weighted_mean_over_mask():
    a, b = _pair(9, 8, seed=6)
    g = torch.Generator().manual_seed(7)
    mask = torch.rand(9, 8, generator=g, dtype=torch.float64)
    mask[:3] = 0.0
    lam = 0.25
    smap = ssim_map_ref(a, b, 11, 1.5)
    l1 = sum(float(mask[i, j]) * float((a[i, j] - b[i, j]).abs().sum()) for i in range(9) for j in range(8))
    l1 /= 3.0 * float(mask.sum())
    s = float((smap * mask).sum() / mask.sum())
    expect = lam * l1 + (1 - lam) * (1 - s)
    assert abs(float(frame_loss(a, b, mask, lam)) - expect) < TOL64
    # pixels outside a binary mask do not change the L1 term; the SSIM map is computed on the
    # whole image, so only pixels farther than the window radius from the mask are ignored
    binm = torch.zeros(9, 8, dtype=torch.bool)
    binm[:2, :2] = True
    b2 = b.clone()
    b2[8, 7] = 1.0 - b2[8, 7]  # 6+ px from the mask: beyond the window radius (5)
    assert abs(float(frame_loss(a, b, binm)) - float(frame_loss(a, b2, binm))) < TOL64
    # empty mask: nothing to compare
    assert float(frame_loss(a, b, torch.zeros(9, 8))) == 0.0


def test_frame_loss_batched_and_gradcheck():
    a, b = _pair(6, 6, seed=8)
    c, d = _pair(6, 6, seed=9)
    m1 = torch.rand(6, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(10))
    batched = frame_loss(torch.stack([a, c]), torch.stack([b, d]), torch.stack([m1, torch.ones_like(m1)]))
    assert torch.isfinite(batched)
    pred = a.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: frame_loss(p, b, m1), (pred,))
    assert torch.autograd.gradcheck(lambda p: frame_loss(p, b, None, 0.5, window=5), (pred,))


def test_loss_shape_errors():
    a = torch.rand(4, 4, 3)
    with pytest.raises(ValueError, match="one shape"):
        ssim(a, torch.rand(4, 5, 3))
    with pytest.raises(ValueError, match="odd"):
        ssim(a, a, window=4)
    with pytest.raises(ValueError, match="mask"):
        frame_loss(a, a, torch.ones(4, 5))
    with pytest.raises(ValueError, match="lam"):
        frame_loss(a, a, lam=1.5)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        frame_loss(torch.rand(4, 4), torch.rand(4, 4))
