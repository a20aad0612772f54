"""Photometric refinement of Phase 2's SE(3) table (not in the paper; `MotionConfig.refine_*`).

After the closed-form start (`MotionConfig.init = "fit"`), a rigid template of each moving
object's first-frame Gaussians (`_RigidTemplate`) is tracked through the stored frames against
the training views, optionally with rounds of fitting the template's own colours to every view
and tracking again (`refine_texture_rounds`): D_theta's colours are a texture averaged over its
morph, which pulls the poses toward the blur (docs/results/phase2-robustness.md). The model is
unchanged; only the SE(3) table's entries of the moving objects are rewritten.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from sync4d import watchdog
from sync4d.events import Advanced, Finished, Started, Stats, emit
from sync4d.geometry import axis_angle_to_quat, matrix_to_rotvec, quat_multiply, rotvec_to_matrix
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.losses import photometric_loss
from sync4d.phase2.motion import MotionConfig, SE3Table, cosine_lr

if TYPE_CHECKING:
    from sync4d.phase2.strategy import MotionStrategy

__all__ = ["refine_motion"]


def _centroids(x: Tensor, owner: Tensor, k: int) -> Tensor:
    """Mean [k, 3] of the points `x` [M, 3] of each owner index in `owner` [M] (0 if none)."""
    count = torch.bincount(owner, minlength=k).clamp_min(1)
    return torch.zeros(k, 3).index_add_(0, owner, x) / count[:, None]


@dataclass
class _RigidTemplate:
    """The refinement's rigid template: the moving objects' Gaussians of the first frame.
    `sel` [N] marks them, `owner` [M] their index in `moving`, `offsets` [M, 3, 1] their
    positions about their object's centroid `centre` [K', 3], `quats` [M, 4] and `scales`
    [M, 3] their shape there; `views` the training frame indices per stored frame; `sh_dc`
    [N, 1, 3] the base colours rendered (a copy of the model's that the texture fit changes)."""

    moving: list[int]
    sel: Tensor
    owner: Tensor
    offsets: Tensor
    centre: Tensor
    quats: Tensor
    scales: Tensor
    views: list[list[int]]
    sh_dc: Tensor

    @property
    def rows(self) -> Tensor:
        """Indices [M] of the template's Gaussians in the model."""
        return torch.nonzero(self.sel).squeeze(-1)

    @classmethod
    @torch.no_grad()
    def build(cls, p2: MotionStrategy, moving: list[int]) -> _RigidTemplate:
        """The template of `moving` objects from the strategy `p2`'s model and labels."""
        views: list[list[int]] = [[] for _ in p2.times]
        for index, f in enumerate(p2.trainer.scene.train):
            views[p2.motion.frame_index(f.time)].append(index)
        slot = torch.full_like(p2.labels, -1)  # index into `moving`, -1 elsewhere
        for i, k in enumerate(moving):
            slot[p2.labels == k] = i
        sel = slot >= 0
        owner = slot[sel]
        x_ref, q_ref, s_ref = (v[sel] for v in p2.trainer.model.at_time(float(p2.times[0])))
        centre = _centroids(x_ref, owner, len(moving))
        offsets = (x_ref - centre[owner]).unsqueeze(-1)
        return cls(moving, sel, owner, offsets, centre, q_ref, s_ref, views,
                   p2.trainer.model.sh_dc.detach().clone())  # fmt: skip

    def centroids(self, x: Tensor) -> Tensor:
        """Each moving object's centroid [K', 3] of the template's points `x` [M, 3]."""
        return _centroids(x, self.owner, len(self.moving))

    @torch.no_grad()
    def deformed(self, model: DeformableGaussians, t: float) -> tuple[Tensor, Tensor, Tensor]:
        """D_theta's Gaussians at `t` with the template's scales (fixed while it is posed)."""
        x_t, q_t, scales = model.at_time(t)
        scales[self.sel] = self.scales
        return x_t, q_t, scales

    def pose(
        self, w: Tensor, d: Tensor, deformed: tuple[Tensor, Tensor, Tensor]
    ) -> tuple[Tensor, Tensor, Tensor]:
        """`deformed` with the template's Gaussians turned by rotation vectors `w` [K', 3] about
        their centroids and shifted by `d` [K', 3] (differentiable in both)."""
        x_t, q_t, scales = deformed
        means, quats = x_t.clone(), q_t.clone()
        moved = (rotvec_to_matrix(w)[self.owner] @ self.offsets).squeeze(-1)
        means[self.sel] = moved + self.centre[self.owner] + d[self.owner]
        quats[self.sel] = quat_multiply(axis_angle_to_quat(w)[self.owner], self.quats)
        return means, quats, scales


def refine_motion(p2: MotionStrategy, config: MotionConfig | None = None) -> None:
    """Photometric refinement of the motion strategy `p2`'s SE(3) table with the `refine_*`
    settings of `config` (default: its `phase2.motion`; `steps` below is `refine_steps`, `lr`
    `refine_lr`, and so on): every moving
    object's Gaussians of the first frame, moved rigidly as R_k (x - c_k) + c_k + d_k (c_k:
    their centroid), are rendered beside D_theta's other Gaussians and compared with each
    stored frame's training views in time order: `steps` Adam steps per frame on every
    R_k and d_k (learning rate cosine-annealed from `lr` to `lr_final`, at most and by
    default `lr`; each step renders `views_per_step` of the frame's views in turn, 0: all),
    starting from the previous frame's rotation and from D_theta's centroid offset. The
    first frame is refined too (4 x `steps`, from the identity): D_theta's Gaussians there
    may carry their texture turned away from the images (a time-averaged orientation when
    D_theta morphs instead of rotating), and the motion is relative to that frame.

    Then `texture_rounds` times: the template's base colours (SH DC of the moving
    Gaussians, a copy: the model keeps its own) are fitted to every training view with the
    poses fixed (`colour_epochs` passes in a seeded random order, Adam at `colour_lr`), and
    every frame is tracked again from its last pose with `retrack_steps` steps (default
    `steps`) from rate `retrack_lr` (default `lr`). D_theta's colours are a texture
    averaged over a morph; seen through the rigid motion it is blurred where the object
    turned most, which pulls the poses there toward the blur. Table entries become the
    result composed with the first frame's fitted transform; static objects (the strategy's
    `static` and held `frozen` ones) and the model are unchanged. Each pass's (object, stored
    frame) visits are counted on the strategy: `refine_visits` for the moving objects,
    `refine_visits_skipped` for the static ones."""
    mc = config or p2.phase2.motion
    steps, lr, views_per_step = mc.refine_steps, mc.refine_lr, mc.refine_views
    lr_final = min(mc.refine_lr_final, lr)
    texture_rounds, colour_epochs = mc.refine_texture_rounds, mc.refine_colour_epochs
    retrack_steps = mc.refine_retrack_steps or steps
    retrack_lr = mc.refine_retrack_lr or lr
    motion = p2.motion
    if not isinstance(motion, SE3Table):
        raise ValueError("refine_motion refines an SE(3) table (phase2.motion.kind=se3)")
    k_all = p2.assignment.num_objects
    still = p2.static | p2.motion.frozen
    moving = [k for k in range(k_all) if not bool(still[k])]
    times = p2.times
    if len(times) < 2 or steps <= 0:
        return
    visited = {motion.frame_index(f.time) for f in p2.trainer.scene.train}
    pairs = len(visited) * (1 + texture_rounds)  # stored frames tracked, over every pass
    p2.refine_visits += pairs * len(moving)
    p2.refine_visits_skipped += pairs * (k_all - len(moving))
    if not moving:
        return
    template = _RigidTemplate.build(p2, moving)
    with torch.no_grad():
        r0 = rotvec_to_matrix(motion.rotvecs[moving, 0].detach().float())
        b0 = motion.translations[moving, 0].detach().float()
    # The bar counts Adam steps (tracking and texture fit), so its ETA holds across passes.
    first = [(4 * steps if j == 0 else steps) if v else 0 for j, v in enumerate(template.views)]
    n_views = sum(len(v) for v in template.views)
    per_round = colour_epochs * n_views + retrack_steps * sum(1 for v in template.views if v)
    emit(Started("refine M_phi", sum(first) + texture_rounds * per_round, log_every=10))
    done = 0

    def advance(n: int, loss: float) -> None:
        nonlocal done
        done += n
        emit(Advanced("refine M_phi", done, Stats(loss=loss)))

    poses: list[tuple[Tensor, Tensor]] = []
    scores: list[float] = []  # each tracked frame's mean loss over its views (restarts only)
    w = torch.zeros(len(moving), 3)
    for j in range(len(times)):
        # The first frame starts from the fitted pose, which holds whatever orientation
        # D_theta's texture has there: it gets more steps than the warm-started rest.
        deformed = template.deformed(p2.trainer.model, float(times[j]))
        d = template.centroids(deformed[0][template.sel]) - template.centre
        n = 4 * steps if j == 0 else steps
        track = (n, lr, lr_final, views_per_step, deformed)
        pose, loss = _track_frame(p2, template, j, w, d, *track)
        if mc.refine_restart_jump > 0:
            pose, scores = _restart_if_jumped(p2, template, j, pose, poses, scores, mc, track)
        poses.append(pose)
        w = pose[0]
        advance(first[j], loss)
    for r in range(texture_rounds):
        loss = _fit_template_colours(
            p2, template, poses, mc.refine_colour_lr, colour_epochs, seed=r
        )
        advance(colour_epochs * n_views, loss)
        scores = []
        for j in range(len(times)):
            track = (retrack_steps, retrack_lr, min(lr_final, retrack_lr), views_per_step, None)
            poses[j], loss = _track_frame(p2, template, j, *poses[j], *track)
            if mc.refine_restart_jump > 0:
                poses[j], scores = _restart_if_jumped(
                    p2, template, j, poses[j], poses[:j], scores, mc, track
                )
            advance(retrack_steps if template.views[j] else 0, loss)
    emit(Finished("refine M_phi"))
    p2.template_colours = template.sh_dc
    with torch.no_grad():
        centre = template.centre
        for j, (w, d) in enumerate(poses):
            r = rotvec_to_matrix(w)
            a_j = r @ r0
            b_j = (r @ (b0 - centre).unsqueeze(-1)).squeeze(-1) + centre + d
            for i, k in enumerate(moving):
                motion.rotvecs[k, j] = torch.as_tensor(
                    matrix_to_rotvec(a_j[i].double().numpy()), dtype=motion.rotvecs.dtype
                )
                motion.translations[k, j] = b_j[i].to(motion.translations.dtype)


def _frame_score(
    p2: MotionStrategy, template: _RigidTemplate, j: int, pose: tuple[Tensor, Tensor]
) -> float:
    """Mean loss over stored frame `j`'s training views with the template at `pose`."""
    t = float(p2.times[j])
    with torch.no_grad():
        posed = template.pose(*pose, template.deformed(p2.trainer.model, t))
        return float(np.mean([float(_template_loss(p2, i, t, posed, template.sh_dc))
                              for i in template.views[j]]))  # fmt: skip


def _restart_if_jumped(
    p2: MotionStrategy,
    template: _RigidTemplate,
    j: int,
    pose: tuple[Tensor, Tensor],
    before: list[tuple[Tensor, Tensor]],
    scores: list[float],
    mc: MotionConfig,
    track: tuple,
) -> tuple[tuple[Tensor, Tensor], list[float]]:
    """`pose` of frame `j`, or a better one when its score jumped (`refine_restart_jump`): each
    moving object tracked again from the previous frame's rotation turned by each restart angle
    about the axis of its last turn (frames `before` are the poses of 0..j-1); `scores` with
    frame j's appended."""
    if not template.views[j]:
        return pose, [*scores, scores[-1] if scores else float("nan")]
    score = _frame_score(p2, template, j, pose)
    if j >= 2 and scores and score > (1.0 + mc.refine_restart_jump) * scores[-1]:
        w_prev, w_last = before[j - 2][0], before[j - 1][0]
        for i in range(len(template.moving)):
            r_prev = rotvec_to_matrix(w_prev[i].double())
            r_last = rotvec_to_matrix(w_last[i].double())
            turn = torch.as_tensor(matrix_to_rotvec((r_last @ r_prev.T).numpy()))
            if float(turn.norm()) < 1e-4:
                continue
            axis = turn / turn.norm()
            for angle in mc.refine_restart_angles:
                start = pose[0].clone()
                kick = rotvec_to_matrix(axis * np.radians(angle)) @ r_last
                start[i] = torch.as_tensor(matrix_to_rotvec(kick.numpy()), dtype=start.dtype)
                cand, _ = _track_frame(p2, template, j, start, pose[1], *track)
                cand_score = _frame_score(p2, template, j, cand)
                if cand_score < score:
                    pose, score = cand, cand_score
    return pose, [*scores, score]


def _track_frame(
    p2: MotionStrategy,
    template: _RigidTemplate,
    j: int,
    w: Tensor,
    d: Tensor,
    n_steps: int,
    lr: float,
    lr_final: float,
    views_per_step: int,
    deformed: tuple[Tensor, Tensor, Tensor] | None = None,
) -> tuple[tuple[Tensor, Tensor], float]:
    """`n_steps` Adam steps on the moving objects' rotation vectors `w` [K', 3] and shifts
    `d` [K', 3] at stored frame `j` (`refine_motion`; `deformed`: the template's
    `deformed` at that frame when the caller has it); the new pose and the last loss."""
    views = template.views[j]
    if not views or n_steps <= 0:
        return (w.clone(), d.clone()), float("nan")
    t = float(p2.times[j])
    if deformed is None:
        deformed = template.deformed(p2.trainer.model, t)
    w_j = w.clone().requires_grad_(True)
    d_j = d.clone().requires_grad_(True)
    opt = torch.optim.Adam([w_j, d_j], lr=lr)
    per_step = len(views) if views_per_step <= 0 else views_per_step
    drawn = 0
    loss_value = float("nan")
    for s in range(n_steps):
        for g in opt.param_groups:
            g["lr"] = cosine_lr(lr, lr_final, s / max(1, n_steps - 1))
        opt.zero_grad(set_to_none=True)
        loss_value = 0.0
        for _ in range(per_step):
            index = views[drawn % len(views)]
            drawn += 1
            pose = template.pose(w_j, d_j, deformed)
            loss = _template_loss(p2, index, t, pose, template.sh_dc,
                                  lambda inputs: watchdog.check_inputs(
                                      "Phase 2 refinement", j, inputs,
                                      scale=p2.trainer.watch_scale))  # fmt: skip
            loss = watchdog.check_loss("Phase 2 refinement", j, loss)
            loss.backward()
            loss_value += float(loss.detach()) / per_step
        pose_params = {"rotation": w_j, "shift": d_j}
        units = {"rotation": "objects", "shift": "objects"}
        watchdog.check_grads("Phase 2 refinement", j, pose_params, units)
        opt.step()
        watchdog.check_params("Phase 2 refinement", j, pose_params, units, p2.trainer.watch_scale)
    return (w_j.detach().clone(), d_j.detach().clone()), loss_value


def _fit_template_colours(
    p2: MotionStrategy,
    template: _RigidTemplate,
    poses: list[tuple[Tensor, Tensor]],
    lr: float,
    epochs: int,
    seed: int,
) -> float:
    """Fit the template's base colours (the moving Gaussians' rows of `template.sh_dc`) to
    every training view, each frame's objects at its pose in `poses`: `epochs` passes in an
    order drawn from `seed`, one view per Adam step. Returns the mean loss of the last pass."""
    frames = [(j, index) for j, views in enumerate(template.views) for index in views]
    if not frames or epochs <= 0:
        return float("nan")
    with torch.no_grad():
        posed = [
            template.pose(w, d, template.deformed(p2.trainer.model, float(p2.times[j])))
            for j, (w, d) in enumerate(poses)
        ]
    rows = template.rows
    colours = template.sh_dc[rows].clone().requires_grad_(True)
    opt = torch.optim.Adam([colours], lr=lr)
    generator = torch.Generator().manual_seed(p2.trainer.config.seed * 1000 + seed)
    total = 0.0
    for _ in range(epochs):
        total = 0.0
        for k in torch.randperm(len(frames), generator=generator).tolist():
            j, index = frames[k]
            opt.zero_grad(set_to_none=True)
            sh_dc = template.sh_dc.index_put((rows,), colours)
            loss = _template_loss(p2, index, float(p2.times[j]), posed[j], sh_dc)
            loss.backward()
            opt.step()
            total += float(loss.detach())
    template.sh_dc[rows] = colours.detach()
    return total / len(frames)


def _template_loss(
    p2: MotionStrategy,
    index: int,
    t: float,
    deformed: tuple[Tensor, Tensor, Tensor],
    sh_dc: Tensor,
    check: Callable[[dict[str, Tensor]], None] | None = None,
) -> Tensor:
    """Photometric loss of training frame `index` rendered at time `t` with `deformed`
    means, quaternions and scales and base colours `sh_dc` [N, 1, 3] (`check`: the
    watchdog's, on what the rasteriser receives)."""
    frame = p2.trainer.scene.train[index]
    out = p2.trainer.model.render(
        frame.camera, t, sh_degree=p2.trainer.model.sh_degree, background=p2.trainer.background,
        deformed=deformed, sh_dc=sh_dc, threads=p2.trainer.threads, check=check,
    )  # fmt: skip
    return photometric_loss(
        out.features, p2.trainer.image(index, frame), p2.trainer.config.lambda_l1,
        p2.trainer.config.lambda_dssim, threads=p2.trainer.threads,
    )  # fmt: skip
