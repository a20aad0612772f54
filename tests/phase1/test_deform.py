"""Phase 1 deformation model: gamma(t), aa2q, quaternion products, Eqs. 2-4, zero init."""

from __future__ import annotations

import math

import torch

from sync4d.geometry import axis_angle_to_quat, quat_multiply
from sync4d.phase1.deform import (
    DeformationMLP,
    DeformConfig,
    deform_gaussians,
    position_encoding,
    time_encoding,
)


def _rotmat(q: torch.Tensor) -> torch.Tensor:
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    th = w.norm()
    k = w / th
    kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=w.dtype)
    return torch.eye(3, dtype=w.dtype) + math.sin(th) * kx + (1 - math.cos(th)) * kx @ kx


def test_time_encoding_matches_appendix_a() -> None:
    t = torch.tensor([0.0, 0.25, 1.0], dtype=torch.float64)
    g = time_encoding(t, bands=6)
    assert g.shape == (3, 13)
    assert torch.allclose(g[:, 0], t)
    for j in range(6):
        assert torch.allclose(g[:, 1 + 2 * j], torch.sin(2**j * math.pi * t))
        assert torch.allclose(g[:, 2 + 2 * j], torch.cos(2**j * math.pi * t))


def test_time_frequency_sets_the_lowest_band_and_pi_shares_the_ends() -> None:
    t = torch.tensor([0.0, 1.0], dtype=torch.float64)
    g = time_encoding(t, bands=6, frequency=1.0)
    for j in range(6):
        assert torch.allclose(g[:, 1 + 2 * j], torch.sin(2**j * t))
    # pi: the first and last instants differ in t and one cosine only; 1: in every band
    # (sin(2^j) != 0 for j < 6).
    pi = time_encoding(t, bands=6)
    assert int((~torch.isclose(pi[0], pi[1], atol=1e-9)).sum()) == 2
    assert int((~torch.isclose(g[0], g[1], atol=1e-9)).sum()) == 13
    # D_theta reads it: the same weights, another frequency, other offsets at t = 0.5.
    g0 = torch.Generator().manual_seed(0)
    a = DeformationMLP(DeformConfig(), g0)
    b = DeformationMLP(DeformConfig(time_frequency=1.0), torch.Generator().manual_seed(0))
    for m in (a, b):
        torch.nn.init.normal_(m.head.weight, generator=torch.Generator().manual_seed(1))
    x0, z = torch.zeros(2, 3), torch.zeros(2, 32)
    assert not torch.allclose(a(x0, z, 0.5)[0], b(x0, z, 0.5)[0])
    assert torch.allclose(a(x0, z, 0.0)[0], b(x0, z, 0.0)[0])  # at t = 0 both read zeros


def test_position_encoding_layout_and_input_width() -> None:
    x = torch.tensor([[0.1, -0.7, 1.3], [0.0, 0.5, -1.0]], dtype=torch.float64)
    assert torch.equal(position_encoding(x, 0), x)
    e = position_encoding(x, 3)
    assert e.shape == (2, 21)
    assert torch.equal(e[:, :3], x)
    for k in range(3):
        ang = 2**k * math.pi * x
        assert torch.allclose(e[:, 3 + 6 * k : 6 + 6 * k], torch.sin(ang))
        assert torch.allclose(e[:, 6 + 6 * k : 9 + 6 * k], torch.cos(ang))
    c = DeformConfig(position_bands=3)
    assert c.input_dim == 21 + 32 + 13
    mlp = DeformationMLP(c, torch.Generator().manual_seed(0))
    assert mlp.trunk[0].in_features == c.input_dim
    dx, dw, dl = mlp(x.float(), torch.zeros(2, 32), 0.5)
    assert dx.shape == dw.shape == dl.shape == (2, 3)


def test_axis_angle_to_quat_matches_rodrigues_and_zero() -> None:
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        w = torch.randn(3, generator=gen, dtype=torch.float64)
        assert torch.allclose(_rotmat(axis_angle_to_quat(w)), _rodrigues(w), atol=1e-10)
    q0 = axis_angle_to_quat(torch.zeros(2, 3))
    assert torch.allclose(q0, torch.tensor([[1.0, 0, 0, 0]] * 2))


def test_axis_angle_to_quat_gradient_at_and_near_zero() -> None:
    """The derivative at w = 0 is [0; I / 2] (D_theta's zero-initialised rotation head starts
    there; the axis-times-sine form had a zero gradient, so no rotation was ever learnt), and
    finite differences agree on both sides of the Taylor-series switch."""
    zero = torch.zeros(3, dtype=torch.float64)
    jac = torch.autograd.functional.jacobian(axis_angle_to_quat, zero)
    want = torch.cat([torch.zeros(1, 3), 0.5 * torch.eye(3)]).double()
    assert torch.allclose(jac, want, atol=1e-12)
    gen = torch.Generator().manual_seed(3)
    for scale in (1e-6, 3e-5, 2e-4, 0.3, 2.5):
        w = (torch.randn(3, generator=gen, dtype=torch.float64) * scale).requires_grad_()
        assert torch.autograd.gradcheck(axis_angle_to_quat, (w,), eps=1e-7, atol=1e-7)


def test_deformation_learns_a_rotation_from_the_zero_head() -> None:
    """One gradient step on a loss that wants the Gaussians turned moves the rotation head off
    zero (it did not before 2026-12-03)."""
    mlp = DeformationMLP(DeformConfig(), torch.Generator().manual_seed(0))
    x0 = torch.randn(8, 3, generator=torch.Generator().manual_seed(1))
    _, dw, _ = mlp(x0, torch.zeros(8, 32), 0.3)
    q = quat_multiply(axis_angle_to_quat(dw), torch.tensor([[1.0, 0, 0, 0]]).expand(8, 4))
    (-q[:, 3]).sum().backward()  # wants a turn about z
    assert mlp.head.weight.grad[3:6].abs().sum() > 0


def test_quat_multiply_composes_rotations() -> None:
    gen = torch.Generator().manual_seed(1)
    a, b = torch.randn(2, 4, generator=gen, dtype=torch.float64)
    a, b = a / a.norm(), b / b.norm()
    assert torch.allclose(_rotmat(quat_multiply(a, b)), _rotmat(a) @ _rotmat(b), atol=1e-12)


def test_zero_initialised_mlp_is_identity_deformation() -> None:
    torch.manual_seed(0)
    mlp = DeformationMLP()
    assert (
        sum(p.numel() for p in mlp.parameters())
        == 48 * 128 + 128 + 2 * (128 * 128 + 128) + 128 * 9 + 9
    )
    n = 7
    x0 = torch.randn(n, 3)
    z = torch.randn(n, 32) * 0.01
    q0 = torch.randn(n, 4)
    q0 = q0 / q0.norm(dim=-1, keepdim=True)
    log_s0 = torch.randn(n, 3)
    dx, dw, dl = mlp(x0, z, 0.3)
    assert dx.abs().max() == 0 and dw.abs().max() == 0 and dl.abs().max() == 0
    x, q, s = deform_gaussians(x0, q0, log_s0, dx, dw, dl)
    assert torch.equal(x, x0)
    assert torch.allclose(q, q0, atol=1e-7)
    assert torch.allclose(s, log_s0.exp())


def test_output_scales_and_gradients_flow() -> None:
    torch.manual_seed(0)
    mlp = DeformationMLP()
    torch.nn.init.constant_(mlp.head.bias, 1.0)
    x0, z = torch.randn(4, 3), torch.randn(4, 32)
    dx, dw, dl = mlp(x0, z, torch.full((4,), 0.5))
    assert torch.allclose(dx, torch.full_like(dx, 0.10))
    assert torch.allclose(dw, torch.full_like(dw, 0.10))
    assert torch.allclose(dl, torch.full_like(dl, 0.05))
    # Eq. 3 rotates the canonical quaternion by the delta rotation.
    q0 = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(4, 4)
    _, q, _ = deform_gaussians(x0, q0, torch.zeros(4, 3), dx, dw, dl)
    assert torch.allclose(q, axis_angle_to_quat(dw), atol=1e-6)
    (dx.sum() + dw.sum() + dl.sum()).backward()
    assert mlp.head.weight.grad.abs().sum() > 0


def test_bfloat16_hidden_layers_match_float32() -> None:
    """The bfloat16 option changes D_theta's arithmetic, not its function: outputs and
    weight gradients within 3 % of float32's, the outputs float32."""
    g = torch.Generator().manual_seed(3)
    mlp = DeformationMLP(DeformConfig(), g)
    with torch.no_grad():
        mlp.head.weight.normal_(0.0, 0.1, generator=g)
    x = torch.randn(500, 3, generator=g)
    z = torch.randn(500, 32, generator=g) * 0.1
    results = []
    for precision in ("float32", "bfloat16"):
        mlp.config = DeformConfig(precision=precision)
        mlp.zero_grad()
        out = mlp(x, z, 0.3)
        sum(o.square().sum() for o in out).backward()
        results.append((out, [p.grad.clone() for p in mlp.parameters()]))
    (ref, ref_grads), (low, low_grads) = results
    for a, b in zip(ref, low, strict=True):
        assert b.dtype == torch.float32
        assert (a - b).norm() <= 0.03 * a.norm()
    for a, b in zip(ref_grads, low_grads, strict=True):
        assert torch.isfinite(b).all()
        assert (a - b).norm() <= 0.03 * a.norm() + 1e-12


def test_bad_encoding_or_precision_is_rejected() -> None:
    """A checkpoint's deform_config reaches DeformationMLP unvalidated: an unknown precision
    must not fall back to float32 silently, nor a negative band count build a broken MLP."""
    import pytest

    with pytest.raises(ValueError, match="precision"):
        DeformationMLP(DeformConfig(precision="float16"))
    with pytest.raises(ValueError, match="position_bands"):
        DeformationMLP(DeformConfig(position_bands=-1))
