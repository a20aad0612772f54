"""The 28-D kinematic feature vector of Appendix B, per object and frame, from per-object tracks.

Pure numpy on `Tracks` (built from a Phase 2 run by `sync4d.phase3.tracks`). Dimension order
exactly as Appendix B:

    0 speed |v|            1 |a|                 2 angular velocity     3 residual mean
    4 rigid share rho      5 visible fraction    6-8 v (x, y, z)        9-11 a (x, y, z)
    12 speed delta         13 rho delta          14 EMA speed           15 EMA |a|
    16 rotation angle |w|  17 |t|                18 residual std        19 |A - I|_F (affine)
    20 speed / s_ref       21 speed rank         22 is fastest          23 f / (T - 1)
    24 nearest distance    25 d/dt of 24         26 distance to hand    27 d/dt of 26

Decisions (docs/phase3.md): velocities and accelerations are central differences (second-order
one-sided at the ends, `numpy.gradient` over the frame times) of M_phi's predicted object centroid
c_k(f) = A_k(f) c0_k + b_k(f), in world units per unit of normalised time, so they are the
shared motion Phase 2 factored out, not the residual wiggle; deltas (12, 13) are backward
differences, 0 at the first frame; the EMAs (14, 15) are causal with a 5-frame time constant
(weight 1 - exp(-1/5) on the new frame), started at the first value; the angular velocity (2) is
the angle of R(f) R(f-1)^T over the frame gap (forward at frame 0), with R the rotation of
A's polar decomposition in affine mode; s_ref is the 95th percentile of every object's speed
over all frames; the rank (21) is the fraction of other objects slower than k (0 with one
object); relational distances are between centroids; hand dims (26, 27) are 0 when the scene has
no hand object or for the hand itself.

Relational dims of unobserved objects: every object of the field has M_phi's transform at every
stored frame (Phase 2 fits it to D_theta's positions of all the object's Gaussians, seen or
not), so its centroid, and every distance to it, is defined whether or not a view sees it; a
label with no Gaussian is no object of the field at all (`observe` leaves it out). The
relational dims are therefore computed at every frame, also where the object or the other one
is unobserved: the prediction e_hat at an unobserved frame is all the field has there (Sec. 3.5:
under occlusion it is the sole embedding), while standardisation and the ridge read the
observed frames only. Nothing here is skipped for visibility; `relational_counts` says how many
object-frames that concerns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["FEATURE_NAMES", "NUM_FEATURES", "RANK_TIE", "RELATIONAL_DIMS", "Tracks",
           "continuous_angle", "kinematic_features", "relational_counts",
           "rotation_angle"]  # fmt: skip

NUM_FEATURES = 28
#: Short name of each of the 28 dimensions, in order.
FEATURE_NAMES = (
    "speed", "accel", "angular_velocity", "residual_mean", "rigid_share", "visible",
    "vx", "vy", "vz", "ax", "ay", "az", "speed_delta", "rigid_share_delta", "speed_ema",
    "accel_ema", "rotation_angle", "translation", "residual_std", "affine_delta",
    "relative_speed", "speed_rank", "is_fastest", "time_fraction", "nearest_distance",
    "nearest_closing_speed", "hand_distance", "hand_closing_speed",
)  # fmt: skip
#: What each of the 28 dimensions is, by name (units: world units and normalised time; the
#: module's docstring has how each is computed).
FEATURE_DESCRIPTIONS = {
    "speed": "0: |v|, the speed of M_phi's object centroid (world units per unit time)",
    "accel": "1: |a|, the magnitude of its acceleration",
    "angular_velocity": "2: angle of R(f) R(f-1)^T over the frame gap (radians per unit time)",
    "residual_mean": "3: mean |r| of its Gaussians, r = D_theta's position - M_phi's (Eq. 6)",
    "rigid_share": "4: rho, the mean of |x~ - x0| / (|x~ - x0| + |r|) over its Gaussians: the "
                   "share of their motion that M_phi carries",
    "visible": "5: the largest fraction of its projected Gaussians that the label map of one "
               "view gives to it (0 unseen)",
    "vx": "6: velocity, x", "vy": "7: velocity, y", "vz": "8: velocity, z",
    "ax": "9: acceleration, x", "ay": "10: acceleration, y", "az": "11: acceleration, z",
    "speed_delta": "12: speed minus the previous frame's (0 at the first)",
    "rigid_share_delta": "13: rho minus the previous frame's (0 at the first)",
    "speed_ema": "14: causal moving average of the speed (5-frame time constant)",
    "accel_ema": "15: causal moving average of |a| (5-frame time constant)",
    "rotation_angle": "16: |w|, the angle of M_phi's rotation from the canonical pose, kept "
                      "continuous in time (radians, up to a full turn)",
    "translation": "17: |t|, the length of M_phi's translation b",
    "residual_std": "18: standard deviation of |r| over its Gaussians",
    "affine_delta": "19: |A - I|_F, how far M_phi's linear part is from the identity (affine)",
    "relative_speed": "20: speed over s_ref, the 95th percentile of every object's speed",
    "speed_rank": "21: the fraction of the other objects slower than this one",
    "is_fastest": "22: 1 where this object is the fastest (ties within 1 % of s_ref), else 0",
    "time_fraction": "23: the frame's index over T - 1",
    "nearest_distance": "24: distance between centroids to the nearest other object",
    "nearest_closing_speed": "25: time derivative of dim 24 (negative: closing in)",
    "hand_distance": "26: distance to the hand object's centroid (0 without one, or the hand)",
    "hand_closing_speed": "27: time derivative of dim 26",
}
#: The dims that relate an object to another one (rank, nearest, hand): 0 with one object.
RELATIONAL_DIMS = (21, 24, 25, 26, 27)
#: Time constant (frames) of the smoothed speed and acceleration (dims 14, 15).
EMA_FRAMES = 5.0
#: Speeds closer than this fraction of the reference speed s_ref count as equal in the speed
#: rank and is-fastest (dims 21, 22), so float noise among objects at rest flips neither; an
#: object no faster than that is never the fastest.
RANK_TIE = 0.01
#: ... and closer than this fraction of the largest distance between the objects' canonical
#: centroids per unit of time (a scene where nothing moves has an s_ref of noise alone).
STILL_SPEED = 1e-3


@dataclass
class Tracks:
    """Per-object, per-frame motion of K objects over T frames (float64).

    `times` [T] normalised frame times; `linear` [K, T, 3, 3] and `offsets` [K, T, 3]: M_phi's
    transform x~ = A x0 + b; `canonical_centroids` [K, 3]: mean canonical position of each
    object's Gaussians; `residual_mean`, `residual_std`, `rigid_share`, `visible` [K, T];
    `rigid`: SE(3) (True) or affine M_phi; `hand`: index of the hand object or None.
    """

    times: np.ndarray
    linear: np.ndarray
    offsets: np.ndarray
    canonical_centroids: np.ndarray
    residual_mean: np.ndarray
    residual_std: np.ndarray
    rigid_share: np.ndarray
    visible: np.ndarray
    rigid: bool = True
    hand: int | None = None

    @property
    def centroids(self) -> np.ndarray:
        """M_phi's predicted centroid of each object [K, T, 3]: A c0 + b."""
        return np.einsum("ktij,kj->kti", self.linear, self.canonical_centroids) + self.offsets


def _rotation_part(a: np.ndarray) -> np.ndarray:
    """The rotation of the polar decomposition of `a` [..., 3, 3] (nearest rotation)."""
    u, _, vt = np.linalg.svd(a)
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angle (radians, in [0, pi]) of rotation matrices `r` [..., 3, 3]."""
    cos = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def continuous_angle(r: np.ndarray) -> np.ndarray:
    """Rotation angle [K, T] of rotations `r` [K, T, 3, 3] kept continuous in time (dim 16):
    the angle of each frame's unit quaternion, its sign chosen to follow the previous frame's,
    as 2 atan2(|v|, w) in [0, 2 pi]. `rotation_angle` folds angles above pi back (a turn of
    200 degrees reads 160); this one goes on through pi, up to a full turn."""
    k, t = r.shape[:2]
    m = r.reshape(-1, 3, 3)
    w = np.sqrt(np.maximum(0.0, 1.0 + np.trace(m, axis1=1, axis2=2))) / 2.0
    v = np.stack([m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]], 1)
    # the axis from the antisymmetric part (|v| = 2 sin(angle)), its length from the angle
    sin_half = np.sqrt(np.maximum(0.0, 1.0 - w * w))
    norm = np.linalg.norm(v, axis=1)
    axis = np.where(norm[:, None] > 1e-12, v / np.maximum(norm, 1e-300)[:, None], 0.0)
    # near pi the antisymmetric part vanishes: the axis from the symmetric part instead
    near_pi = norm < 1e-6
    if near_pi.any():
        sym = (m[near_pi] + np.eye(3)) / 2.0
        idx = np.argmax(np.diagonal(sym, axis1=1, axis2=2), axis=1)
        col = sym[np.arange(len(idx)), :, idx]
        axis[near_pi] = col / np.maximum(np.linalg.norm(col, axis=1), 1e-300)[:, None]
    q = np.concatenate([w[:, None], axis * sin_half[:, None]], 1).reshape(k, t, 4)
    for f in range(1, t):
        flip = np.einsum("ki,ki->k", q[:, f], q[:, f - 1]) < 0
        q[flip, f] *= -1.0
    return 2.0 * np.arctan2(np.linalg.norm(q[..., 1:], axis=-1), q[..., 0])


def _gradient(x: np.ndarray, times: np.ndarray) -> np.ndarray:
    """d x / d t along axis 1 of `x` [K, T, ...] (0 with a single frame)."""
    if x.shape[1] < 2:
        return np.zeros_like(x)
    return np.gradient(x, times, axis=1, edge_order=2 if x.shape[1] >= 3 else 1)


def _backward_delta(x: np.ndarray) -> np.ndarray:
    """x(f) - x(f-1) along axis 1, 0 at f = 0."""
    d = np.zeros_like(x)
    d[:, 1:] = x[:, 1:] - x[:, :-1]
    return d


def _ema(x: np.ndarray, frames: float = EMA_FRAMES) -> np.ndarray:
    """Causal EMA along axis 1 with time constant `frames`, started at the first value."""
    w = 1.0 - math.exp(-1.0 / frames)
    out = np.empty_like(x)
    out[:, 0] = x[:, 0]
    for f in range(1, x.shape[1]):
        out[:, f] = (1.0 - w) * out[:, f - 1] + w * x[:, f]
    return out


def _rank_tie(tr: Tracks, s_ref: float) -> float:
    """Speeds closer than this count as equal in dims 21-22: `RANK_TIE` of the reference speed,
    and at least `STILL_SPEED` of the distance between the objects per unit time, so that in a
    scene where nothing moves (s_ref itself is noise) float noise does not decide either."""
    c = np.asarray(tr.canonical_centroids, np.float64)
    spread = float(np.linalg.norm(c[:, None] - c[None, :], axis=-1).max()) if len(c) else 0.0
    return max(RANK_TIE * s_ref, STILL_SPEED * spread) + 1e-12


def kinematic_features(tr: Tracks) -> np.ndarray:
    """The Appendix B feature vectors [K, T, 28] (float64) of the objects in `tr`."""
    k, t = tr.residual_mean.shape
    times = np.asarray(tr.times, dtype=np.float64)
    c = tr.centroids
    v = _gradient(c, times)
    a = _gradient(v, times)
    speed = np.linalg.norm(v, axis=-1)
    accel = np.linalg.norm(a, axis=-1)
    rot = tr.linear if tr.rigid else _rotation_part(tr.linear)
    ang = np.zeros((k, t))
    if t > 1:
        rel = rot[:, 1:] @ np.swapaxes(rot[:, :-1], -1, -2)
        step = rotation_angle(rel) / np.diff(times)[None, :]
        ang[:, 1:] = step
        ang[:, 0] = step[:, 0]
    f = np.zeros((k, t, NUM_FEATURES))
    f[..., 0] = speed
    f[..., 1] = accel
    f[..., 2] = ang
    f[..., 3] = tr.residual_mean
    f[..., 4] = tr.rigid_share
    f[..., 5] = tr.visible
    f[..., 6:9] = v
    f[..., 9:12] = a
    f[..., 12] = _backward_delta(speed)
    f[..., 13] = _backward_delta(np.asarray(tr.rigid_share, dtype=np.float64))
    f[..., 14] = _ema(speed)
    f[..., 15] = _ema(accel)
    f[..., 16] = continuous_angle(rot)
    f[..., 17] = np.linalg.norm(tr.offsets, axis=-1)
    f[..., 18] = tr.residual_std
    if not tr.rigid:
        f[..., 19] = np.linalg.norm(tr.linear - np.eye(3), axis=(-2, -1))
    s_ref = float(np.percentile(speed, 95)) if speed.size else 0.0
    f[..., 20] = speed / (s_ref + 1e-12)
    tie = _rank_tie(tr, s_ref)
    if k > 1:
        slower = (speed[:, None, :] > speed[None, :, :] + tie).sum(1)  # [K, T]
        f[..., 21] = slower / (k - 1)
    fastest = (speed >= speed.max(0, keepdims=True) - tie) & (speed > tie)
    f[..., 22] = fastest.astype(np.float64)
    f[..., 23] = np.arange(t) / max(t - 1, 1)
    if k > 1:
        d = np.linalg.norm(c[:, None] - c[None, :], axis=-1)  # [K, K, T]
        d[np.arange(k), np.arange(k)] = np.inf
        nearest = d.min(1)
        f[..., 24] = nearest
        f[..., 25] = _gradient(nearest, times)
    if tr.hand is not None:
        dh = np.linalg.norm(c - c[tr.hand][None], axis=-1)
        dh[tr.hand] = 0.0
        f[..., 26] = dh
        f[..., 27] = _gradient(dh, times)
        f[tr.hand, :, 27] = 0.0
    return f


def relational_counts(observed: np.ndarray) -> dict[str, int]:
    """Object-frames of `observed` [K, T] whose relational dims (`RELATIONAL_DIMS`) another object
    makes (``relational``: all K T with two objects or more, none with one), those left at 0
    for want of another object (``relational_skipped``), and of the computed ones those at a
    frame where the object or another one is unobserved (``relational_unobserved``: computed
    all the same, see the module note)."""
    observed = np.asarray(observed, dtype=bool)
    k, t = observed.shape
    if k < 2:
        return {"relational": 0, "relational_skipped": k * t, "relational_unobserved": 0}
    return {"relational": k * t, "relational_skipped": 0,
            "relational_unobserved": k * int((~observed).any(0).sum())}  # fmt: skip
