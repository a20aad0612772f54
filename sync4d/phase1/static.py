"""Static Gaussians: the ones D_theta does not move skip it (issue "skip what a scene doesn't
need").

Design. Every Gaussian pays D_theta's forward and backward at every iteration, yet in most
dynamic scenes most Gaussians never move (bouncingballs: the plate and floor, 11.2k of 17.8k).
On a schedule (`StaticConfig.start`, then every `every` iterations and after the last
densification), D_theta is evaluated without gradients for every Gaussian at `times` training
times spread over the run's frames. A Gaussian whose offsets vary over time by less than the
thresholds (position: `position` times the scene extent; rotation vector: `rotation`
radians; log-scale: `log_scale`) is marked static: its time-mean offsets are baked into its
canonical state (so what it renders does not jump by more than the thresholds), and from then
on its canonical state *is* its state at every time: D_theta is evaluated only on the others
(`DeformableGaussians.at_time`), forward and backward. A constant offset is not motion, so the
criterion is the spread around the mean, not the offset's size.

A static Gaussian is released when D_theta, which keeps learning from its moving neighbours,
would now move it by more than `release` times the thresholds: its bake is undone (the mean
offset at its position is subtracted), so the first render after release matches the last
static one on average over time. Split and cloned children inherit the flag (the densifier
carries it row by row). The set is stored in checkpoints (``gaussians.static``), which
`sync4d-render` reads: a static Gaussian renders its canonical state there too.

The first check waits for `start` iterations: D_theta starts at zero, so before it has learnt
the motion every Gaussian looks static. When every Gaussian is static the scene has no motion
and D_theta is not evaluated at all.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from sync4d.geometry import axis_angle_to_quat, quat_multiply
from sync4d.settings import ranged

__all__ = [
    "StaticConfig",
    "StaticUpdate",
    "deformation_spread",
    "motion_sparsity",
    "update_static_set",
]


@dataclass(frozen=True)
class StaticConfig:
    """When Gaussians count as static and skip D_theta (off by default: the paper evaluates
    D_theta on every Gaussian)."""

    #: Mark Gaussians that D_theta does not move as static and skip D_theta for them.
    enabled: bool = False
    #: Iteration of the first check (scaled with `fit --iters`); D_theta must have learnt
    #: the motion by then, or moving Gaussians look static. At most `phase1.iterations` while
    #: `enabled` (checked when the config is read).
    start: int = ranged(3_000, 1, scales=1)
    #: Iterations between checks (scaled with `fit --iters`); the last densification also
    #: triggers one.
    every: int = ranged(1_000, 1, scales=10)
    #: Training times at which D_theta is evaluated per check (evenly spread over the frames).
    times: int = ranged(16, 2, 1_000)
    #: Largest spread over time of the position offset of a static Gaussian, as a fraction of
    #: the scene extent.
    position: float = ranged(1e-3, 0.0)
    #: Largest spread over time of its rotation vector offset, radians.
    rotation: float = ranged(0.01, 0.0)
    #: Largest spread over time of its log-scale offset.
    log_scale: float = ranged(0.01, 0.0)
    #: A static Gaussian is released when its spread exceeds this multiple of the thresholds.
    release: float = ranged(2.0, 1.0)
    #: Weight of the motion-sparsity loss (`motion_sparsity`) added to Phase 1's photometric
    #: loss while `enabled`: D_theta otherwise moves nearly every Gaussian a little
    #: (bouncingballs: median spread 2.5 % of the extent, 3 of 19k below 1e-3), so nothing
    #: looks static; the loss drives the offsets of Gaussians that do not need motion to zero.
    sparsity: float = ranged(0.0, 0.0)
    #: The loss applies to Gaussians whose offset score (`motion_sparsity`'s per-row term:
    #: 1 is ten times the static thresholds) is below this, so it snaps small motions to
    #: zero without holding back the ones the scene needs; 0 applies it to every Gaussian.
    sparsity_below: float = ranged(0.0, 0.0)


@dataclass(frozen=True)
class StaticUpdate:
    """What one check did: Gaussians newly `marked` static, `released`, and the `static`
    total after it, out of `total`."""

    marked: int
    released: int
    static: int
    total: int


@torch.no_grad()
def deformation_spread(
    model, times: Tensor, chunk: int = 16_384
) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor, Tensor]]:
    """D_theta's offsets of every Gaussian of `model` at `times` [T]: the largest deviation
    from their time-mean of the position offset (world units) [N], of the rotation vector
    (radians) [N] and of the log-scale (max over axes) [N], and the means (dx, dw, dl), each
    [N, 3]. Evaluated in chunks of `chunk` Gaussians, without gradients."""
    n = model.num_gaussians
    spread = [torch.zeros(n) for _ in range(3)]
    means = [torch.zeros(n, 3) for _ in range(3)]
    for lo in range(0, n, chunk):
        x0 = model.means[lo : lo + chunk]
        z = model.embeddings[lo : lo + chunk]
        outs = [model.deform(x0, z, float(t)) for t in times]  # T x (dx, dw, dl)
        for k in range(3):
            stack = torch.stack([o[k] for o in outs]).float()  # [T, n, 3]
            mean = stack.mean(0)
            dev = stack - mean
            means[k][lo : lo + chunk] = mean
            if k == 2:
                spread[k][lo : lo + chunk] = dev.abs().amax(dim=(0, 2))
            else:
                spread[k][lo : lo + chunk] = dev.norm(dim=-1).amax(0)
    return spread[0], spread[1], spread[2], (means[0], means[1], means[2])


def _conj(q: Tensor) -> Tensor:
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


@torch.no_grad()
def update_static_set(model, times: Tensor, extent: float, config: StaticConfig) -> StaticUpdate:
    """Mark the Gaussians of `model` that D_theta does not move at `times` as static, baking
    their mean offsets into their canonical state, and release static ones it now moves
    (undoing the bake); `extent` scales the position threshold. Changes `model.static` and the
    canonical parameters of the rows concerned in place (their Adam moments are kept)."""
    c = config
    dpos, drot, dscale, (mdx, mdw, mdl) = deformation_spread(model, times)
    limits = (c.position * extent, c.rotation, c.log_scale)
    still = (dpos <= limits[0]) & (drot <= limits[1]) & (dscale <= limits[2])
    moving = (
        (dpos > c.release * limits[0])
        | (drot > c.release * limits[1])
        | (dscale > c.release * limits[2])
    )
    static = model.static
    mark = still & ~static
    release = moving & static
    # Bake: the canonical state takes the mean offsets, so the static render is the time-mean
    # of the deformed one; releasing subtracts the offsets D_theta now gives at that position,
    # so the deformed render's time-mean is the static one.
    for rows, sign in ((mark, 1.0), (release, -1.0)):
        if not bool(rows.any()):
            continue
        model.means.data[rows] += sign * mdx[rows]
        model.log_scales.data[rows] += sign * mdl[rows]
        rot = axis_angle_to_quat(mdw[rows])
        if sign < 0:
            rot = _conj(rot)
        model.quats.data[rows] = quat_multiply(rot, model.quats.data[rows])
    model.static = (static | mark) & ~release
    return StaticUpdate(int(mark.sum()), int(release.sum()), int(model.static.sum()),
                        model.num_gaussians)  # fmt: skip


def motion_sparsity(
    offsets: tuple[Tensor, Tensor, Tensor], extent: float, n: int, below: float = 0.0
) -> Tensor:
    """The motion-sparsity loss of D_theta's offsets (dx, dw, dl), each [M, 3], of the `n`
    Gaussians' moving rows: sum over rows of ``|dx| / (1e-2 extent) + |dw| / 0.1 + |dl| / 0.1``
    (Euclidean norms, each offset over ten times its static threshold), divided by `n`; with
    `below` > 0 only rows whose term is below it count. A group lasso: its gradient does not
    vanish near zero, so offsets that the images do not ask for go to zero rather than
    staying small."""
    dx, dw, dl = offsets
    per_row = dx.norm(dim=-1) / (1e-2 * extent) + (dw.norm(dim=-1) + dl.norm(dim=-1)) / 0.1
    if below > 0:
        per_row = per_row * (per_row.detach() < below)
    return per_row.sum() / max(1, n)
