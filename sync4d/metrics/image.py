"""Image metrics of [H, W, C] images in [0, 1], plain torch: PSNR; the standard SSIM that
papers report (`ssim_gaussian`: 11x11 Gaussian window, sigma 1.5, valid windows); and the SSIM
with 3x3 average pooling that the photometric loss uses (`ssim`, `dssim`, Appendix A).
LPIPS-Alex is in `sync4d.metrics.lpips`. docs/metrics.md defines each one.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["GAUSSIAN_WINDOW", "check_image_pair", "dssim", "psnr", "ssim", "ssim_gaussian"]

_C1 = 0.01**2
_C2 = 0.03**2
#: Side of the standard SSIM's Gaussian window, in pixels (scikit-image: 2 * int(3.5 * 1.5 +
#: 0.5) + 1 = 11 taps, i.e. a truncation at 3.5 sigma; torchmetrics' default kernel_size).
GAUSSIAN_WINDOW = 11
GAUSSIAN_SIGMA = 1.5


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
    (reflect padding keeps the output the input's size): the form of the training loss
    (`dssim`, Appendix A). Not the SSIM papers report; that is `ssim_gaussian`."""
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


def _gaussian_taps(dtype: torch.dtype) -> Tensor:
    """The normalised 1-D Gaussian [GAUSSIAN_WINDOW] with sigma GAUSSIAN_SIGMA, centred."""
    r = GAUSSIAN_WINDOW // 2
    x = torch.arange(-r, r + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / GAUSSIAN_SIGMA) ** 2)
    return (k / k.sum()).to(dtype)


def _gaussian_filter_valid(v: Tensor) -> Tensor:
    """Weighted means of [B, H, W] maps under the separable Gaussian window at every window
    position fully inside the map: [B, H - 10, W - 10]. Shifted-slice sums accumulated in
    place: several times faster on the CPU than conv2d in float64."""
    taps = _gaussian_taps(v.dtype).tolist()
    n = len(taps)
    h, w = v.shape[-2:]
    rows = v[:, :, 0 : w - n + 1] * taps[0]
    for i in range(1, n):
        rows.add_(v[:, :, i : i + w - n + 1], alpha=taps[i])
    out = rows[:, 0 : h - n + 1] * taps[0]
    for i in range(1, n):
        out.add_(rows[:, i : i + h - n + 1], alpha=taps[i])
    return out


def ssim_gaussian(pred: Tensor, target: Tensor) -> Tensor:
    """The standard SSIM (Wang et al. 2004) of two [H, W, C] images in [0, 1]: a 0-d float64
    tensor (differentiable in `pred`).

    Per channel: local means, population variances and covariance under a separable 11-tap
    Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, data range 1; the SSIM map is averaged
    over the valid windows only (the (H - 10) x (W - 10) windows fully inside the image), then
    over channels. This is what scikit-image's ``structural_similarity(..., gaussian_weights=
    True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1)`` and
    torchmetrics' default ``structural_similarity_index_measure`` compute. The original 3DGS
    ``ssim`` (utils/loss_utils.py; Deformable-3DGS, 4DGaussians, SC-GS score with it) zero-pads
    instead and averages over all H x W pixels, so its values differ slightly near the border
    (docs/metrics.md gives the measured difference). Computed in float64.
    Raises ValueError for images smaller than 11 pixels on a side."""
    check_image_pair(pred, target)
    h, w, c = pred.shape
    if min(h, w) < GAUSSIAN_WINDOW:
        raise ValueError(
            f"SSIM: the {GAUSSIAN_WINDOW}x{GAUSSIAN_WINDOW} Gaussian window needs images of at "
            f"least {GAUSSIAN_WINDOW} pixels on a side, got {w}x{h}"
        )
    x = pred.to(torch.float64).permute(2, 0, 1)
    y = target.to(torch.float64).permute(2, 0, 1)
    stats = _gaussian_filter_valid(torch.cat([x, y, x * x, y * y, x * y]))
    mx, my, exx, eyy, exy = stats.split(c)
    vx, vy, cxy = exx - mx * mx, eyy - my * my, exy - mx * my
    num = (2 * mx * my + _C1) * (2 * cxy + _C2)
    den = (mx * mx + my * my + _C1) * (vx + vy + _C2)
    return (num / den).mean()


def dssim(pred: Tensor, target: Tensor) -> Tensor:
    """(1 - SSIM) / 2 with the 3x3 box SSIM (`ssim`): the training loss's D-SSIM term."""
    return (1.0 - ssim(pred, target)) / 2.0


def psnr(pred: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of [H, W, C] images in [0, 1]: `pred` clamped to
    [0, 1], the MSE averaged over all pixels and channels, peak 1; inf for identical images."""
    check_image_pair(pred, target)
    mse = float(((pred.detach().clamp(0, 1) - target) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * torch.log10(torch.tensor(mse)).item()
