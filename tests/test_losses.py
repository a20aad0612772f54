"""Photometric loss and metrics."""

from __future__ import annotations

import math

import pytest
import torch

from sync4d.losses import dssim, photometric_loss, psnr, ssim


def test_ssim_identity_and_degradation() -> None:
    g = torch.Generator().manual_seed(0)
    img = torch.rand(24, 20, 3, generator=g)
    assert ssim(img, img).item() == pytest.approx(1.0, abs=1e-6)
    assert dssim(img, img).item() == pytest.approx(0.0, abs=1e-6)
    noisy = (img + 0.1 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    noisier = (img + 0.3 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    assert 1.0 > ssim(img, noisy).item() > ssim(img, noisier).item()


def test_photometric_loss_weights_and_gradient() -> None:
    a = torch.zeros(8, 8, 3, requires_grad=True)
    b = torch.full((8, 8, 3), 0.5)
    loss = photometric_loss(a, b)
    expected = 0.8 * 0.5 + 0.2 * dssim(a.detach(), b).item()
    assert loss.item() == pytest.approx(expected, rel=1e-6)
    loss.backward()
    assert a.grad is not None and torch.isfinite(a.grad).all()


def test_psnr_and_shape_errors() -> None:
    a = torch.zeros(4, 4, 3)
    assert psnr(a, a) == math.inf
    assert psnr(a, torch.full_like(a, 0.1)) == pytest.approx(20.0, rel=1e-5)
    with pytest.raises(ValueError, match="pred/target"):
        photometric_loss(a, torch.zeros(4, 5, 3))
