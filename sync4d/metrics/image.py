"""Image metrics of [H, W, C] images in [0, 1], plain torch: PSNR, and SSIM with 3x3 average
pooling (the form the photometric loss uses, Appendix A); LPIPS-Alex is in `sync4d.metrics.lpips`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["check_image_pair", "dssim", "psnr", "ssim"]

_C1 = 0.01**2
_C2 = 0.03**2


def check_image_pair(pred: Tensor, target: Tensor) -> None:
    """Raise ValueError unless `pred` and `target` are [H, W, C] images of one shape."""
    if pred.shape != target.shape or pred.dim() != 3:
        raise ValueError(
            f"pred/target: expected matching [H, W, C] images, got {list(pred.shape)} and "
            f"{list(target.shape)}"
        )


def _box_filter(v: Tensor, window: int) -> Tensor:
    """Mean over `window`x`window` neighbourhoods of [B, H, W] maps (reflect padding keeps the
    size); separable shifted-slice sums, several times faster on the CPU than avg_pool2d."""
    pad = window // 2
    h, w = v.shape[-2:]
    v = F.pad(v.unsqueeze(0), (pad, pad, pad, pad), mode="reflect").squeeze(0)
    rows = v[:, :, 0:w]
    for k in range(1, window):
        rows = rows + v[:, :, k : k + w]
    out = rows[:, 0:h]
    for k in range(1, window):
        out = out + rows[:, k : k + h]
    return out * (1.0 / (window * window))


def ssim(pred: Tensor, target: Tensor, window: int = 3) -> Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1], with `window`x`window` average pooling
    (reflect padding keeps the output the input's size)."""
    check_image_pair(pred, target)
    x = pred.permute(2, 0, 1)
    y = target.permute(2, 0, 1)
    c = x.shape[0]
    stats = _box_filter(torch.cat([x, y, x * x, y * y, x * y]), window)
    mx, my, exx, eyy, exy = stats.split(c)
    mxx, myy, mxy = mx * mx, my * my, mx * my
    num = (2 * mxy + _C1) * (2 * (exy - mxy) + _C2)
    den = (mxx + myy + _C1) * ((exx - mxx) + (eyy - myy) + _C2)
    return (num / den).mean()


def dssim(pred: Tensor, target: Tensor) -> Tensor:
    """(1 - SSIM) / 2."""
    return (1.0 - ssim(pred, target)) / 2.0


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of [H, W, C] images in [0, 1]."""
    check_image_pair(pred, target)
    mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
