"""Phase 3's maths on analytic inputs: every kinematic dimension (Appendix B) on constant
velocity, constant acceleration, pure rotation and two approaching objects; the ridge against
a direct least-squares solve; standardisation, blend, EMA and the query score (Sec. 3.5)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sync4d.phase3 import field as fm
from sync4d.phase3.kinematics import FEATURE_NAMES, NUM_FEATURES, Tracks, kinematic_features


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _tracks(offsets: np.ndarray, linear: np.ndarray | None = None, c0=None, hand=None,
            rigid=True) -> Tracks:  # fmt: skip
    k, t, _ = offsets.shape
    if linear is None:
        linear = np.broadcast_to(np.eye(3), (k, t, 3, 3)).copy()
    rng = np.random.default_rng(0)
    return Tracks(
        times=np.linspace(0.0, 1.0, t), linear=linear, offsets=offsets,
        canonical_centroids=np.zeros((k, 3)) if c0 is None else np.asarray(c0, float),
        residual_mean=rng.uniform(0.0, 0.1, (k, t)), residual_std=rng.uniform(0.0, 0.1, (k, t)),
        rigid_share=rng.uniform(0.5, 1.0, (k, t)), visible=rng.uniform(0.0, 1.0, (k, t)),
        rigid=rigid, hand=hand,
    )  # fmt: skip


T = 11
TIMES = np.linspace(0.0, 1.0, T)


def test_names_cover_the_28_dims():
    assert len(FEATURE_NAMES) == NUM_FEATURES == 28


def test_constant_velocity():
    v = np.array([0.3, -0.2, 0.1])
    tr = _tracks((TIMES[:, None] * v)[None], c0=[[1.0, 2.0, 3.0]])
    f = kinematic_features(tr)[0]
    np.testing.assert_allclose(f[:, 0], np.linalg.norm(v), atol=1e-12)  # speed
    np.testing.assert_allclose(f[:, 1], 0.0, atol=1e-10)  # |a|
    np.testing.assert_allclose(f[:, 2], 0.0, atol=1e-7)  # angular velocity
    np.testing.assert_allclose(f[:, 3], tr.residual_mean[0])
    np.testing.assert_allclose(f[:, 4], tr.rigid_share[0])
    np.testing.assert_allclose(f[:, 5], tr.visible[0])
    np.testing.assert_allclose(f[:, 6:9], np.broadcast_to(v, (T, 3)), atol=1e-12)
    np.testing.assert_allclose(f[:, 9:12], 0.0, atol=1e-10)
    np.testing.assert_allclose(f[:, 12], 0.0, atol=1e-12)  # speed delta
    rho = tr.rigid_share[0]
    np.testing.assert_allclose(f[1:, 13], rho[1:] - rho[:-1])
    assert f[0, 13] == 0.0
    np.testing.assert_allclose(f[:, 14], np.linalg.norm(v), atol=1e-12)  # EMA of a constant
    np.testing.assert_allclose(f[:, 16], 0.0, atol=1e-7)  # rotation angle
    np.testing.assert_allclose(f[:, 17], TIMES * np.linalg.norm(v), atol=1e-12)  # |t|
    np.testing.assert_allclose(f[:, 18], tr.residual_std[0])
    np.testing.assert_allclose(f[:, 19], 0.0)  # SE(3): no affine delta
    np.testing.assert_allclose(f[:, 20], 1.0, atol=1e-9)  # speed / its own 95th percentile
    np.testing.assert_allclose(f[:, 21], 0.0)  # one object: no rank
    np.testing.assert_allclose(f[:, 22], 1.0)  # ... and it is the fastest
    np.testing.assert_allclose(f[:, 23], np.arange(T) / (T - 1))
    np.testing.assert_allclose(f[:, 24:], 0.0)  # no other object, no hand


def test_constant_acceleration_is_exact_at_the_ends():
    a = np.array([0.0, 0.0, -9.81])
    v0 = np.array([1.0, 0.0, 2.0])
    off = TIMES[:, None] * v0 + 0.5 * TIMES[:, None] ** 2 * a
    f = kinematic_features(_tracks(off[None]))[0]
    vel = v0 + TIMES[:, None] * a
    np.testing.assert_allclose(f[:, 6:9], vel, atol=1e-9)
    np.testing.assert_allclose(f[:, 9:12], np.broadcast_to(a, (T, 3)), atol=1e-8)
    np.testing.assert_allclose(f[:, 1], 9.81, atol=1e-8)
    speed = np.linalg.norm(vel, axis=1)
    np.testing.assert_allclose(f[:, 0], speed, atol=1e-9)
    np.testing.assert_allclose(f[1:, 12], np.diff(speed), atol=1e-9)
    w = 1.0 - math.exp(-1.0 / 5.0)
    ema = [speed[0]]
    for s in speed[1:]:
        ema.append((1 - w) * ema[-1] + w * s)
    np.testing.assert_allclose(f[:, 14], ema, atol=1e-9)
    np.testing.assert_allclose(f[:, 20], speed / np.percentile(speed, 95), atol=1e-9)


def test_pure_rotation():
    omega = 1.2  # rad per unit time, 69 degrees over the sequence
    lin = np.stack([_rot_z(omega * t) for t in TIMES])[None]
    f = kinematic_features(_tracks(np.zeros((1, T, 3)), lin))[0]
    np.testing.assert_allclose(f[:, 0], 0.0, atol=1e-12)  # the centroid (origin) stays put
    np.testing.assert_allclose(f[:, 2], omega, atol=1e-9)
    np.testing.assert_allclose(f[:, 16], omega * TIMES, atol=1e-7)
    np.testing.assert_allclose(f[:, 17], 0.0)
    # off-origin centroid: speed = omega * radius
    f2 = kinematic_features(_tracks(np.zeros((1, T, 3)), lin, c0=[[2.0, 0.0, 0.0]]))[0]
    np.testing.assert_allclose(f2[2:-2, 0], omega * 2.0, rtol=5e-3)  # (omega h)^2 / 6 = 2.4e-3


def test_affine_mode_reports_the_linear_delta_and_the_rotation_part():
    lin = np.stack([_rot_z(0.5 * t) * (1.0 + t) for t in TIMES])[None]
    f = kinematic_features(_tracks(np.zeros((1, T, 3)), lin, rigid=False))[0]
    np.testing.assert_allclose(f[:, 19], np.linalg.norm(lin[0] - np.eye(3), axis=(1, 2)))
    np.testing.assert_allclose(f[:, 16], 0.5 * TIMES, atol=1e-7)
    np.testing.assert_allclose(f[:, 2], 0.5, atol=1e-7)


def test_two_objects_approaching_and_a_hand():
    off = np.zeros((3, T, 3))
    off[0, :, 0] = -1.0 + TIMES  # 1 m per unit time towards +x
    off[1, :, 0] = 1.0 - 2.0 * TIMES  # 2 m per unit time towards -x: the fastest
    off[2, :, 1] = 3.0  # the hand, at rest
    f = kinematic_features(_tracks(off, hand=2))
    gap = np.abs(off[0, :, 0] - off[1, :, 0])  # 2 - 3t
    np.testing.assert_allclose(f[0, :, 24], np.minimum(gap, np.hypot(off[0, :, 0], 3.0)))
    np.testing.assert_allclose(f[0, :6, 25], -3.0, atol=1e-9)  # closing while approaching
    np.testing.assert_allclose(f[1, :, 22], 1.0)
    np.testing.assert_allclose(f[0, :, 22], 0.0)
    np.testing.assert_allclose(f[1, :, 21], 1.0)  # both others slower
    np.testing.assert_allclose(f[0, :, 21], 0.5)  # faster than the hand only
    np.testing.assert_allclose(f[2, :, 21], 0.0)
    speeds = np.array([1.0, 2.0, 0.0])
    s_ref = np.percentile(np.repeat(speeds, T), 95)
    np.testing.assert_allclose(f[1, :, 20], 2.0 / s_ref, atol=1e-9)
    dh = np.hypot(off[0, :, 0], 3.0)
    np.testing.assert_allclose(f[0, :, 26], dh)
    np.testing.assert_allclose(f[0, :, 27], np.gradient(dh, TIMES, edge_order=2), atol=1e-12)
    np.testing.assert_allclose(f[2, :, 26:], 0.0)  # the hand itself


def test_standardise_per_object_over_observed_frames():
    rng = np.random.default_rng(1)
    feats = rng.normal(3.0, 2.0, (2, 20, 28))
    feats[:, :, 5] = 7.0  # a constant dim
    observed = rng.uniform(size=(2, 20)) > 0.3
    s = fm.standardise(feats, observed)
    assert s.shape == (2, 20, 29)
    np.testing.assert_allclose(s[..., 28], 1.0)
    for k in range(2):
        sel = observed[k]
        np.testing.assert_allclose(s[k, sel, :28].mean(0), 0.0, atol=1e-9)
        sd = s[k, sel, :28].std(0)
        np.testing.assert_allclose(np.delete(sd, 5), 1.0, atol=1e-6)
        np.testing.assert_allclose(s[k, :, 5], 0.0)


def test_unobserved_frames_stay_in_the_observed_range():
    """`clip_unobserved`: an occluded object's visible fraction (dim 5) drops to 0, far below
    what it was when seen; its standardised value there is clipped to the seen range, so the
    ridge map is not extrapolated. Observed frames are untouched; off, Eq. 14 as written."""
    rng = np.random.default_rng(2)
    feats = rng.normal(0.0, 1.0, (1, 30, 28))
    feats[0, :, 5] = rng.uniform(0.6, 0.9, 30)
    observed = np.ones((1, 30), bool)
    observed[0, 10:15] = False
    feats[0, 10:15, 5] = 0.0
    on, off = fm.standardise(feats, observed), fm.standardise(feats, observed, False)
    sel = observed[0]
    np.testing.assert_array_equal(on[0, sel], off[0, sel])
    lo, hi = off[0, sel].min(0), off[0, sel].max(0)
    assert np.all(on[0, ~sel] >= lo - 1e-12) and np.all(on[0, ~sel] <= hi + 1e-12)
    assert off[0, 10, 5] < lo[5] - 5.0 and on[0, 10, 5] == pytest.approx(lo[5])
    # W = 0: e_hat is the static anchor at every frame, the observations still blended
    obs = fm._unit(rng.normal(size=(1, 30, 8)))
    static = fm.static_embeddings(obs, observed)
    pred, w = fm.predict_embeddings(on, obs, observed, static, kinematics=False)
    assert not w.any()
    np.testing.assert_allclose(pred, np.repeat(static[:, None], 30, 1), atol=1e-12)
    sync = fm.temporal_ema(fm.blend(pred, obs, observed), 0.15)
    np.testing.assert_allclose(fm.unconditioned_sync(static, obs, observed), sync, atol=1e-12)


def test_ridge_equals_a_direct_solve():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(40, 29))
    y = rng.normal(size=(40, 16))
    lam = 0.01
    w = fm.fit_ridge(x, y, lam)
    aug_x = np.vstack([x, math.sqrt(lam) * np.eye(29)])
    aug_y = np.vstack([y, np.zeros((29, 16))])
    ref = np.linalg.lstsq(aug_x, aug_y, rcond=None)[0]
    np.testing.assert_allclose(w, ref, atol=1e-10)
    # the normal equations hold
    np.testing.assert_allclose(x.T @ (x @ w - y) + lam * w, 0.0, atol=1e-9)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_static_prediction_blend_and_unobserved_frames():
    rng = np.random.default_rng(3)
    k, t, d = 2, 12, 8
    obs = _unit(rng.normal(size=(k, t, d)))
    observed = np.ones((k, t), bool)
    observed[0, 4:7] = False
    obs[~observed] = 0.0
    static = fm.static_embeddings(obs, observed)
    np.testing.assert_allclose(static[0], _unit(obs[0, observed[0]].mean(0)))
    feats = fm.standardise(rng.normal(size=(k, t, 28)), observed)
    pred, w = fm.predict_embeddings(feats, obs, observed, static, 0.01)
    np.testing.assert_allclose(pred[1], _unit(static[1] + feats[1] @ w[1]))
    np.testing.assert_allclose(w[1], fm.fit_ridge(feats[1], obs[1] - static[1], 0.01))
    b = fm.blend(pred, obs, observed, 0.65, "prediction")
    np.testing.assert_allclose(b[1, 0], _unit(0.65 * pred[1, 0] + 0.35 * obs[1, 0]))
    np.testing.assert_allclose(b[0, 5], pred[0, 5])  # unobserved: the prediction alone
    b2 = fm.blend(pred, obs, observed, 0.65, "observation")
    np.testing.assert_allclose(b2[1, 0], _unit(0.35 * pred[1, 0] + 0.65 * obs[1, 0]))
    # an object seen once has no ridge map: its prediction is the static anchor
    once = np.zeros((k, t), bool)
    once[:, 0] = True
    p1, w1 = fm.predict_embeddings(feats, obs, once, fm.static_embeddings(obs, once))
    np.testing.assert_allclose(w1, 0.0)
    np.testing.assert_allclose(p1[:, 5], _unit(obs[:, 0]), atol=1e-12)


def test_ema_is_zero_phase_and_keeps_constants():
    d = 4
    const = np.tile(_unit(np.arange(1.0, d + 1))[None, None], (1, 9, 1))
    np.testing.assert_allclose(fm.temporal_ema(const, 0.15), const, atol=1e-12)
    base, spike = np.eye(d)[0], np.eye(d)[1]
    x = np.tile(base, (1, 9, 1))
    x[0, 4] = spike
    s = fm.temporal_ema(x, 0.15)
    np.testing.assert_allclose(np.linalg.norm(s, axis=-1), 1.0)
    on = s[0] @ spike
    assert on.argmax() == 4  # not delayed
    assert on[3] == pytest.approx(on[5], abs=0.03)  # symmetric spread
    assert 0.5 < on[4] < 1.0 and on[3] > 0.0 and on[2] < on[3]
    np.testing.assert_allclose(fm.temporal_ema(x, 0.0), x)


def test_query_score_is_eq_15():
    static = np.array([[1.0, 0.0], [0.0, 1.0]])
    sync = np.array([[[1.0, 0.0], [0.6, 0.8]], [[0.0, 1.0], [0.8, 0.6]]])
    q = np.array([3.0, 4.0])  # normalised inside: (0.6, 0.8)
    s, sims = fm.query_scores(static, sync, q)
    np.testing.assert_allclose(sims, [[0.6, 1.0], [0.8, 0.96]])
    np.testing.assert_allclose(s, [0.35 * 0.6 + 0.65 * 1.0, 0.35 * 0.8 + 0.65 * 0.96])
