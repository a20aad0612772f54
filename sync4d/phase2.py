"""Phase 2: in-loop motion decomposition (paper Sec. 3.2-3.4, Appendix A "Phase 2", App. C).

Training continues from a Phase 1 model. Every Gaussian i has an object label o(i) (from
`sync4d.assign`); M_phi predicts where each object carries its Gaussians,
x~_i(t) = M_phi(o(i), t)(x0_i) (Eq. 5), and the residual r_i(t) = x_i(t) - x~_i(t) (Eq. 6)
enters five regularisers plus the identity prior on static objects. Rendering is untouched: it
always uses D_theta's x_i(t).

Staged activation (Appendix A): M_phi and the smoothness, rigid-share and identity terms from
iteration `motion_start` (200), velocity coherence from `velocity_start` (300), the modulated
residual energy from `residual_start` (600), and a linear warm-up of all auxiliary terms over
[`warmup_start`, `warmup_end`] (500-1000). The paper's "400-iteration head start lets shared
transforms capture the dominant rigid component first" needs M_phi to learn before the warm-up
ends, so the warm-up scales only the gradient the auxiliary terms send into the scene (D_theta,
Gaussians); M_phi always sees them at full weight from their start iteration. `simultaneous`
switches every term on at iteration 0 without warm-up (the paper's failing ablation).

Before the loop, `MotionConfig.init = "fit"` starts the SE(3) table at the closed-form fit of
D_theta's motion, and `refine_steps` > 0 refines it photometrically (not in the paper): a rigid
template of each moving object's first-frame Gaussians (`_RigidTemplate`) is tracked through
the stored frames against the training views, optionally with rounds of fitting the template's
own colours to every view and tracking again (`refine_texture_rounds`). The model is unchanged.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from sync4d.assign import (
    ASSIGN_SOURCES,
    AssignConfig,
    Assignment,
    adjusted_rand_index,
    assign_from_masks,
    cluster_trajectories,
)
from sync4d.data.scene import Frame, Scene
from sync4d.deform import axis_angle_to_quat, quat_multiply
from sync4d.gaussians import DeformableGaussians
from sync4d.losses import photometric_loss
from sync4d.motion import (
    MotionConfig,
    ObjectMotion,
    SE3Table,
    cosine_lr,
    make_motion,
    matrix_to_rotvec,
    rotvec_to_matrix,
)
from sync4d.progress import Progress
from sync4d.train import Phase1Config, Phase1Trainer

__all__ = [
    "Phase2Config",
    "Phase2Trainer",
    "assign_objects",
    "frame_times",
    "rigid_share",
]


@dataclass(frozen=True)
class Phase2Config:
    """Phase 2 hyperparameters (Appendix A; the paper's values as defaults) and ablations."""

    motion: MotionConfig = field(default_factory=MotionConfig)
    assign: AssignConfig = field(default_factory=AssignConfig)
    lambda_res: float = 0.02
    lambda_share: float = 0.01
    tau: float = 0.35
    lambda_vel: float = 0.01
    lambda_smooth: float = 0.01
    lambda_id: float = 0.001
    #: EMA factor of the per-Gaussian residual magnitude (Appendix A's modulation).
    eta: float = 0.95
    #: Epsilon in the rigid share's denominator (metres).
    share_eps: float = 1e-6
    motion_start: int = 200
    velocity_start: int = 300
    warmup_start: int = 500
    warmup_end: int = 1000
    residual_start: int = 600
    #: Keep densifying (clone/split/prune, opacity reset) on Phase 1's schedule, counted from
    #: Phase 2's first iteration; every change re-runs the assignment. Off by default: Phase 1's
    #: densification window is over when Phase 2 starts.
    densify: bool = False
    #: An object whose Gaussians' mean Phase 1 displacement stays below this fraction of the
    #: scene extent is static (it gets the identity prior); background always is.
    static_fraction: float = 0.005
    # Ablation switches.
    use_motion: bool = True
    modulation: bool = True
    hinge: bool = True
    simultaneous: bool = False


def frame_times(scene: Scene) -> np.ndarray:
    """Sorted distinct training times [T] of `scene` (M_phi's stored frames)."""
    return np.unique(np.asarray([f.time for f in scene.train], dtype=np.float64))


@torch.no_grad()
def _positions_fn(model: DeformableGaussians):
    def positions_at(t: float) -> np.ndarray:
        return model.at_time(float(t))[0].double().numpy()

    return positions_at


@torch.no_grad()
def displacement_curves(model: DeformableGaussians, times: np.ndarray) -> np.ndarray:
    """[N, S, 3] float64 displacements x_i(t_s) - x_i(t_0) at the given sample times."""
    pos = np.stack([model.at_time(float(t))[0].double().numpy() for t in times], axis=1)
    return pos - pos[:, :1]


def assign_objects(
    model: DeformableGaussians, scene: Scene, extent: float, config: AssignConfig | None = None
) -> Assignment:
    """Object labels for `model`'s Gaussians: mask voting when the training frames have masks,
    otherwise trajectory clustering."""
    config = config or AssignConfig()
    if config.source not in ASSIGN_SOURCES:
        raise ValueError(
            f"phase2.assign.source: expected one of {', '.join(ASSIGN_SOURCES)}, "
            f"got {config.source!r}"
        )
    use_masks = config.source == "masks" or (config.source == "auto" and scene.has_masks)
    if use_masks:
        if not scene.has_masks:
            raise ValueError(
                f"phase2.assign.source=masks: scene '{scene.name}' has training frames without "
                "instance masks; use source=trajectories (unsupervised) or auto"
            )
        return assign_from_masks(_positions_fn(model), scene.train, scene.labels, config)
    times = np.linspace(0.0, 1.0, config.trajectory_samples)
    return cluster_trajectories(displacement_curves(model, times), extent, config)


def rigid_share(x0: Tensor, x_obj: Tensor, residual: Tensor, eps: float = 1e-6) -> Tensor:
    """Per-Gaussian rigid share ||x~ - x0|| / (||x~ - x0|| + ||r|| + eps) [N] (Eq. 9's terms)."""
    shared = (x_obj - x0).norm(dim=-1)
    return shared / (shared + residual.norm(dim=-1) + eps)


def _scale_grad(x: Tensor, scale: float) -> Tensor:
    """`x` in the forward pass, with its gradient multiplied by `scale`."""
    if scale >= 1.0:
        return x
    return x.detach() + scale * (x - x.detach())


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
    def build(cls, trainer: Phase2Trainer, moving: list[int]) -> _RigidTemplate:
        """The template of `moving` objects from `trainer`'s model and labels."""
        views: list[list[int]] = [[] for _ in trainer.times]
        for index, f in enumerate(trainer.scene.train):
            views[trainer.motion.frame_index(f.time)].append(index)
        slot = torch.full_like(trainer.labels, -1)  # index into `moving`, -1 elsewhere
        for i, k in enumerate(moving):
            slot[trainer.labels == k] = i
        sel = slot >= 0
        owner = slot[sel]
        x_ref, q_ref, s_ref = (v[sel] for v in trainer.model.at_time(float(trainer.times[0])))
        centre = _centroids(x_ref, owner, len(moving))
        offsets = (x_ref - centre[owner]).unsqueeze(-1)
        return cls(moving, sel, owner, offsets, centre, q_ref, s_ref, views,
                   trainer.model.sh_dc.detach().clone())  # fmt: skip

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


class Phase2Trainer(Phase1Trainer):
    """Phase 1's loop plus M_phi and the Phase 2 regularisers, on a Phase 1 model."""

    def __init__(
        self,
        model: DeformableGaussians,
        scene: Scene,
        config: Phase1Config | None = None,
        phase2: Phase2Config | None = None,
        total_iterations: int = 20_000,
        threads: int | None = None,
        assignment: Assignment | None = None,
    ) -> None:
        super().__init__(model, scene, config, total_iterations, threads)
        self.phase2 = phase2 or Phase2Config()
        if not self.phase2.densify:
            never = 2**62
            self.densifier.config = dataclasses.replace(
                self.densifier.config, start=never, opacity_reset_interval=never
            )
        self.times = frame_times(scene)
        self.assignment = assignment or assign_objects(
            model, scene, self.extent, self.phase2.assign
        )
        k = self.assignment.num_objects
        mc = self.phase2.motion
        if mc.init not in ("identity", "fit"):
            raise ValueError(f"phase2.motion.init: expected 'identity' or 'fit', got {mc.init!r}")
        self.motion: ObjectMotion = make_motion(mc, k, self.times, self.config.seed)
        #: Base colours [N, 1, 3] the refinement's template was last rendered with (its texture
        #: fit's result; None before a refinement).
        self.template_colours: Tensor | None = None
        if mc.init == "fit" and not self.motion.fits_closed_form:
            raise ValueError(
                f"phase2.motion.init=fit: the {mc.kind} M_phi has no closed-form start; "
                "use phase2.motion.init=identity"
            )
        self.motion_optimizer = torch.optim.Adam(
            self.motion.parameters(), lr=self.phase2.motion.lr, eps=1e-15, fused=True
        )
        self._set_labels(self.assignment.labels)
        self.static = self._static_objects()
        if mc.refine_steps < 0:
            raise ValueError(f"phase2.motion.refine_steps: expected >= 0, got {mc.refine_steps}")
        if mc.refine_lr <= 0:
            raise ValueError(f"phase2.motion.refine_lr: expected > 0, got {mc.refine_lr}")
        if mc.refine_lr_final <= 0:
            raise ValueError(
                f"phase2.motion.refine_lr_final: expected > 0, got {mc.refine_lr_final}"
            )
        for name in ("refine_texture_rounds", "refine_colour_epochs", "refine_retrack_steps",
                     "refine_retrack_lr"):  # fmt: skip
            if getattr(mc, name) < 0:
                raise ValueError(f"phase2.motion.{name}: expected >= 0, got {getattr(mc, name)}")
        if mc.refine_colour_lr <= 0:
            raise ValueError(
                f"phase2.motion.refine_colour_lr: expected > 0, got {mc.refine_colour_lr}"
            )
        if mc.refine_views < 0:
            raise ValueError(f"phase2.motion.refine_views: expected >= 0, got {mc.refine_views}")
        if mc.refine_steps > 0 and (mc.init != "fit" or mc.kind != "se3"):
            raise ValueError(
                "phase2.motion.refine_steps refines the fitted SE(3) table: it needs "
                f"phase2.motion.init=fit and kind=se3 (got init={mc.init!r}, kind={mc.kind!r})"
            )
        if mc.init == "fit":
            self.fit_motion()
            if mc.refine_steps > 0:
                self.refine_motion()

    @torch.no_grad()
    def fit_motion(self) -> None:
        """Set M_phi to the closed-form fit of every object's canonical Gaussians onto their
        D_theta positions at each stored frame (MotionConfig.init = "fit")."""
        x0 = self.model.means.double().numpy()
        pos = [self.model.at_time(float(t))[0].double().numpy() for t in self.times]
        self.motion.fit_to(x0, pos, self.labels.numpy())

    def refine_motion(self, config: MotionConfig | None = None, progress: bool = True) -> None:
        """Photometric refinement of the SE(3) table with the `refine_*` settings of `config`
        (default: this trainer's `phase2.motion`; `steps` below is `refine_steps`, `lr`
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
        result composed with the first frame's fitted transform; static objects and the model
        are unchanged."""
        mc = config or self.phase2.motion
        steps, lr, views_per_step = mc.refine_steps, mc.refine_lr, mc.refine_views
        lr_final = min(mc.refine_lr_final, lr)
        texture_rounds, colour_epochs = mc.refine_texture_rounds, mc.refine_colour_epochs
        retrack_steps = mc.refine_retrack_steps or steps
        retrack_lr = mc.refine_retrack_lr or lr
        motion = self.motion
        if not isinstance(motion, SE3Table):
            raise ValueError("refine_motion refines an SE(3) table (phase2.motion.kind=se3)")
        moving = [k for k in range(self.assignment.num_objects) if not bool(self.static[k])]
        times = self.times
        if not moving or len(times) < 2 or steps <= 0:
            return
        template = _RigidTemplate.build(self, moving)
        with torch.no_grad():
            r0 = rotvec_to_matrix(motion.rotvecs[moving, 0].detach().float())
            b0 = motion.translations[moving, 0].detach().float()
        # The bar counts Adam steps (tracking and texture fit), so its ETA holds across passes.
        first = [(4 * steps if j == 0 else steps) if v else 0 for j, v in enumerate(template.views)]
        n_views = sum(len(v) for v in template.views)
        per_round = colour_epochs * n_views + retrack_steps * sum(1 for v in template.views if v)
        bar = Progress(sum(first) + texture_rounds * per_round, desc="refine M_phi", log_every=10)
        done = 0

        def advance(n: int, loss: float) -> None:
            nonlocal done
            done += n
            if progress:
                bar.update(done, {"loss": f"{loss:.4f}"})

        poses: list[tuple[Tensor, Tensor]] = []
        w = torch.zeros(len(moving), 3)
        for j in range(len(times)):
            # The first frame starts from the fitted pose, which holds whatever orientation
            # D_theta's texture has there: it gets more steps than the warm-started rest.
            deformed = template.deformed(self.model, float(times[j]))
            d = template.centroids(deformed[0][template.sel]) - template.centre
            pose, loss = self._track_frame(
                template, j, w, d, 4 * steps if j == 0 else steps, lr, lr_final, views_per_step,
                deformed,
            )  # fmt: skip
            poses.append(pose)
            w = pose[0]
            advance(first[j], loss)
        for r in range(texture_rounds):
            loss = self._fit_template_colours(
                template, poses, mc.refine_colour_lr, colour_epochs, seed=r
            )
            advance(colour_epochs * n_views, loss)
            for j in range(len(times)):
                poses[j], loss = self._track_frame(
                    template, j, *poses[j], retrack_steps, retrack_lr,
                    min(lr_final, retrack_lr), views_per_step,
                )  # fmt: skip
                advance(retrack_steps if template.views[j] else 0, loss)
        if progress:
            bar.close()
        self.template_colours = template.sh_dc
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

    def _track_frame(
        self,
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
        `d` [K', 3] at stored frame `j` (refine_motion; `deformed`: the template's
        `deformed` at that frame when the caller has it); the new pose and the last loss."""
        views = template.views[j]
        if not views or n_steps <= 0:
            return (w.clone(), d.clone()), float("nan")
        t = float(self.times[j])
        if deformed is None:
            deformed = template.deformed(self.model, t)
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
                loss = self._template_loss(index, t, pose, template.sh_dc)
                loss.backward()
                loss_value += float(loss.detach()) / per_step
            opt.step()
        return (w_j.detach().clone(), d_j.detach().clone()), loss_value

    def _fit_template_colours(
        self,
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
                template.pose(w, d, template.deformed(self.model, float(self.times[j])))
                for j, (w, d) in enumerate(poses)
            ]
        rows = template.rows
        colours = template.sh_dc[rows].clone().requires_grad_(True)
        opt = torch.optim.Adam([colours], lr=lr)
        generator = torch.Generator().manual_seed(self.config.seed * 1000 + seed)
        total = 0.0
        for _ in range(epochs):
            total = 0.0
            for k in torch.randperm(len(frames), generator=generator).tolist():
                j, index = frames[k]
                opt.zero_grad(set_to_none=True)
                sh_dc = template.sh_dc.index_put((rows,), colours)
                loss = self._template_loss(index, float(self.times[j]), posed[j], sh_dc)
                loss.backward()
                opt.step()
                total += float(loss.detach())
        template.sh_dc[rows] = colours.detach()
        return total / len(frames)

    def _template_loss(
        self, index: int, t: float, deformed: tuple[Tensor, Tensor, Tensor], sh_dc: Tensor
    ) -> Tensor:
        """Photometric loss of training frame `index` rendered at time `t` with `deformed`
        means, quaternions and scales and base colours `sh_dc` [N, 1, 3]."""
        frame = self.scene.train[index]
        out = self.model.render(
            frame.camera, t, sh_degree=self.model.sh_degree, background=self._background,
            deformed=deformed, sh_dc=sh_dc, threads=self.threads,
        )  # fmt: skip
        return photometric_loss(
            out.features, self._image(index, frame), self.config.lambda_l1,
            self.config.lambda_dssim, threads=self.threads,
        )  # fmt: skip

    # -- assignment state ----------------------------------------------------------------
    def _set_labels(self, labels: np.ndarray) -> None:
        self.labels = torch.as_tensor(labels, dtype=torch.long)
        self.residual_ema = torch.zeros(len(labels))
        self._ema_started = False

    @torch.no_grad()
    def _static_objects(self) -> Tensor:
        """[K] bool: background and objects that barely move in D_theta."""
        k = self.assignment.num_objects
        static = torch.zeros(k, dtype=torch.bool)
        static[0] = True
        samples = np.linspace(0.0, 1.0, 9)
        disp = np.linalg.norm(displacement_curves(self.model, samples), axis=-1).mean(1)
        labels = self.labels.numpy()
        for j in range(1, k):
            sel = labels == j
            if not sel.any() or disp[sel].mean() < self.phase2.static_fraction * self.extent:
                static[j] = True
        return static

    def on_gaussians_changed(self) -> None:
        """Densification changed N: re-run the assignment and restart the modulation EMA."""
        a = assign_objects(self.model, self.scene, self.extent, self.phase2.assign)
        if a.num_objects != self.assignment.num_objects:
            a.labels = np.minimum(a.labels, self.assignment.num_objects - 1)
            a.num_objects = self.assignment.num_objects
        self.assignment = a
        self._set_labels(a.labels)

    def sh_degree_now(self) -> int:
        """Phase 1 has reached the full SH degree: Phase 2 renders with it throughout."""
        return self.model.sh_degree

    # -- schedule --------------------------------------------------------------------------
    def _active(self, start: int) -> bool:
        return self.phase2.simultaneous or self.iteration >= start

    def _warmup(self) -> float:
        p = self.phase2
        if p.simultaneous:
            return 1.0
        span = max(1, p.warmup_end - p.warmup_start)
        return min(1.0, max(0.0, (self.iteration - p.warmup_start) / span))

    # -- losses -----------------------------------------------------------------------------
    def modulation_weights(self, residual_norm: Tensor) -> Tensor:
        """Update the EMA of ||r_i|| (eta) and return m_i = sigmoid(z-score) [N] (Eq. 8)."""
        eta = self.phase2.eta
        r = residual_norm.detach()
        if not self._ema_started:
            self.residual_ema = r.clone()
            self._ema_started = True
        else:
            self.residual_ema = eta * self.residual_ema + (1 - eta) * r
        ema = self.residual_ema
        return torch.sigmoid((ema - ema.mean()) / (ema.std(unbiased=False) + 1e-6))

    def auxiliary_loss(self, frame: Frame, means: Tensor) -> tuple[Tensor | None, dict[str, float]]:
        p = self.phase2
        if not p.use_motion or not self._active(p.motion_start):
            return None, {}
        j = self.motion.frame_index(frame.time)
        x0 = self.model.means
        # The scene side (D_theta, canonical means) gets the warm-up-scaled gradient.
        w = self._warmup()
        x = _scale_grad(means, w)
        x0s = _scale_grad(x0, w)
        x_obj = self.motion(x0s, self.labels, float(self.times[j]))
        r = x - x_obj
        terms: dict[str, Tensor] = {}
        terms["smooth"] = p.lambda_smooth * self.motion.smoothness(j)
        terms["id"] = p.lambda_id * self.motion.identity_prior(j, self.static)
        rho_i = rigid_share(x0s, x_obj, r, p.share_eps)
        rho = rho_i.mean()
        if p.hinge:
            terms["share"] = p.lambda_share * torch.clamp(p.tau - rho, min=0.0) ** 2
        if j > 0 and self._active(p.velocity_start):
            t_prev = float(self.times[j - 1])
            x_prev = _scale_grad(self.model.at_time(t_prev)[0], w)
            x_obj_prev = self.motion(x0s, self.labels, t_prev)
            d = (x - x_prev) - (x_obj - x_obj_prev)
            terms["vel"] = p.lambda_vel * (d * d).sum(-1).mean()
        rn = r.norm(dim=-1)
        m = self.modulation_weights(rn) if p.modulation else torch.zeros_like(rn)
        if self._active(p.residual_start):
            terms["res"] = p.lambda_res * ((1.0 - m) * rn * rn).mean()
        total = sum(terms.values())
        stats = {f"L_{k}": float(v.detach()) for k, v in terms.items()}
        stats["rho"] = float(rho.detach())
        return total, stats

    def _update_learning_rates(self) -> None:
        super()._update_learning_rates()
        mc = self.phase2.motion
        lr = cosine_lr(mc.lr, mc.lr_final, self.iteration / self.total)
        for g in self.motion_optimizer.param_groups:
            g["lr"] = lr

    def step(self) -> dict[str, float]:
        """One Phase 2 iteration: the Phase 1 step with the auxiliary losses, plus an M_phi
        update once M_phi is active."""
        stats = super().step()
        if self.phase2.use_motion and self._active(self.phase2.motion_start):
            self.motion_optimizer.step()
        self.motion_optimizer.zero_grad(set_to_none=True)
        return stats

    # -- diagnostics (Appendix C) -------------------------------------------------------------
    @torch.no_grad()
    def residuals_at(self, t: float, labels: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """(x_i(t) [N, 3], r_i(t) [N, 3]) at time `t`, optionally with other `labels`."""
        x = self.model.at_time(float(t))[0]
        lab = self.labels if labels is None else labels
        return x, x - self.motion(self.model.means, lab, float(t))

    @torch.no_grad()
    def diagnostics(self, shuffles: int = 5, seed: int = 0) -> dict:
        """Appendix C diagnostics over every stored frame: per-object and mean rigid share,
        residual mean, motion variance, the fraction of Gaussians with m_i > 0.5, and the
        shuffle test (residual energy under `shuffles` random label permutations over that
        with the true labels, no retraining)."""
        k = self.assignment.num_objects
        x0 = self.model.means
        labels = self.labels
        rho_k = np.zeros(k)
        res_k = np.zeros(k)
        var_k = np.zeros(k)
        energy = 0.0
        rho_all = 0.0
        for t in self.times:
            x, r = self.residuals_at(float(t))
            x_obj = x - r
            rho_i = rigid_share(x0, x_obj, r, self.phase2.share_eps)
            rho_all += float(rho_i.mean())
            rn = r.norm(dim=-1)
            energy += float((rn * rn).mean())
            disp = x - x0
            for j in range(k):
                sel = labels == j
                if sel.any():
                    rho_k[j] += float(rho_i[sel].mean())
                    res_k[j] += float(rn[sel].mean())
                    dj = disp[sel]
                    var_k[j] += float(((dj - dj.mean(0)) ** 2).sum(-1).mean())
        nt = len(self.times)
        g = torch.Generator().manual_seed(seed)
        ratios = []
        for _ in range(shuffles):
            perm = labels[torch.randperm(len(labels), generator=g)]
            e = 0.0
            for t in self.times:
                _, r = self.residuals_at(float(t), perm)
                e += float((r * r).sum(-1).mean())
            ratios.append(e / max(energy, 1e-30))
        ema = self.residual_ema
        m = torch.sigmoid((ema - ema.mean()) / (ema.std(unbiased=False) + 1e-6))
        counts = self.assignment.counts()
        names = self.assignment.names
        return {
            "objects": [
                {
                    "label": j, "name": names.get(j, f"object {j}"), "gaussians": counts[j],
                    "static": bool(self.static[j]), "rigid_share": rho_k[j] / nt,
                    "residual_mean": res_k[j] / nt, "motion_variance": var_k[j] / nt,
                }
                for j in range(k)
            ],  # fmt: skip
            "rigid_share": rho_all / nt,
            "residual_energy": energy / nt,
            "modulated_fraction": float((m > 0.5).float().mean()) if self._ema_started else 0.0,
            "shuffle_ratio": float(np.mean(ratios)) if ratios else math.nan,
            "shuffle_ratios": ratios,
            "assignment": self.assignment.source,
            "num_objects": k,
            **self._mask_agreement(),
        }

    def _mask_agreement(self) -> dict:
        """For an unsupervised assignment of a scene that has masks: the adjusted Rand index of
        the trajectory clusters against mask voting over all Gaussians (empty otherwise)."""
        if self.assignment.source != "trajectories" or not self.scene.has_masks:
            return {}
        cfg = dataclasses.replace(self.phase2.assign, source="masks")
        reference = assign_objects(self.model, self.scene, self.extent, cfg)
        return {
            "mask_agreement_ari": adjusted_rand_index(self.assignment.labels, reference.labels),
            "mask_objects": reference.num_objects - 1,
        }

    @torch.no_grad()
    def motion_export(self) -> dict[str, np.ndarray]:
        """Per-object per-frame motion for later phases: rotations (linear part) [K, T, 3, 3],
        translations [K, T, 3], centroids of each object's Gaussians [K, T, 3] and their
        velocities [K, T, 3] (central differences in world units per unit time), frame times
        [T] and labels [N]."""
        a, b = self.motion.trajectory()
        k, nt = a.shape[0], a.shape[1]
        cent = np.zeros((k, nt, 3))
        labels = self.labels.numpy()
        for i, t in enumerate(self.times):
            x = self.model.at_time(float(t))[0].double().numpy()
            for j in range(k):
                sel = labels == j
                if sel.any():
                    cent[j, i] = x[sel].mean(0)
        vel = np.gradient(cent, self.times, axis=1) if nt > 1 else np.zeros_like(cent)
        return {
            "rotations": a, "translations": b, "centroids": cent, "velocities": vel,
            "times": self.times.copy(), "labels": labels.astype(np.int64),
        }  # fmt: skip
