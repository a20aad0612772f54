"""The kinematic features' numerical edges (Appendix B): the rotation angle (dim 16) continuous
through pi, the speed rank and is-fastest (dims 21, 22) stable for objects at rest under float
noise, and the smoothed acceleration (dim 15) against its closed form."""

from __future__ import annotations

import math

import numpy as np

from sync4d.phase3.kinematics import RANK_TIE, Tracks, continuous_angle, kinematic_features


def _tracks(linear: np.ndarray, offsets: np.ndarray, times: np.ndarray) -> Tracks:
    k, t = offsets.shape[:2]
    z = np.zeros((k, t))
    apart = np.eye(3)[:k] * np.arange(1, k + 1)[:, None]  # objects 1-3 m apart
    return Tracks(times=times, linear=linear, offsets=offsets,
                  canonical_centroids=apart, residual_mean=z, residual_std=z,
                  rigid_share=np.ones((k, t)), visible=np.ones((k, t)))  # fmt: skip


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_the_rotation_angle_goes_on_through_pi():
    times = np.linspace(0.0, 1.0, 41)
    true = 1.9 * math.pi * times  # a turn of 342 degrees
    linear = np.stack([[_rot_z(a) for a in true]])
    f = kinematic_features(_tracks(linear, np.zeros((1, 41, 3)), times))
    np.testing.assert_allclose(f[0, :, 16], true, atol=1e-6)
    assert np.all(np.diff(f[0, :, 16]) > 0)  # no fold at pi
    # the angle of a single frame near pi, from either side, about any axis
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    for a in (math.pi - 1e-7, math.pi, math.pi + 1e-7):
        r = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k
        got = continuous_angle(r[None, None])[0, 0]
        assert abs(got - min(a, 2 * math.pi - a)) < 1e-6


def test_rank_and_fastest_do_not_flip_on_noise_at_rest():
    rng = np.random.default_rng(0)
    t = 30
    times = np.linspace(0.0, 1.0, t)
    offsets = np.zeros((3, t, 3))
    offsets[0, :, 0] = times  # object 0 moves at speed 1
    offsets[1:] = rng.normal(scale=1e-9, size=(2, t, 3))  # objects 1, 2 at rest, float noise
    f = kinematic_features(_tracks(np.tile(np.eye(3), (3, t, 1, 1)), offsets, times))
    assert np.all(f[0, :, 22] == 1.0) and np.all(f[0, :, 21] == 1.0)
    assert np.all(f[1:, :, 22] == 0.0)  # at rest: never the fastest
    assert np.all(f[1:, :, 21] == 0.0)  # and slower than no one
    # every object at rest: none is fastest, all tie
    still = kinematic_features(_tracks(np.tile(np.eye(3), (2, t, 1, 1)),
                                       rng.normal(scale=1e-9, size=(2, t, 3)), times))
    assert np.all(still[..., 21:23] == 0.0)
    # two moving objects within the tie tolerance of each other are both fastest
    offsets[1, :, 0] = times * (1 - 0.5 * RANK_TIE)
    f = kinematic_features(_tracks(np.tile(np.eye(3), (3, t, 1, 1)), offsets, times))
    assert np.all(f[:2, 2:-2, 22] == 1.0)


def test_the_smoothed_acceleration_is_a_causal_ema():
    t = 25
    times = np.linspace(0.0, 1.0, t)
    offsets = np.zeros((1, t, 3))
    offsets[0, :, 2] = 0.5 * 3.0 * times**2 + np.where(times > 0.5, 2.0 * (times - 0.5) ** 2, 0)
    f = kinematic_features(_tracks(np.tile(np.eye(3), (1, t, 1, 1)), offsets, times))
    accel = f[0, :, 1]
    w = 1.0 - math.exp(-1.0 / 5.0)
    want = np.empty(t)
    want[0] = accel[0]
    for i in range(1, t):
        want[i] = (1 - w) * want[i - 1] + w * accel[i]
    np.testing.assert_allclose(f[0, :, 15], want, rtol=1e-12, atol=1e-12)
    assert abs(accel[3] - 3.0) < 1e-6 and abs(accel[-4] - 7.0) < 1e-6  # |a| of the track
    assert abs(f[0, 5, 15] - 3.0) < 1e-6 and f[0, -1, 15] < accel[-1] - 0.1  # lags the jump
