"""Phase 2: in-loop motion decomposition (paper Sec. 3.2-3.4, Appendix A "Phase 2", App. C).

Training continues from a Phase 1 model. Every Gaussian i has an object label o(i) (from
`sync4d.phase2.assign`); M_phi predicts where each object carries its Gaussians,
x~_i(t) = M_phi(o(i), t)(x0_i) (Eq. 5), and the residual r_i(t) = x_i(t) - x~_i(t) (Eq. 6)
enters five regularisers plus the identity prior on static objects. Rendering is untouched: it
always uses D_theta's x_i(t).

The regularisers are loss-term objects (`sync4d.phase2.terms`: each its weight and start from
this config), summed by `auxiliary_loss` in their order; `Phase2Trainer(terms=...)` replaces
them. Staged activation (Appendix A): M_phi and the smoothness, rigid-share and identity terms
from iteration `motion_start` (200), velocity coherence from `velocity_start` (300), the
modulated residual energy from `residual_start` (600), and a linear warm-up of all auxiliary
terms over [`warmup_start`, `warmup_end`] (500-1000). Each of these fields is declared
`ranged(..., scales=0)`, so `fit --iters` scales it (`sync4d.config.phase2_budget`). The
paper's "400-iteration head start lets shared transforms capture the dominant rigid component
first" needs M_phi to learn before the warm-up ends, so the warm-up scales only the gradient
the auxiliary terms send into the scene (D_theta, Gaussians); M_phi always sees them at full
weight from their start iteration. `simultaneous` switches every term on at iteration 0
without warm-up (the paper's failing ablation).

Before the loop, `MotionConfig.init = "fit"` starts the SE(3) table at the closed-form fit of
D_theta's motion, and `refine_steps` > 0 refines it photometrically (not in the paper;
`sync4d.phase2.refine`). The room: `assign` (object labels), `motion` (M_phi), `refine`,
`diagnostics` (Appendix C and the motion export) and this trainer.

Still objects (not in the paper): after the assignment and every re-assignment, objects whose
Gaussians D_theta keeps within `still_position` of the extent of their mean positions over the
training times (and which do not turn by more than `still_rotation`) are still. With
`freeze_static` they are held at their constant transform (the closed-form fit of their
canonical Gaussians onto those mean positions): M_phi masks them (no gradient), their Adam
moments are cleared and the refinement skips them. When every object is still the scene has
no motion: with `skip_still_scene` (default) all are held and `skip_loop` marks Phase 2's
iterations done without running them (`sync4d.pipeline.fit` says so). Counters: `skip_counts`.

Shape: `Phase2Trainer` is Phase 1's loop (it subclasses `Phase1Trainer`) with its policies
passed in at construction, not rewritten afterwards: the densifier's settings
(`phase2_densify`: no pruning after Phase 1's stop; no densification without `densify`) and
the `FinishedSchedule` (full resolution, full SH degree, D_theta on at its full rate). It
overrides Phase 1's documented hooks only: `auxiliary_loss` (the terms), `on_gaussians_changed`
(re-assignment), `update_learning_rates` (M_phi's rate) and `step` (M_phi's update), plus the
checkpoint's `state` / `restore` / `from_state`. `refine` and `diagnostics` read it through
public names (`image`, `background`, `ema_started`, ...).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from sync4d import watchdog
from sync4d.data.scene import Frame, Scene
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.trainer import FinishedSchedule, Phase1Config, Phase1Trainer
from sync4d.phase2.assign import (
    AssignConfig,
    Assignment,
    assign_objects,
    displacement_curves,
    node_votes,
)
from sync4d.phase2.diagnostics import diagnostics, motion_export
from sync4d.phase2.motion import (
    MotionConfig,
    ObjectMotion,
    cosine_lr,
    make_motion,
    still_objects,
)
from sync4d.phase2.refine import refine_motion
from sync4d.phase2.terms import LossTerm, TermContext, default_terms, scale_grad
from sync4d.settings import ranged

__all__ = ["Phase2Config", "Phase2Trainer", "frame_times", "phase2_densify"]


@dataclass(frozen=True)
class Phase2Config:
    """Phase 2 hyperparameters (Appendix A; the paper's values as defaults) and ablations."""

    #: Phase 2 iterations after Phase 1 (Appendix A: 20k; 0: only M_phi's start, its
    #: closed-form fit and refinement).
    iterations: int = ranged(20_000, 0)
    motion: MotionConfig = field(default_factory=MotionConfig)
    assign: AssignConfig = field(default_factory=AssignConfig)
    #: Weight of the modulated residual energy (Eq. 8).
    lambda_res: float = ranged(0.02, 0.0)
    #: Weight of the rigid-share hinge (Eq. 9).
    lambda_share: float = ranged(0.01, 0.0)
    #: Target rigid share of the hinge: mean rho below tau is penalised (Eq. 9).
    tau: float = ranged(0.35, 0.0, 1.0)
    #: Weight of the velocity coherence term (Eq. 10).
    lambda_vel: float = ranged(0.01, 0.0)
    #: Weight of M_phi's temporal smoothness (Eq. 11).
    lambda_smooth: float = ranged(0.01, 0.0)
    #: Weight of the identity prior on static objects (Eq. 12).
    lambda_id: float = ranged(0.001, 0.0)
    #: EMA factor of the per-Gaussian residual magnitude (Appendix A's modulation).
    eta: float = ranged(0.95, 0.0, 1.0)
    #: Epsilon in the rigid share's denominator (metres).
    share_eps: float = ranged(1e-6, 0.0, lo_open=True)
    #: Iteration from which M_phi trains and the smoothness, rigid-share and identity terms act.
    motion_start: int = ranged(200, 0, scales=0)
    #: Iteration from which the velocity coherence term acts.
    velocity_start: int = ranged(300, 0, scales=0)
    #: Start of the linear warm-up of the auxiliary terms' gradient into the scene.
    warmup_start: int = ranged(500, 0, scales=0)
    #: End of that warm-up (full weight from here).
    warmup_end: int = ranged(1000, 0, scales=0)
    #: Iteration from which the modulated residual energy acts.
    residual_start: int = ranged(600, 0, scales=0)
    #: Keep densifying (clone/split/prune, opacity reset) on Phase 1's schedule, counted from
    #: Phase 2's first iteration; every change re-runs the assignment. Off by default: Phase 1's
    #: densification window is over when Phase 2 starts.
    densify: bool = False
    #: An object whose Gaussians' mean Phase 1 displacement stays below this fraction of the
    #: scene extent is static (it gets the identity prior); background always is.
    static_fraction: float = ranged(0.005, 0.0)
    #: Hold the objects that do not move (`still_position`, `still_rotation`) at their
    #: constant transform: their M_phi rows get no update (masked: zero gradients; Adam
    #: moments cleared) and the refinement skips them. Decided after the assignment and on
    #: every re-assignment. Not in the paper, which trains every object's transform and pulls
    #: the static ones to the identity (lambda_id). Off by default because it changes moving
    #: objects too, through Eq. 9 alone: the rigid share is a mean over all Gaussians, where a
    #: held Gaussian counts its constant transform's share (0 for one D_theta leaves in place)
    #: while a trained static row, which Adam moves by about its rate per step on noise
    #: gradients, makes its Gaussians count about 0.5 (oracle scene, init fit: mean rho 0.37
    #: held vs 0.73; moving rows differ by up to 2e-3 after 10 steps, and are bit-identical
    #: without the hinge and the modulation: tests/phase2/test_phase2_static.py).
    freeze_static: bool = False
    #: When no object moves (each passes the test below), hold every object at its constant
    #: transform and skip Phase 2's loop: its checkpoint is Phase 1's model with those
    #: transforms. No moving object exists to be changed; the Gaussians miss Phase 2's
    #: photometric iterations, which a scene without motion can get from a longer Phase 1.
    #: Not in the paper.
    skip_still_scene: bool = True
    #: An object is still when none of its Gaussians strays farther than this fraction of the
    #: scene extent from its mean D_theta position over the training times (a constant offset
    #: is not motion; it goes into the held transform, the closed-form fit of the canonical
    #: positions onto the mean ones). 1e-3 is Phase 1's static threshold
    #: (`phase1.static.position`): under a pixel at the usual framing (an image spans about the
    #: extent in a few hundred pixels), so the images cannot tell the held transform from the
    #: object's D_theta motion. The largest spread, not the mean: one Gaussian that moves keeps
    #: its object trained. (Measured: a still synthetic scene after 1000 default Phase 1
    #: iterations spreads at most 0.9e-3 of the extent about offsets of up to 3.3e-2.)
    still_position: float = ranged(1e-3, 0.0)
    #: And the closed-form rotation (Kabsch) of its Gaussians from their mean positions to
    #: those at each training time stays below this (radians): the position test alone lets a
    #: small object turn by `still_position * extent / radius`. 0.01 is Phase 1's
    #: `phase1.static.rotation`.
    still_rotation: float = ranged(0.01, 0.0)
    # Ablation switches.
    #: Ablation: false trains Phase 2 without M_phi and its terms.
    use_motion: bool = True
    #: Ablation: false drops the residual modulation m_i (every residual penalised).
    modulation: bool = True
    #: Ablation: false drops the rigid-share hinge.
    hinge: bool = True
    #: Ablation: every term from iteration 0, no warm-up (the paper's failing variant).
    simultaneous: bool = False


def frame_times(scene: Scene) -> np.ndarray:
    """Sorted distinct training times [T] of `scene` (M_phi's stored frames)."""
    return np.unique(np.asarray([f.time for f in scene.train], dtype=np.float64))


def phase2_densify(d: DensifyConfig, p: Phase2Config) -> DensifyConfig:
    """The densifier settings of Phase 2 from Phase 1's `d`: Phase 2 refines a finished
    reconstruction, so its rows change only through its own `densify` switch (on Phase 1's
    schedule, counted from Phase 2's first iteration), never by Phase 1's pruning after
    densification."""
    d = dataclasses.replace(d, prune_after_stop=False)
    if not p.densify:
        never = 2**62
        d = dataclasses.replace(d, start=never, opacity_reset_interval=never)
    return d


class _Positions:
    """D_theta's positions [N, 3] (float64) of a trainer's model at each stored frame time,
    evaluated one frame at a time on every pass (no list of T arrays in memory)."""

    def __init__(self, trainer: Phase2Trainer) -> None:
        self.trainer = trainer

    @torch.no_grad()
    def __iter__(self) -> Iterator[np.ndarray]:
        for t in self.trainer.times:
            yield self.trainer.model.at_time(float(t))[0].double().numpy()


class Phase2Trainer(Phase1Trainer):
    """Phase 1's loop plus M_phi and the Phase 2 regularisers, on a Phase 1 model."""

    KIND = "sync4d.phase2"

    def __init__(
        self,
        model: DeformableGaussians,
        scene: Scene,
        config: Phase1Config | None = None,
        phase2: Phase2Config | None = None,
        total_iterations: int | None = None,
        threads: int | None = None,
        assignment: Assignment | None = None,
        start_motion: bool = True,
        terms: list[LossTerm] | None = None,
    ) -> None:
        """`assignment`: the object labels (default: `assign_objects`); `start_motion`: fit
        (and refine) M_phi's start when `MotionConfig.init` is "fit" (off when a checkpoint's
        state replaces it); `terms`: the regularisers, summed in order (default: the paper's,
        `sync4d.phase2.terms.default_terms`)."""
        phase2 = phase2 or Phase2Config()
        total = phase2.iterations if total_iterations is None else total_iterations
        densify = phase2_densify((config or Phase1Config()).densify, phase2)
        super().__init__(
            model, scene, config, total, threads, densify=densify, schedule=FinishedSchedule()
        )
        self.phase2 = phase2
        #: The loss terms `auxiliary_loss` sums, in order.
        self.terms: list[LossTerm] = default_terms(phase2) if terms is None else list(terms)
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
        #: M_phi object-row updates made and skipped (rows of held objects), over the optimizer
        #: steps of this process; the refinement's (object, stored frame) tracking visits made
        #: and skipped (static objects; every pass counted); Phase 2 iterations skipped because
        #: no object moves (`skip_loop`).
        self.motion_updates = 0
        self.motion_updates_skipped = 0
        self.refine_visits = 0
        self.refine_visits_skipped = 0
        self.loop_skipped = 0
        #: Objects whose M_phi start was fitted on node trajectories (node models only).
        self.node_fitted_objects = 0
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
                     "refine_retrack_lr", "refine_restart_jump"):  # fmt: skip
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
        fit = mc.init == "fit" and start_motion
        positions = self._frame_positions() if fit else None
        if start_motion:  # else the checkpoint's flags replace the decision (`restore`)
            self.hold_still_objects(positions)
        if fit:
            self.fit_motion(positions)
            if mc.refine_steps > 0:
                self.refine_motion()

    def refine_motion(self, config: MotionConfig | None = None) -> None:
        """Photometric refinement of the SE(3) table (`sync4d.phase2.refine.refine_motion`)."""
        refine_motion(self, config)

    @torch.no_grad()
    def fit_motion(self, positions: list[np.ndarray] | None = None) -> None:
        """Set M_phi to the closed-form fit of every object's canonical Gaussians onto their
        D_theta positions at each stored frame (MotionConfig.init = "fit"; `positions`: those
        positions [T][N, 3] when the caller has them); held objects keep their transform.
        On a node model (`sync4d.phase1.nodes`) an object with at least 3 nodes (by their
        Gaussians' votes, `node_votes`) is fitted on its nodes' trajectories instead:
        hundreds of rows, not tens of thousands."""
        labels = self.labels.numpy()
        nodes = self.model.nodes
        if nodes is not None:  # objects with >= 3 nodes: fitted on their node trajectories
            node_labels = node_votes(nodes, self.model.means.detach(), labels,
                                     self.assignment.num_objects)  # fmt: skip
            counts = np.bincount(node_labels, minlength=self.assignment.num_objects)
            on_nodes = counts >= 3
            node_x0 = nodes.positions.detach().double().numpy()
            node_pos = [node_x0 + nodes.motion(self.model.deform, float(t))[1].double().numpy()
                        for t in self.times]  # fmt: skip
            self.motion.fit_to(node_x0, node_pos, np.where(on_nodes[node_labels], node_labels,
                                                           -1))  # fmt: skip
            self.node_fitted_objects = int(on_nodes.sum())
            if on_nodes.all():
                return
            labels = np.where(on_nodes[labels], -1, labels)
        x0 = self.model.means.double().numpy()
        pos = self._frame_positions() if positions is None else positions
        self.motion.fit_to(x0, pos, labels)

    def _frame_positions(self) -> list[np.ndarray]:
        """D_theta's positions [N, 3] (float64) at every stored frame time."""
        return list(_Positions(self))

    @property
    def frozen(self) -> Tensor:
        """[K] bool: the objects held at their constant transform (M_phi's `frozen`)."""
        return self.motion.frozen

    @property
    def nothing_moves(self) -> bool:
        """Whether every object is held at its constant transform: no motion to learn."""
        return bool(self.motion.frozen.all())

    @torch.no_grad()
    def hold_still_objects(self, positions: list[np.ndarray] | None = None) -> Tensor:
        """Decide which objects are still (`still_objects` with `still_position` times the
        extent and `still_rotation`) and hold them at their constant transform: all of them
        with `freeze_static`, or with `skip_still_scene` when every object is still; none
        otherwise. Their rows of M_phi's Adam moments are cleared, so that momentum does not
        move them either. `positions` [T][N, 3]: D_theta at the stored frames when the caller
        has them. Returns the flags [K] (bool)."""
        p = self.phase2
        k = self.assignment.num_objects
        frozen = torch.zeros(k, dtype=torch.bool)
        linear = offset = None
        if p.freeze_static or p.skip_still_scene:
            still, lin, off = still_objects(
                self.model.means.detach().double().numpy(),
                _Positions(self) if positions is None else positions,
                self.labels.numpy(), k, p.still_position * self.extent, p.still_rotation,
                self.motion.rigid, all_or_none=not p.freeze_static,
            )  # fmt: skip
            if p.freeze_static or still.all():
                frozen = torch.as_tensor(still)
                linear, offset = torch.as_tensor(lin).float(), torch.as_tensor(off).float()
        self.motion.hold(frozen, linear, offset)
        self._clear_frozen_moments()
        return frozen

    @torch.no_grad()
    def _clear_frozen_moments(self) -> None:
        frozen = self.motion.frozen
        if not bool(frozen.any()):
            return
        for name in self.motion.row_params:
            st = self.motion_optimizer.state.get(getattr(self.motion, name))
            if st:
                st["exp_avg"][frozen] = 0.0
                st["exp_avg_sq"][frozen] = 0.0

    def skip_loop(self, total: int) -> bool:
        """With `skip_still_scene`, when no object moves (every one held, `nothing_moves`):
        mark the iterations up to `total` done without running them (counted in
        `loop_skipped`); returns whether it did. The model stays as it is (Phase 1's) and
        M_phi at the held transforms."""
        p = self.phase2
        if not p.skip_still_scene or not self.nothing_moves or self.iteration >= total:
            return False
        self.loop_skipped += total - self.iteration
        self.iteration = total
        return True

    def skip_counts(self) -> dict[str, int]:
        """What Phase 2 skipped in this process: held objects (of K), M_phi object-row
        updates, refinement visits and loop iterations."""
        return {
            "objects": self.assignment.num_objects, "held": int(self.motion.frozen.sum()),
            "motion_updates": self.motion_updates,
            "motion_updates_skipped": self.motion_updates_skipped,
            "refine_visits": self.refine_visits,
            "refine_visits_skipped": self.refine_visits_skipped,
            "loop_skipped": self.loop_skipped,
        }  # fmt: skip

    # -- assignment state ----------------------------------------------------------------
    def _set_labels(self, labels: np.ndarray) -> None:
        self.labels = torch.as_tensor(labels, dtype=torch.long)
        #: EMA of each Gaussian's residual magnitude (the modulation's, Eq. 8) and whether it
        #: has had its first value since the labels were set.
        self.residual_ema = torch.zeros(len(labels))
        self.ema_started = False

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
        """Densification changed N: re-run the assignment, restart the modulation EMA and
        decide again which objects are held static."""
        a = assign_objects(self.model, self.scene, self.extent, self.phase2.assign)
        if a.num_objects != self.assignment.num_objects:
            a.labels = np.minimum(a.labels, self.assignment.num_objects - 1)
            a.num_objects = self.assignment.num_objects
        self.assignment = a
        self._set_labels(a.labels)
        self.hold_still_objects()

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
        if not self.ema_started:
            self.residual_ema = r.clone()
            self.ema_started = True
        else:
            self.residual_ema = eta * self.residual_ema + (1 - eta) * r
        ema = self.residual_ema
        return torch.sigmoid((ema - ema.mean()) / (ema.std(unbiased=False) + 1e-6))

    def auxiliary_loss(self, frame: Frame, means: Tensor) -> tuple[Tensor | None, dict[str, float]]:
        """The sum of the loss terms (`terms`, in order) on `frame` from M_phi's start, given
        D_theta's positions `means` [N, 3] the render used; reports each term as ``L_<name>``
        and the mean rigid share as ``rho``."""
        p = self.phase2
        if not p.use_motion or not self._active(p.motion_start):
            return None, {}
        ctx = self._term_context(frame, means)
        terms: dict[str, Tensor] = {}
        for term in self.terms:
            term.observe(ctx)
            if term.applies(ctx):
                terms[term.name] = term.loss(ctx)
        total = sum(terms.values())
        stats = {f"L_{k}": float(v.detach()) for k, v in terms.items()}
        stats["rho"] = float(ctx.rho.detach())
        return total, stats

    def _term_context(self, frame: Frame, means: Tensor) -> TermContext:
        """The terms' view of this iteration: M_phi's positions of the canonical Gaussians at
        `frame`'s stored time and the residuals of D_theta's `means`. The scene side
        (D_theta, canonical means) gets the warm-up-scaled gradient."""
        p = self.phase2
        j = self.motion.frame_index(frame.time)
        w = self._warmup()
        x = scale_grad(means, w)
        x0s = scale_grad(self.model.means, w)
        x_obj = self.motion(x0s, self.labels, float(self.times[j]))
        return TermContext(
            iteration=self.iteration, simultaneous=p.simultaneous, motion=self.motion,
            model=self.model, labels=self.labels, static=self.static, times=self.times, j=j,
            w=w, x=x, x0=x0s, x_obj=x_obj, r=x - x_obj, share_eps=p.share_eps,
            modulate=self.modulation_weights,
        )  # fmt: skip

    def update_learning_rates(self) -> None:
        """Phase 1's rates, then M_phi's (cosine from `motion.lr` to `motion.lr_final`)."""
        super().update_learning_rates()
        mc = self.phase2.motion
        lr = cosine_lr(mc.lr, mc.lr_final, self.iteration / self.total)
        for g in self.motion_optimizer.param_groups:
            g["lr"] = lr

    #: The name the watchdog gives this trainer's failures.
    phase_name = "Phase 2"

    def step(self) -> dict[str, float]:
        """One Phase 2 iteration: the Phase 1 step with the auxiliary losses, plus an M_phi
        update once M_phi is active."""
        stats = super().step()
        motion = dict(self.motion.named_parameters(prefix="motion"))
        units = dict.fromkeys(motion, "objects")
        if self.phase2.use_motion and self._active(self.phase2.motion_start):
            # Held rows get exact zero gradients (every path to M_phi's parameters goes
            # through `transform_at` or `rows_at`) and their Adam moments were cleared when
            # they were held, so the step leaves them as they are.
            frozen = self.motion.frozen
            held = int(frozen.sum())
            self.motion_optimizer.step()
            self.motion_updates += len(frozen) - held
            self.motion_updates_skipped += held
        self.motion_optimizer.zero_grad(set_to_none=True)
        watchdog.check_params(self.phase_name, self.iteration, motion, units, self.watch_scale)
        return stats

    def watched(self) -> tuple[dict[str, Tensor], dict[str, str]]:
        """Phase 1's parameters and M_phi's (``motion.*``, rows: objects): their gradients are
        checked before either optimizer steps."""
        params, units = super().watched()
        motion = dict(self.motion.named_parameters(prefix="motion"))
        return {**params, **motion}, {**units, **dict.fromkeys(motion, "objects")}

    # -- checkpoint state -------------------------------------------------------------------
    def state(self) -> tuple[dict[str, Tensor], dict]:
        """Phase 1's state plus M_phi (``motion.*``), its Adam moments (``motion_optim.*``),
        the labels, residual EMA and static flags (``phase2.*``) and the motion export
        (``export.*``, for readers that build no trainer); settings under ``"phase2"``."""
        tensors, meta = super().state()
        for k, v in self.motion.state_dict().items():
            tensors[f"motion.{k}"] = v.detach().float()
        steps: dict[str, float] = {}
        for pi, p in enumerate(self.motion_optimizer.param_groups[0]["params"]):
            st = self.motion_optimizer.state.get(p)
            if st:
                tensors[f"motion_optim.{pi}.exp_avg"] = st["exp_avg"]
                tensors[f"motion_optim.{pi}.exp_avg_sq"] = st["exp_avg_sq"]
                steps[str(pi)] = float(st["step"])
        tensors["phase2.labels"] = self.labels.to(torch.int64)
        tensors["phase2.residual_ema"] = self.residual_ema
        tensors["phase2.static"] = self.static.to(torch.uint8)
        for k, v in self.motion_export().items():
            v = torch.as_tensor(v)
            tensors[f"export.{k}"] = v if k == "labels" else v.float()
        a = self.assignment
        meta["phase2"] = {
            "num_objects": a.num_objects,
            "names": {str(k): v for k, v in a.names.items()},
            "assignment": a.source,
            "motion_kind": self.phase2.motion.kind,
            "motion_config": dataclasses.asdict(self.phase2.motion),
            "motion_rigid": self.motion.rigid,
            "times": [float(t) for t in self.times],
            "ema_started": self.ema_started,
            "motion_adam_steps": steps,
        }
        return tensors, meta

    @classmethod
    def from_state(
        cls,
        tensors: dict[str, Tensor],
        meta: dict,
        scene: Scene,
        *,
        config: Phase1Config | None = None,
        phase2: Phase2Config | None = None,
        total_iterations: int | None = None,
        threads: int | None = None,
        near: float | None = None,
    ) -> Phase2Trainer:
        """The Phase 2 trainer `state` described, with `phase2`'s settings (M_phi's start is
        not fitted again: the stored table replaces it)."""
        model = DeformableGaussians.from_state(tensors, meta, near)
        info = meta["phase2"]
        labels = tensors["phase2.labels"].numpy().astype("int64")
        if len(labels) != model.num_gaussians:
            raise ValueError("'phase2.labels' does not match the Gaussian count")
        names = {int(k): v for k, v in info["names"].items()}
        assignment = Assignment(labels, int(info["num_objects"]), names, info["assignment"])
        total = total_iterations or meta["total_iterations"]
        trainer = cls(model, scene, config, phase2, total, threads, assignment, start_motion=False)
        trainer.restore(tensors, meta)
        return trainer

    def restore(self, tensors: dict[str, Tensor], meta: dict) -> None:
        """Phase 1's `restore` plus M_phi (with its held objects), its optimizer and the Phase
        2 loop state."""
        super().restore(tensors, meta)
        info = meta["phase2"]
        self.motion.load_state(tensors)
        for pi, p in enumerate(self.motion_optimizer.param_groups[0]["params"]):
            key = str(pi)
            if key in info["motion_adam_steps"]:
                self.motion_optimizer.state[p] = {
                    "step": torch.tensor(info["motion_adam_steps"][key]),
                    "exp_avg": tensors[f"motion_optim.{key}.exp_avg"].clone(),
                    "exp_avg_sq": tensors[f"motion_optim.{key}.exp_avg_sq"].clone(),
                }
        self.residual_ema = tensors["phase2.residual_ema"].clone()
        self.ema_started = bool(info["ema_started"])
        self.static = tensors["phase2.static"].to(torch.bool).clone()
        # The stored flags (``motion.frozen``), unless the switches that set them are now off.
        p = self.phase2
        frozen = self.motion.frozen
        keep = p.freeze_static or (p.skip_still_scene and bool(frozen.all()))
        self.motion.hold(frozen & keep, self.motion.held_linear, self.motion.held_offset)
        self._clear_frozen_moments()

    # -- diagnostics (Appendix C) and export ---------------------------------------------------
    def diagnostics(self, shuffles: int = 5, seed: int = 0) -> dict:
        """Appendix C diagnostics (`sync4d.phase2.diagnostics.diagnostics`)."""
        return diagnostics(self, shuffles, seed)

    def motion_export(self) -> dict[str, np.ndarray]:
        """Per-object per-frame motion (`sync4d.phase2.diagnostics.motion_export`)."""
        return motion_export(self)
