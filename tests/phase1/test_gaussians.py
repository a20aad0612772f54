"""Phase 1 scene model: Appendix A initialisation and a differentiable render at time t."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sync4d.data.scene import Camera
from sync4d.phase1.gaussians import SH_C0, DeformableGaussians


def _camera(w: int = 32, h: int = 24) -> Camera:
    vm = np.eye(4)
    vm[2, 3] = 3.0  # world origin 3 units in front
    return Camera(vm, 30.0, 30.0, w / 2, h / 2, w, h)


def test_initialisation_follows_appendix_a() -> None:
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(50, 3, generator=g) * 0.3
    cols = torch.rand(50, 3, generator=g)
    m = DeformableGaussians(pts, cols, generator=g)
    assert torch.equal(m.means.data, pts)
    assert torch.equal(m.quats.data[:, 0], torch.ones(50)) and m.quats.data[:, 1:].abs().max() == 0
    assert torch.allclose(m.log_scales.data, torch.full((50, 3), math.log(0.02)))
    assert torch.allclose(torch.sigmoid(m.opacity_logits.data), torch.full((50,), 0.1))
    assert torch.allclose(m.sh_dc.data[:, 0] * SH_C0 + 0.5, cols, atol=1e-6)
    assert m.sh_rest.shape == (50, 15, 3) and m.sh_rest.abs().max() == 0
    assert m.embeddings.std().item() == pytest.approx(0.01, rel=0.2)


def test_render_at_time_is_differentiable_and_starts_static() -> None:
    g = torch.Generator().manual_seed(1)
    m = DeformableGaussians.random_in_box(
        200, -torch.ones(3) * 0.5, torch.ones(3) * 0.5, generator=g
    )
    cam = _camera()
    a = m.render(cam, 0.0, threads=1)
    b = m.render(cam, 0.9, threads=1)
    assert a.features.shape == (24, 32, 3)
    assert torch.equal(a.features, b.features)  # zero-initialised D_theta: identity deformation
    target = torch.rand(24, 32, 3, generator=g)
    loss = (b.features - target).abs().mean()
    loss.backward()
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "embeddings"):
        grad = getattr(m, name).grad
        assert grad is not None and torch.isfinite(grad).all(), name
    assert m.means.grad.abs().sum() > 0
    assert m.deform.head.weight.grad.abs().sum() > 0  # time-dependent path is trained


def test_bad_points_are_rejected() -> None:
    with pytest.raises(ValueError, match="points: expected shape"):
        DeformableGaussians(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="points: contains NaN"):
        DeformableGaussians(torch.full((5, 3), float("nan")))
    with pytest.raises(ValueError, match="colors: expected shape"):
        DeformableGaussians(torch.zeros(5, 3), torch.zeros(4, 3))
