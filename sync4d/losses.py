"""Photometric loss and image metrics (Appendix A "Photometric Loss"):
L_rgb = 0.8 |F_hat - F|_1 + 0.2 DSSIM, DSSIM = (1 - SSIM) / 2 with 3x3 average-pool SSIM.

`photometric_loss` runs the fused Rust kernel (value and gradient in one parallel pass) for CPU
float32/float64 images; `photometric_loss_reference` is the plain torch composition it is tested
against, and the fallback for other devices and dtypes."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from sync4d import _core
from sync4d.raster import _threads

__all__ = ["ssim", "dssim", "photometric_loss", "photometric_loss_reference", "psnr"]

_C1 = 0.01**2
_C2 = 0.03**2


def _check(pred: Tensor, target: Tensor) -> None:
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
    _check(pred, target)
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


def photometric_loss_reference(
    pred: Tensor, target: Tensor, lambda_l1: float = 0.8, lambda_dssim: float = 0.2
) -> Tensor:
    """0.8 * mean |pred - target| + 0.2 * DSSIM for [H, W, C] images, composed of torch ops."""
    _check(pred, target)
    return lambda_l1 * (pred - target).abs().mean() + lambda_dssim * dssim(pred, target)


class _FusedLoss(torch.autograd.Function):
    """The Rust kernel computes the loss and dL/d pred together; backward scales the latter."""

    @staticmethod
    def forward(ctx, pred, target, lambda_l1, lambda_dssim, threads):  # type: ignore[override]
        h, w, c = pred.shape
        want_grad = bool(ctx.needs_input_grad[0])
        x = pred.detach().contiguous().numpy().reshape(-1)
        y = target.detach().to(pred.dtype).contiguous().numpy().reshape(-1)
        loss, _, _, grad = _core.photometric_loss(
            x, y, h, w, c, float(lambda_l1), float(lambda_dssim), 3, want_grad, threads
        )
        if want_grad:
            ctx.save_for_backward(torch.from_numpy(grad).view(h, w, c))
        return torch.tensor(loss, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad_loss):  # type: ignore[override]
        (grad,) = ctx.saved_tensors
        return grad * grad_loss, None, None, None, None


def photometric_loss(
    pred: Tensor,
    target: Tensor,
    lambda_l1: float = 0.8,
    lambda_dssim: float = 0.2,
    threads: int | None = None,
) -> Tensor:
    """0.8 * mean |pred - target| + 0.2 * DSSIM for [H, W, C] images (scalar tensor with a
    gradient for `pred`). `threads`: CPU threads for the fused kernel (None: all)."""
    _check(pred, target)
    fused = (
        pred.device.type == "cpu"
        and target.device.type == "cpu"
        and pred.dtype in (torch.float32, torch.float64)
        and not target.requires_grad
    )
    if not fused:
        return photometric_loss_reference(pred, target, lambda_l1, lambda_dssim)
    return _FusedLoss.apply(pred, target, lambda_l1, lambda_dssim, _threads(threads))


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of [H, W, C] images in [0, 1]."""
    _check(pred, target)
    mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
