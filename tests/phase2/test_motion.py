"""M_phi (sync4d.phase2.motion): rotations, the three parameterisations, interpolation, losses."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from sync4d.geometry import axis_angle_to_quat, quat_slerp, rotvec_to_matrix
from sync4d.phase2.motion import MotionConfig, cosine_lr, make_motion, quat_to_matrix

TIMES = np.linspace(0.0, 1.0, 5)


def test_rotvec_to_matrix_matches_quaternion_path_and_is_orthonormal():
    g = torch.Generator().manual_seed(0)
    w = torch.randn(64, 3, generator=g, dtype=torch.float64) * 2.0
    w[0] = 0.0
    w[1] = torch.tensor([1e-6, -2e-6, 5e-7], dtype=torch.float64)
    r = rotvec_to_matrix(w)
    assert torch.allclose(r, quat_to_matrix(axis_angle_to_quat(w)), atol=1e-10)
    eye = torch.eye(3, dtype=torch.float64).expand_as(r)
    assert torch.allclose(r @ r.transpose(-1, -2), eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(64, dtype=torch.float64))
    # Rotating about z by 90 degrees maps x to y.
    rz = rotvec_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    assert torch.allclose(rz @ torch.tensor([1.0, 0, 0], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)  # fmt: skip


def test_rotvec_to_matrix_gradient_is_finite_and_correct_near_zero():
    for scale in (0.0, 1e-5, 0.3, 2.5):
        w = (torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64) * scale).requires_grad_()
        assert torch.autograd.gradcheck(rotvec_to_matrix, (w,), eps=1e-7, atol=1e-6)


def test_slerp_endpoints_midpoint_and_shorter_arc():
    q0 = axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.0], dtype=torch.float64))
    q1 = axis_angle_to_quat(torch.tensor([0.0, 0.0, 1.2], dtype=torch.float64))
    assert torch.allclose(quat_slerp(q0, q1, 0.0), q0)
    assert torch.allclose(quat_slerp(q0, q1, 1.0), q1)
    mid = quat_slerp(q0, q1, 0.5)
    assert torch.allclose(mid, axis_angle_to_quat(torch.tensor([0.0, 0.0, 0.6],
                                                               dtype=torch.float64)))  # fmt: skip
    # -q1 is the same rotation: the result must not take the long way round.
    assert torch.allclose(quat_to_matrix(quat_slerp(q0, -q1, 0.5)), quat_to_matrix(mid))
    # Identical inputs do not divide by zero.
    assert torch.allclose(quat_slerp(q1, q1, 0.3), q1)


@pytest.mark.parametrize("kind", ["se3", "affine", "mlp"])
def test_every_kind_starts_near_identity_and_applies_per_object(kind):
    m = make_motion(MotionConfig(kind=kind), 3, TIMES)
    x0 = torch.randn(10, 3)
    labels = torch.tensor([0, 1, 2, 0, 1, 2, 0, 1, 2, 0])
    xt = m(x0, labels, 0.5)
    assert xt.shape == (10, 3)
    assert torch.allclose(xt, x0, atol=1e-3)  # init sigma 1e-4 (tables) or zero output (mlp)
    assert m.rigid == (kind != "affine")


def test_se3_table_transform_and_interpolation():
    m = make_motion(MotionConfig(kind="se3", init_std=0.0), 2, TIMES)
    with torch.no_grad():
        m.rotvecs[1, 1] = torch.tensor([0.0, 0.0, 0.4])
        m.translations[1, 1] = torch.tensor([1.0, 0.0, 0.0])
    x0 = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    labels = torch.tensor([0, 1])
    at = m(x0, labels, float(TIMES[1]))
    assert torch.allclose(at[0], x0[0])
    expect = torch.tensor([math.cos(0.4) + 1.0, math.sin(0.4), 0.0])
    assert torch.allclose(at[1], expect, atol=1e-6)
    # Halfway between frame 0 (identity) and frame 1: half the angle, half the translation.
    t = 0.5 * float(TIMES[0] + TIMES[1])
    half = m(x0, labels, t)[1]
    assert torch.allclose(half, torch.tensor([math.cos(0.2) + 0.5, math.sin(0.2), 0.0]), atol=1e-6)
    # Times outside the stored range clamp to the ends.
    assert torch.allclose(m(x0, labels, -1.0), m(x0, labels, 0.0))
    a, b = m.trajectory()
    assert a.shape == (2, len(TIMES), 3, 3) and b.shape == (2, len(TIMES), 3)


def test_smoothness_and_identity_prior():
    m = make_motion(MotionConfig(kind="se3", init_std=0.0), 2, TIMES)
    with torch.no_grad():
        m.translations[0, 2] = torch.tensor([0.0, 0.3, 0.0])
        m.rotvecs[1, 2] = torch.tensor([0.1, 0.0, 0.0])
    assert float(m.smoothness(0).detach()) == 0.0
    assert math.isclose(float(m.smoothness(2).detach()), (0.09 + 0.01) / 2, rel_tol=1e-6)
    assert math.isclose(float(m.smoothness(3).detach()), (0.09 + 0.01) / 2, rel_tol=1e-6)
    static = torch.tensor([True, False])
    assert math.isclose(float(m.identity_prior(2, static).detach()), 0.09, rel_tol=1e-6)
    assert float(m.identity_prior(2, torch.tensor([False, False])).detach()) == 0.0
    loss = m.smoothness(2) + m.identity_prior(2, static)
    loss.backward()
    assert m.translations.grad is not None and torch.isfinite(m.translations.grad).all()


def test_gradients_reach_every_kind():
    for kind in ("se3", "affine", "mlp"):
        m = make_motion(MotionConfig(kind=kind), 2, TIMES)
        x0 = torch.randn(6, 3)
        target = x0 + torch.tensor([0.1, 0.0, 0.0])
        loss = ((m(x0, torch.tensor([0, 1, 0, 1, 0, 1]), 0.25) - target) ** 2).sum()
        loss.backward()
        grads = [p.grad for p in m.parameters() if p.grad is not None]
        assert grads and any(float(g.abs().sum()) > 0 for g in grads), kind


def test_bad_arguments():
    with pytest.raises(ValueError, match="kind"):
        make_motion(MotionConfig(kind="spline"), 2, TIMES)
    with pytest.raises(ValueError, match="increasing"):
        make_motion(MotionConfig(), 2, [0.0, 0.5, 0.5])
    with pytest.raises(ValueError, match="at least one"):
        make_motion(MotionConfig(), 0, TIMES)


def test_cosine_lr():
    assert cosine_lr(1e-3, 1e-5, 0.0) == pytest.approx(1e-3)
    assert cosine_lr(1e-3, 1e-5, 1.0) == pytest.approx(1e-5)
    assert cosine_lr(1e-3, 1e-5, 0.5) == pytest.approx(0.5 * (1e-3 + 1e-5))


def test_closed_form_fits_recover_known_transforms():
    from sync4d.geometry import fit_affine, kabsch, matrix_to_rotvec

    rng = np.random.default_rng(3)
    src = rng.normal(size=(50, 3))
    for w in ([0.0, 0.0, 0.0], [0.3, -0.2, 0.9], [0.0, math.pi - 1e-9, 0.0], [1e-10, 0, 0]):
        r = rotvec_to_matrix(torch.tensor(w, dtype=torch.float64)).numpy()
        t = np.array([0.5, -1.0, 2.0])
        rr, tt = kabsch(src, src @ r.T + t)
        assert np.allclose(rr, r, atol=1e-9) and np.allclose(tt, t, atol=1e-9)
        back = rotvec_to_matrix(torch.as_tensor(matrix_to_rotvec(rr))).numpy()
        assert np.allclose(back, r, atol=1e-7)
    a = np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.2], [0.1, 0.0, 1.1]])
    aa, bb = fit_affine(src, src @ a.T + [1.0, 2.0, 3.0])
    assert np.allclose(aa, a) and np.allclose(bb, [1.0, 2.0, 3.0])


@pytest.mark.parametrize("kind", ["se3", "affine"])
def test_fit_to_reproduces_per_object_motion(kind):
    rng = np.random.default_rng(4)
    x0 = rng.normal(size=(60, 3))
    labels = np.repeat([0, 1, 2], 20)
    rots = [rotvec_to_matrix(torch.tensor([0.0, 0.0, 0.5 * j], dtype=torch.float64)).numpy()
            for j in range(len(TIMES))]  # fmt: skip
    positions = []
    for j in range(len(TIMES)):
        p = x0.copy()
        p[labels == 1] += [0.1 * j, 0.0, 0.0]
        p[labels == 2] = x0[labels == 2] @ rots[j].T
        positions.append(p)
    m = make_motion(MotionConfig(kind=kind), 3, TIMES)
    m.fit_to(x0, positions, labels)
    lab = torch.as_tensor(labels)
    for j, t in enumerate(TIMES):
        got = m(torch.as_tensor(x0, dtype=torch.float32), lab, float(t)).detach().double().numpy()
        assert np.allclose(got, positions[j], atol=1e-5)
