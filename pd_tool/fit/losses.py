"""Image losses for fitting: SSIM and the per-frame loss lambda * L1 + (1 - lambda) * D-SSIM.

SSIM follows the 3D Gaussian Splatting / PhysDreamer training code, so that losses compare
with theirs: an 11 x 11 Gaussian window (sigma 1.5 px), local statistics by convolution with
ZERO padding (the window keeps its weights at the border; pixels outside the image count as
0), C1 = 0.01^2, C2 = 0.03^2 (images in 0-1), one map per colour channel, averaged over the
channels. D-SSIM = 1 - SSIM (the 3DGS form, range 0-2; not (1 - SSIM) / 2).

Image layouts: [H, W, 3] (one frame, channels last, as the rasteriser returns it) or
[B, 3, H, W] (batch, channels first). Values are linear 0-1 floats.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

SSIM_C1 = 0.01 ** 2  # (K1 * L)^2 with K1 = 0.01, dynamic range L = 1
SSIM_C2 = 0.03 ** 2  # (K2 * L)^2 with K2 = 0.03
DEFAULT_WINDOW = 11  # px, side of the Gaussian window
DEFAULT_SIGMA = 1.5  # px, std of the Gaussian window
DEFAULT_LAMBDA = 0.1  # weight of L1 in the frame loss (paper)


def gaussian_window_1d(window: int, sigma: float, *, dtype=torch.float32, device=None) -> Tensor:
    """Normalised 1D Gaussian [window], centred on index window // 2 (sums to 1)."""
    if window < 1 or window % 2 == 0:
        raise ValueError(f"SSIM window must be a positive odd number of pixels, got {window}")
    if not sigma > 0:
        raise ValueError(f"SSIM sigma must be > 0 px, got {sigma}")
    x = torch.arange(window, dtype=dtype, device=device) - window // 2
    g = torch.exp(-(x * x) / (2.0 * sigma * sigma))
    return g / g.sum()


def _to_bchw(img: Tensor, name: str) -> Tensor:
    if img.dim() == 3:
        if img.shape[-1] != 3:
            raise ValueError(f"{name} as [H, W, 3] expected, got {tuple(img.shape)}")
        return img.permute(2, 0, 1)[None]
    if img.dim() == 4:
        if img.shape[1] != 3:
            raise ValueError(f"{name} as [B, 3, H, W] expected, got {tuple(img.shape)}")
        return img
    raise ValueError(f"{name} must be [H, W, 3] or [B, 3, H, W], got {tuple(img.shape)}")


def ssim_map(img1: Tensor, img2: Tensor, window: int = DEFAULT_WINDOW,
             sigma: float = DEFAULT_SIGMA) -> Tensor:
    """Per-pixel SSIM, averaged over the colour channels.

    Args:
        img1, img2: [H, W, 3] or [B, 3, H, W], 0-1, same shape, dtype and device.
        window: odd window side in px; sigma: Gaussian std in px.
    Returns:
        [H, W] for [H, W, 3] input, [B, H, W] for [B, 3, H, W]; 1 where the images agree.
    """
    if img1.shape != img2.shape:
        raise ValueError(f"SSIM needs images of one shape, got {tuple(img1.shape)} and {tuple(img2.shape)}")
    single = img1.dim() == 3
    x, y = _to_bchw(img1, "img1"), _to_bchw(img2, "img2")
    c = x.shape[1]
    g = gaussian_window_1d(window, sigma, dtype=x.dtype, device=x.device)
    # The 2D window is the outer product g g^T, so two 1D passes give the same result as the
    # 2D convolution (zero padding included) at 2k instead of k^2 taps per pixel. The five
    # moments go through one grouped convolution.
    stack = torch.cat([x, y, x * x, y * y, x * y], dim=1)  # [B, 5C, H, W]
    k = 5 * c
    h_pass = F.conv2d(stack, g.view(1, 1, 1, -1).expand(k, 1, 1, window), padding=(0, window // 2), groups=k)
    blur = F.conv2d(h_pass, g.view(1, 1, -1, 1).expand(k, 1, window, 1), padding=(window // 2, 0), groups=k)
    mu1, mu2, e11, e22, e12 = blur.split(c, dim=1)
    mu11, mu22, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s11, s22, s12 = e11 - mu11, e22 - mu22, e12 - mu12
    num = (2.0 * mu12 + SSIM_C1) * (2.0 * s12 + SSIM_C2)
    den = (mu11 + mu22 + SSIM_C1) * (s11 + s22 + SSIM_C2)
    m = (num / den).mean(dim=1)  # [B, H, W]
    return m[0] if single else m


def ssim(img1: Tensor, img2: Tensor, window: int = DEFAULT_WINDOW, sigma: float = DEFAULT_SIGMA) -> Tensor:
    """Mean SSIM over all pixels (and the batch): scalar tensor, 1 for identical images.

    Args as `ssim_map`.
    """
    return ssim_map(img1, img2, window, sigma).mean()


def _check_mask(mask: Tensor, hw: tuple[int, ...]) -> Tensor:
    if tuple(mask.shape) != tuple(hw):
        raise ValueError(f"mask must be {list(hw)} to match the frame, got {list(mask.shape)}")
    return mask.to(torch.float64 if mask.dtype == torch.float64 else torch.float32)


def frame_loss(pred: Tensor, target: Tensor, mask: Tensor | None = None,
               lam: float = DEFAULT_LAMBDA, *, window: int = DEFAULT_WINDOW,
               sigma: float = DEFAULT_SIGMA) -> Tensor:
    """lam * L1 + (1 - lam) * (1 - SSIM) for one frame (or a batch of frames).

    Without a mask both terms are means over every pixel (L1 also over the 3 channels).
    With a mask both are weighted means over the mask: L1 = sum(m |pred - target|) /
    (3 sum(m)); SSIM = sum(m * ssim_map) / sum(m). The SSIM map itself is computed on the
    whole, unmasked images, so a window at the silhouette sees the background of both
    images: a silhouette in the wrong place costs SSIM. Soft masks (0-1) weight pixels;
    an empty mask gives a loss of 0 (nothing to compare).

    Args:
        pred: rendered frame [H, W, 3] (or [B, H, W, 3]), 0-1.
        target: reference frame, same shape.
        mask: [H, W] (or [B, H, W]) weights in 0-1 (bool allowed), or None.
        lam: weight of L1 (paper: 0.1).
    Returns:
        scalar tensor, differentiable in pred (and target).
    """
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"lam (weight of L1) must be in [0, 1], got {lam}")
    if pred.shape != target.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} differ in shape")
    if pred.dim() not in (3, 4) or pred.shape[-1] != 3:
        raise ValueError(f"frames must be [H, W, 3] or [B, H, W, 3], got {tuple(pred.shape)}")
    # [.., H, W, 3] -> [B, 3, H, W] for the convolution
    p4 = pred[None] if pred.dim() == 3 else pred
    t4 = target[None] if target.dim() == 3 else target
    smap = ssim_map(p4.permute(0, 3, 1, 2), t4.permute(0, 3, 1, 2), window, sigma)  # [B, H, W]
    l1 = (p4 - t4).abs()  # [B, H, W, 3]
    if mask is None:
        l1_term, ssim_term = l1.mean(), smap.mean()
    else:
        m = _check_mask(mask, pred.shape[:-1]).to(pred.device)
        m = m[None] if m.dim() == 2 else m
        total = m.sum()
        w = total.clamp_min(1e-12)  # empty mask: numerators are 0 too
        l1_term = (l1 * m[..., None]).sum() / (3.0 * w)
        # + 1 for an empty mask so that 1 - SSIM is 0 too; no host sync (GPU stays async)
        ssim_term = (smap * m).sum() / w + (total == 0).to(smap.dtype)
    return lam * l1_term + (1.0 - lam) * (1.0 - ssim_term)
