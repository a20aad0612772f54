"""Photometric loss (Appendix A "Photometric Loss"):
L_rgb = 0.8 |F_hat - F|_1 + 0.2 DSSIM, DSSIM = (1 - SSIM) / 2 with 3x3 average-pool SSIM.

`photometric_loss` runs the fused Rust kernel (value and gradient in one parallel pass) for CPU
float32/float64 images; `photometric_loss_reference` is the plain torch composition it is tested
against (SSIM from `sync4d.metrics`), and the fallback for other devices and dtypes."""

from __future__ import annotations

import torch
from torch import Tensor

from sync4d import _core
from sync4d.metrics.image import check_image_pair, dssim
from sync4d.raster import thread_count

__all__ = ["photometric_loss", "photometric_loss_reference"]


def photometric_loss_reference(
    pred: Tensor, target: Tensor, lambda_l1: float = 0.8, lambda_dssim: float = 0.2
) -> Tensor:
    """0.8 * mean |pred - target| + 0.2 * DSSIM for [H, W, C] images, composed of torch ops."""
    check_image_pair(pred, target)
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
            x, y, height=h, width=w, channels=c, l1=float(lambda_l1),
            dssim=float(lambda_dssim), window=3, want_grad=want_grad, threads=threads,
        )  # fmt: skip
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
    check_image_pair(pred, target)
    fused = (
        pred.device.type == "cpu"
        and target.device.type == "cpu"
        and pred.dtype in (torch.float32, torch.float64)
        and not target.requires_grad
    )
    if not fused:
        return photometric_loss_reference(pred, target, lambda_l1, lambda_dssim)
    return _FusedLoss.apply(pred, target, lambda_l1, lambda_dssim, thread_count(threads))
