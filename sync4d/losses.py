"""Photometric loss and image metrics (Appendix A "Photometric Loss"):
L_rgb = 0.8 |F_hat - F|_1 + 0.2 DSSIM, DSSIM = (1 - SSIM) / 2 with 3x3 average-pool SSIM."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["ssim", "dssim", "photometric_loss", "psnr"]

_C1 = 0.01**2
_C2 = 0.03**2


def _check(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape or pred.dim() != 3:
        raise ValueError(
            f"pred/target: expected matching [H, W, C] images, got {list(pred.shape)} and "
            f"{list(target.shape)}"
        )


def ssim(pred: Tensor, target: Tensor, window: int = 3) -> Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1], with `window`x`window` average pooling
    (reflect padding keeps the output the input's size)."""
    _check(pred, target)
    x = pred.permute(2, 0, 1).unsqueeze(0)
    y = target.permute(2, 0, 1).unsqueeze(0)
    pad = window // 2

    def pool(v: Tensor) -> Tensor:
        return F.avg_pool2d(F.pad(v, (pad, pad, pad, pad), mode="reflect"), window, stride=1)

    mx, my = pool(x), pool(y)
    sxx = pool(x * x) - mx * mx
    syy = pool(y * y) - my * my
    sxy = pool(x * y) - mx * my
    num = (2 * mx * my + _C1) * (2 * sxy + _C2)
    den = (mx * mx + my * my + _C1) * (sxx + syy + _C2)
    return (num / den).mean()


def dssim(pred: Tensor, target: Tensor) -> Tensor:
    """(1 - SSIM) / 2."""
    return (1.0 - ssim(pred, target)) / 2.0


def photometric_loss(
    pred: Tensor, target: Tensor, lambda_l1: float = 0.8, lambda_dssim: float = 0.2
) -> Tensor:
    """0.8 * mean |pred - target| + 0.2 * DSSIM for [H, W, C] images."""
    _check(pred, target)
    return lambda_l1 * (pred - target).abs().mean() + lambda_dssim * dssim(pred, target)


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of [H, W, C] images in [0, 1]."""
    _check(pred, target)
    mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
