"""Phase 3's solve on degenerate inputs: an object at rest whose kinematic features are
constant up to float noise (the ridge must not blow up), two objects with identical motion, an
object observed in one frame or never, a scene of one object; all finite, and the watchdog
names what is not."""

from __future__ import annotations

import numpy as np
import pytest

from sync4d import watchdog
from sync4d.phase3 import field as fm
from sync4d.phase3.kinematics import Tracks, kinematic_features


def _solve(features: np.ndarray, obs: np.ndarray, observed: np.ndarray):
    static = fm.static_embeddings(obs, observed)
    std = fm.standardise(features, observed)
    pred, w = fm.predict_embeddings(std, obs, observed, static, 0.01)
    sync = fm.temporal_ema(fm.blend(pred, obs, observed), 0.15)
    return std, w, pred, sync


def _tracks(offsets: np.ndarray, times: np.ndarray) -> Tracks:
    k, t = offsets.shape[:2]
    z = np.zeros((k, t))
    apart = np.arange(k)[:, None] * np.array([[2.0, 0.0, 0.0]])
    return Tracks(times, np.tile(np.eye(3), (k, t, 1, 1)), offsets, apart, z, z,
                  np.ones((k, t)), np.ones((k, t)))  # fmt: skip


def test_degenerate_objects_give_a_finite_bounded_field():
    rng = np.random.default_rng(0)
    t, d = 24, 8
    times = np.linspace(0.0, 1.0, t)
    offsets = np.zeros((5, t, 3))
    offsets[0, :, 0] = np.sin(3 * times)  # moving
    offsets[1] = rng.normal(scale=1e-9, size=(t, 3))  # at rest: float noise only
    offsets[2, :, 0] = offsets[3, :, 0] = times  # identical motion
    offsets[4, :, 1] = times**2  # observed in one frame only
    feats = kinematic_features(_tracks(offsets, times))
    observed = np.ones((5, t), bool)
    observed[1, ::2] = False  # the one at rest unobserved in half its frames
    observed[4] = False
    observed[4, 7] = True
    obs = rng.normal(size=(5, t, d))
    std, w, pred, sync = _solve(feats, obs, observed)
    for name, a in (("standardised", std), ("W", w), ("e_hat", pred), ("e_sync", sync)):
        assert np.isfinite(a).all(), name
        watchdog.check_array("Phase 3", name, a)
    # at rest: the noise stays noise (its own motion's dims standardise to 0, not to a
    # unit-variance signal); its distance to the others still moves
    own = [0, 1, 6, 7, 8, 9, 10, 11, 12, 14, 15, 20]
    assert not std[1][:, own].any() and std[1][:, 24].any()
    assert np.abs(std).max() < 10.0  # bounded z-scores, observed frames or not
    # identical motion, identical own features (their neighbours differ: dims 21-27 may)
    np.testing.assert_allclose(std[2][:, :21], std[3][:, :21], atol=1e-9)
    assert not w[4].any()  # one observed frame: no ridge, e_hat = e_static
    np.testing.assert_allclose(pred[4], np.tile(fm.static_embeddings(obs, observed)[4], (t, 1)))
    # never observed, and a scene of one object
    observed[4] = False
    _, _, pred, sync = _solve(feats, obs, observed)
    assert np.isfinite(pred).all() and np.isfinite(sync).all()
    one = kinematic_features(_tracks(offsets[:1], times))
    assert np.isfinite(_solve(one, obs[:1], observed[:1])[3]).all()


def test_the_watchdog_names_a_poisoned_solve():
    feats = np.zeros((2, 5, 28))
    feats[1, 3, 0] = np.nan
    with pytest.raises(watchdog.NonFinite, match=r"Phase 3 stopped: f is NaN or inf in 1 objects"):
        watchdog.check_array("Phase 3", "f", feats)
