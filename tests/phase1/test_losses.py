"""Photometric loss and metrics."""

from __future__ import annotations

import math

import pytest
import torch

from sync4d import _core
from sync4d.metrics import dssim, psnr, ssim
from sync4d.phase1.losses import photometric_loss, photometric_loss_reference


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


@pytest.mark.parametrize("shape", [(2, 2, 1), (7, 9, 3), (40, 33, 4)])
def test_fused_loss_matches_the_torch_composition(shape: tuple[int, int, int]) -> None:
    g = torch.Generator().manual_seed(1)
    pred = torch.rand(shape, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(shape, generator=g, dtype=torch.float64)
    fused = photometric_loss(pred, target, 0.7, 0.3, threads=2)
    (g_fused,) = torch.autograd.grad(2.5 * fused, pred)
    ref = photometric_loss_reference(pred, target, 0.7, 0.3)
    (g_ref,) = torch.autograd.grad(2.5 * ref, pred)
    assert fused.dtype == torch.float64
    assert fused.item() == pytest.approx(ref.item(), abs=1e-12)
    torch.testing.assert_close(g_fused, g_ref, rtol=1e-9, atol=1e-14)
    # float32 agrees with float64 to float32 precision.
    p32 = pred.detach().float().requires_grad_(True)
    l32 = photometric_loss(p32, target.float(), 0.7, 0.3)
    l32.backward()
    assert l32.item() == pytest.approx(ref.item(), abs=1e-5)
    assert p32.grad is not None
    torch.testing.assert_close(
        p32.grad.double(), g_ref / 2.5, rtol=1e-3, atol=1e-3 * g_ref.abs().max().item()
    )


def test_fused_loss_rejects_non_finite_renders() -> None:
    pred = torch.rand(6, 6, 3)
    pred[2, 3, 1] = float("nan")
    with pytest.raises(ValueError, match="pred: non-finite"):
        photometric_loss(pred, torch.rand(6, 6, 3))


def test_fused_loss_bad_inputs_are_named() -> None:
    img = torch.rand(6, 6, 3)
    with pytest.raises(ValueError, match="threads"):
        photometric_loss(img, img, threads=0)
    with pytest.raises(ValueError, match="too small for a 3x3 SSIM window"):
        photometric_loss(torch.rand(1, 6, 3), torch.rand(1, 6, 3))
    with pytest.raises(ValueError, match="target: expected an array of the same dtype"):
        _core.photometric_loss(
            img.numpy().ravel(), img.double().numpy().ravel(), height=6, width=6, channels=3,
            l1=0.8, dssim=0.2, window=3, want_grad=True, threads=1,
        )  # fmt: skip
