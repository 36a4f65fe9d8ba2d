"""Photometric losses of 3DGS training: L1, a fast separable SSIM, D-SSIM mix, PSNR.

SSIM follows upstream `utils/loss_utils.py::ssim` (11x11 Gaussian window, sigma 1.5, zero
padding of 5, C1 = 0.01^2, C2 = 0.03^2, mean over all pixels and channels), with the 2D window
applied as two 1D convolutions and the five local statistics filtered in one call.
"""
from __future__ import annotations

import math
from typing import Dict, Tuple

import torch
import torch.nn.functional as F

_C1 = 0.01 ** 2
_C2 = 0.03 ** 2
_WINDOW_CACHE: Dict[Tuple[int, float, torch.dtype, str], torch.Tensor] = {}


def _gauss_1d(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    key = (size, sigma, dtype, str(device))
    w = _WINDOW_CACHE.get(key)
    if w is None:
        x = torch.arange(size, dtype=torch.float64) - size // 2
        g = torch.exp(-(x ** 2) / (2.0 * sigma ** 2))
        w = (g / g.sum()).to(dtype=dtype, device=device)
        _WINDOW_CACHE[key] = w
    return w


def _filter(x: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian filter of x [N, C, H, W] with zero padding (same size)."""
    C = x.shape[1]
    k = g.numel()
    pad = k // 2
    wx = g.view(1, 1, 1, k).expand(C, 1, 1, k)
    wy = g.view(1, 1, k, 1).expand(C, 1, k, 1)
    x = F.conv2d(x, wx, padding=(0, pad), groups=C)
    return F.conv2d(x, wy, padding=(pad, 0), groups=C)


def ssim(img1: torch.Tensor, img2: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two images [C, H, W] (or [N, C, H, W]); differentiable in both."""
    if img1.shape != img2.shape:
        raise ValueError(f"ssim: images must have the same shape, got {list(img1.shape)} and {list(img2.shape)}")
    if img1.ndim == 3:
        img1, img2 = img1.unsqueeze(0), img2.unsqueeze(0)
    C = img1.shape[1]
    g = _gauss_1d(window_size, sigma, img1.dtype, img1.device)
    stats = _filter(torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2], dim=1), g)
    mu1, mu2, s11, s22, s12 = stats.split(C, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    sigma1_sq = s11 - mu1_sq
    sigma2_sq = s22 - mu2_sq
    sigma12 = s12 - mu12
    num = (2 * mu12 + _C1) * (2 * sigma12 + _C2)
    den = (mu1_sq + mu2_sq + _C1) * (sigma1_sq + sigma2_sq + _C2)
    return (num / den).mean()


@torch.no_grad()
def ssim_value_and_grad(x: torch.Tensor, y: torch.Tensor, window_size: int = 11, sigma: float = 1.5):
    """(mean SSIM, d mean SSIM / d x) of images [C, H, W], without autograd.

    The Gaussian window is symmetric and zero-padded, so the filter is its own adjoint:
    d/dx = G(dS/dmu1) + 2 x G(dS/ds11) + y G(dS/ds12) with, per pixel (S = A1 A2 / (B1 B2)),
    dS/dmu1 = 2 mu2 (A2 - A1) / (B1 B2) - 2 mu1 S (1/B1 - 1/B2), dS/ds11 = -S / B2,
    dS/ds12 = 2 A1 / (B1 B2) (each divided by the number of elements for the mean).
    """
    if x.shape != y.shape or x.ndim != 3:
        raise ValueError(f"ssim_value_and_grad: images must be [C, H, W] of the same shape, got "
                         f"{list(x.shape)} and {list(y.shape)}")
    C = x.shape[0]
    g = _gauss_1d(window_size, sigma, x.dtype, x.device)
    stats = _filter(torch.cat([x, y, x * x, y * y, x * y], dim=0).unsqueeze(0), g)[0]
    mu1, mu2, s11, s22, s12 = stats.split(C, dim=0)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    A1 = 2 * mu12 + _C1
    A2 = 2 * (s12 - mu12) + _C2
    B1 = mu1_sq + mu2_sq + _C1
    B2 = (s11 - mu1_sq) + (s22 - mu2_sq) + _C2
    D = B1 * B2
    S = A1 * A2 / D
    n = float(S.numel())
    d_mu1 = (2 * mu2 * (A2 - A1) / D - 2 * mu1 * S * (1.0 / B1 - 1.0 / B2)) / n
    d_s11 = -S / B2 / n
    d_s12 = 2 * A1 / D / n
    f = _filter(torch.cat([d_mu1, d_s11, d_s12], dim=0).unsqueeze(0), g)[0]
    g_mu1, g_s11, g_s12 = f.split(C, dim=0)
    grad = g_mu1 + 2 * x * g_s11 + y * g_s12
    return S.mean(), grad


@torch.no_grad()
def photometric_loss_and_grad(render: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2):
    """(loss, d loss / d render) of `photometric_loss` without autograd (faster on CPU).

    L1's gradient is sign(render - gt) / n (0 where equal, as torch's abs).
    """
    n = float(render.numel())
    diff = render - gt
    loss = (1.0 - lambda_dssim) * diff.abs().mean()
    grad = torch.sign(diff).mul_((1.0 - lambda_dssim) / n)
    if lambda_dssim > 0:
        s, gs = ssim_value_and_grad(render, gt)
        loss = loss + lambda_dssim * (1.0 - s)
        grad.add_(gs, alpha=-lambda_dssim)
    return loss, grad


def l1_loss(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a - b).abs().mean()


def photometric_loss(render: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """Upstream 3DGS loss: (1 - lambda) L1 + lambda (1 - SSIM)."""
    loss = (1.0 - lambda_dssim) * l1_loss(render, gt)
    if lambda_dssim > 0:
        loss = loss + lambda_dssim * (1.0 - ssim(render, gt))
    return loss


def psnr(render: torch.Tensor, gt: torch.Tensor) -> float:
    """PSNR in dB of images in [0, 1] (the render is clamped to [0, 1] first, as upstream metrics)."""
    mse = (render.detach().clamp(0.0, 1.0) - gt).pow(2).mean().item()
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)
