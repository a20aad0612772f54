"""Rigid-body geometry shared by both phases: quaternions (w, x, y, z), rotation vectors,
and closed-form fits of corresponding point sets (Kabsch, affine least squares, and the robust
refit that drops points not following the object). Torch functions are batched over leading
dimensions and differentiable; the fits are float64 numpy.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "axis_angle_to_quat",
    "fit_affine",
    "kabsch",
    "matrix_to_rotvec",
    "quat_multiply",
    "quat_slerp",
    "quat_to_matrix",
    "robust_fit",
    "rotvec_to_matrix",
]


def _rotation_angle(w: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """For rotation vectors `w` [..., 3]: theta^2, where theta is below 1e-4 rad (there the
    callers switch to a Taylor series), and theta with those entries set to 1 so the closed
    forms stay finite (and their gradients zero) where they are not used; each [..., 1]."""
    theta2 = (w * w).sum(-1, keepdim=True)
    small = theta2 < 1e-8
    safe = torch.where(small, torch.ones_like(theta2), theta2.clamp_min(1e-24).sqrt())
    return theta2, small, safe


def axis_angle_to_quat(w: Tensor) -> Tensor:
    """Unit quaternion (w, x, y, z) of rotation vectors `w` [..., 3] (Appendix A's aa2q):
    (cos(theta / 2), w sin(theta / 2) / theta), theta = |w|. A Taylor series below 1e-4 rad
    keeps the derivative right at w = 0 (d q_xyz / d w = I / 2): D_theta's rotation head starts
    at exactly zero, and the axis-times-sine form has a zero gradient there, so before
    2026-12-03 Phase 1 never learnt a rotation."""
    theta2, small, safe = _rotation_angle(w)
    half_sinc = torch.where(small, 0.5 - theta2 / 48.0, torch.sin(0.5 * safe) / safe)
    cos_half = torch.where(small, 1.0 - theta2 / 8.0, torch.cos(0.5 * safe))
    q = torch.cat([cos_half, w * half_sinc], dim=-1)
    return q / q.norm(dim=-1, keepdim=True)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a (x) b of quaternions (w, x, y, z), [..., 4]: rotating by b, then a."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of quaternions (w, x, y, z) [..., 4] (normalised first)."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def rotvec_to_matrix(w: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of rotation vectors `w` [..., 3] (Rodrigues; a Taylor
    series below 1e-4 rad keeps the gradient finite at w = 0)."""
    theta2, small, safe = _rotation_angle(w)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(safe)) / (safe * safe))
    x, y, z = w.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*w.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=w.dtype, device=w.device).expand_as(k)
    return eye + a[..., None] * k + b[..., None] * (k @ k)


def quat_slerp(q0: Tensor, q1: Tensor, alpha: float) -> Tensor:
    """Spherical interpolation of unit quaternions [..., 4] by `alpha` in [0, 1] along the
    shorter arc (linear + renormalise when they nearly coincide)."""
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    omega = torch.acos(dot)
    so = torch.sin(omega)
    near = so < 1e-6
    safe = torch.where(near, torch.ones_like(so), so)
    w0 = torch.where(near, 1.0 - alpha, torch.sin((1.0 - alpha) * omega) / safe)
    w1 = torch.where(near, torch.full_like(so, alpha), torch.sin(alpha * omega) / safe)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def kabsch(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R [3, 3] and translation t [3] minimising sum w ||R src + t - dst||^2 over
    corresponding points `src`, `dst` [M, 3] (float64; proper rotation, det +1)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / max(w.sum(), 1e-300)
    cs, cd = w @ src, w @ dst
    h = ((src - cs) * w[:, None]).T @ (dst - cd)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cd - r @ cs


def fit_affine(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Affine map (A [3, 3], b [3]) minimising sum w ||A src + b - dst||^2 (least squares; the
    identity part is kept where the points do not determine it)."""
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    sw = np.sqrt(w)[:, None]
    x = np.concatenate([src, np.ones((len(src), 1))], axis=1)
    sol, *_ = np.linalg.lstsq(x * sw, (dst - src) * sw, rcond=None)
    return np.eye(3) + sol[:3].T, sol[3]


def robust_fit(
    fit, src: np.ndarray, dsts: list[np.ndarray], rounds: int = 3, cutoff: float = 3.0
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-frame transforms `fit(src, dsts[j], weights)` of one object, refitted `rounds`
    times without the points whose residual (averaged over frames) exceeds `cutoff` times the
    median: points that do not follow the object (mislabelled background under it, floaters)
    drop out, as the paper's residual modulation intends."""
    w = np.ones(len(src))
    for r in range(rounds + 1):
        out = [fit(src, d, w) for d in dsts]
        if r == rounds:
            return out
        res = np.mean(
            [np.linalg.norm(src @ a.T + b - d, axis=1)
             for (a, b), d in zip(out, dsts, strict=True)],
            axis=0,
        )  # fmt: skip
        keep = res <= cutoff * np.median(res) + 1e-9
        if keep.sum() < 4 or keep.all():
            return out
        w = keep.astype(np.float64)
    return out


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation vector [3] of a rotation matrix [3, 3] (float64, angle in [0, pi])."""
    cos = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    angle = math.acos(cos)
    if angle < 1e-8:
        return np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    if math.pi - angle < 1e-6:  # axis from the symmetric part
        m = (r + np.eye(3)) / 2.0
        axis = m[np.argmax(np.diag(m))]
        return axis / np.linalg.norm(axis) * angle
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return v / (2.0 * math.sin(angle)) * angle
