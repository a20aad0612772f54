"""Phase 2's motion strategy: M_phi and the regularisers, plugged into Phase 1's trainer.

`MotionStrategy` is a `sync4d.phase1.plugin.TrainerPlugin`: the trainer it is plugged into
runs Phase 1's step unchanged (render, photometric loss, Adam on the Gaussians and D_theta,
densification) and calls the strategy at its fixed points:

- before the backward pass, `loss`: the loss-term objects (`sync4d.phase2.terms`), summed in
  order, from M_phi's start on;
- after Phase 1's optimizer and densification steps, `after_step`: M_phi's own Adam step
  (held objects' rows get zero gradients and keep their transform) and the watchdog on it;
- `update_learning_rates`: M_phi's cosine rate; `watched`: M_phi's parameters for the
  watchdog's gradient check; `on_gaussians_changed`: re-assignment;
- `state` / `restore`: M_phi, its Adam moments, the labels, the residual EMA, the static flags
  and the motion export, in the same checkpoint as Phase 1's.

How the trainer is built, M_phi started (closed-form fit, refinement) and resumed is
`sync4d.phase2.trainer`'s; the strategy holds the state and the per-step policy.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor

from sync4d import watchdog
from sync4d.data.scene import Frame, Scene
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.plugin import CheckpointKind, TrainerPlugin
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.phase2.assign import (
    Assignment,
    assign_objects,
    displacement_curves,
    node_votes,
)
from sync4d.phase2.config import Phase2Config
from sync4d.phase2.motion import ObjectMotion, cosine_lr, make_motion, still_objects
from sync4d.phase2.terms import LossTerm, TermContext, default_terms, scale_grad

__all__ = ["MotionStrategy", "frame_times", "phase2_densify"]


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
    """D_theta's positions [N, 3] (float64) of a strategy's model at each stored frame time,
    evaluated one frame at a time on every pass (no list of T arrays in memory)."""

    def __init__(self, strategy: MotionStrategy) -> None:
        self.strategy = strategy

    @torch.no_grad()
    def __iter__(self) -> Iterator[np.ndarray]:
        model = self.strategy.trainer.model
        for t in self.strategy.times:
            yield model.at_time(float(t))[0].double().numpy()


class MotionStrategy(TrainerPlugin):
    """M_phi, the object assignment and the Phase 2 regularisers, plugged into `trainer`."""

    kind = CheckpointKind.PHASE2
    phase_name = "Phase 2"

    def __init__(
        self,
        trainer: Phase1Trainer,
        phase2: Phase2Config | None = None,
        assignment: Assignment | None = None,
        terms: list[LossTerm] | None = None,
    ) -> None:
        """Plug into `trainer` (its model and scene: Phase 1's result). `assignment`: the
        object labels (default: `assign_objects`); `terms`: the regularisers, summed in order
        (default: the paper's, `sync4d.phase2.terms.default_terms`). M_phi starts at its
        near-identity table; `sync4d.phase2.trainer.start_motion` fits and refines it."""
        self.trainer = trainer
        self.phase2 = phase2 = phase2 or Phase2Config()
        #: The loss terms `loss` sums, in order.
        self.terms: list[LossTerm] = default_terms(phase2) if terms is None else list(terms)
        self.times = frame_times(trainer.scene)
        self.assignment = assignment or assign_objects(
            trainer.model, trainer.scene, trainer.extent, phase2.assign
        )
        k = self.assignment.num_objects
        mc = phase2.motion
        self.motion: ObjectMotion = make_motion(mc, k, self.times, trainer.config.seed)
        #: Base colours [N, 1, 3] the refinement's template was last rendered with (its texture
        #: fit's result; None before a refinement).
        self.template_colours: Tensor | None = None
        self.motion_optimizer = torch.optim.Adam(
            self.motion.parameters(), lr=mc.lr, eps=1e-15, fused=True
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
        trainer.plug(self)

    @torch.no_grad()
    def fit_motion(self, positions: list[np.ndarray] | None = None) -> None:
        """Set M_phi to the closed-form fit of every object's canonical Gaussians onto their
        D_theta positions at each stored frame (MotionConfig.init = "fit"; `positions`: those
        positions [T][N, 3] when the caller has them); held objects keep their transform.
        On a node model (`sync4d.phase1.nodes`) an object with at least 3 nodes (by their
        Gaussians' votes, `node_votes`) is fitted on its nodes' trajectories instead:
        hundreds of rows, not tens of thousands."""
        model = self.trainer.model
        labels = self.labels.numpy()
        points = model.motion_model.control_points(model)
        if points is not None:  # objects with >= 3 nodes: fitted on their node trajectories
            node_labels = node_votes(points, model.means.detach(), labels,
                                     self.assignment.num_objects)  # fmt: skip
            counts = np.bincount(node_labels, minlength=self.assignment.num_objects)
            on_nodes = counts >= 3
            node_x0 = points.positions.double().numpy()
            node_pos = [node_x0 + points.offset(float(t)).double().numpy()
                        for t in self.times]  # fmt: skip
            self.motion.fit_to(node_x0, node_pos, np.where(on_nodes[node_labels], node_labels,
                                                           -1))  # fmt: skip
            self.node_fitted_objects = int(on_nodes.sum())
            if on_nodes.all():
                return
            labels = np.where(on_nodes[labels], -1, labels)
        x0 = model.means.double().numpy()
        pos = self.frame_positions() if positions is None else positions
        self.motion.fit_to(x0, pos, labels)

    def frame_positions(self) -> list[np.ndarray]:
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
                self.trainer.model.means.detach().double().numpy(),
                _Positions(self) if positions is None else positions,
                self.labels.numpy(), k, p.still_position * self.trainer.extent,
                p.still_rotation, self.motion.rigid, all_or_none=not p.freeze_static,
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
        mark the trainer's iterations up to `total` done without running them (counted in
        `loop_skipped`); returns whether it did. The model stays as it is (Phase 1's) and
        M_phi at the held transforms."""
        trainer = self.trainer
        moves = not self.nothing_moves
        if not self.phase2.skip_still_scene or moves or trainer.iteration >= total:
            return False
        self.loop_skipped += total - trainer.iteration
        trainer.iteration = total
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
        disp = np.linalg.norm(displacement_curves(self.trainer.model, samples), axis=-1).mean(1)
        labels = self.labels.numpy()
        below = self.phase2.static_fraction * self.trainer.extent
        for j in range(1, k):
            sel = labels == j
            if not sel.any() or disp[sel].mean() < below:
                static[j] = True
        return static

    def on_gaussians_changed(self) -> None:
        """Densification changed N: re-run the assignment, restart the modulation EMA and
        decide again which objects are held static."""
        t = self.trainer
        a = assign_objects(t.model, t.scene, t.extent, self.phase2.assign)
        if a.num_objects != self.assignment.num_objects:
            a.labels = np.minimum(a.labels, self.assignment.num_objects - 1)
            a.num_objects = self.assignment.num_objects
        self.assignment = a
        self._set_labels(a.labels)
        self.hold_still_objects()

    # -- schedule --------------------------------------------------------------------------
    def _active(self, start: int) -> bool:
        return self.phase2.simultaneous or self.trainer.iteration >= start

    def _warmup(self) -> float:
        p = self.phase2
        if p.simultaneous:
            return 1.0
        span = max(1, p.warmup_end - p.warmup_start)
        return min(1.0, max(0.0, (self.trainer.iteration - p.warmup_start) / span))

    # -- the step's hooks -------------------------------------------------------------------
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

    def loss(self, frame: Frame, means: Tensor) -> tuple[Tensor | None, dict[str, float]]:
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
        model = self.trainer.model
        j = self.motion.frame_index(frame.time)
        w = self._warmup()
        x = scale_grad(means, w)
        x0s = scale_grad(model.means, w)
        x_obj = self.motion(x0s, self.labels, float(self.times[j]))
        return TermContext(
            iteration=self.trainer.iteration, simultaneous=p.simultaneous, motion=self.motion,
            model=model, labels=self.labels, static=self.static, times=self.times, j=j,
            w=w, x=x, x0=x0s, x_obj=x_obj, r=x - x_obj, share_eps=p.share_eps,
            modulate=self.modulation_weights,
        )  # fmt: skip

    def update_learning_rates(self) -> None:
        """M_phi's rate: cosine from `motion.lr` to `motion.lr_final` over the trainer's run."""
        mc = self.phase2.motion
        lr = cosine_lr(mc.lr, mc.lr_final, self.trainer.iteration / self.trainer.total)
        for g in self.motion_optimizer.param_groups:
            g["lr"] = lr

    def after_step(self) -> None:
        """M_phi's update once it is active, then the watchdog's check of its values."""
        t = self.trainer
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
        watchdog.check_params(t.phase_name, t.iteration, motion, units, t.watch_scale)

    def watched(self) -> tuple[dict[str, Tensor], dict[str, str]]:
        """M_phi's parameters (``motion.*``, rows: objects): their gradients are checked with
        Phase 1's before either optimizer steps."""
        motion = dict(self.motion.named_parameters(prefix="motion"))
        return motion, dict.fromkeys(motion, "objects")

    # -- checkpoint state -------------------------------------------------------------------
    def state(self) -> tuple[dict[str, Tensor], dict]:
        """M_phi (``motion.*``), its Adam moments (``motion_optim.*``), the labels, residual
        EMA and static flags (``phase2.*``) and the motion export (``export.*``, for readers
        that build no trainer); settings under ``"phase2"``."""
        tensors: dict[str, Tensor] = {}
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
        meta = {"phase2": {
            "num_objects": a.num_objects,
            "names": {str(k): v for k, v in a.names.items()},
            "assignment": a.source,
            "motion_kind": self.phase2.motion.kind,
            "motion_config": dataclasses.asdict(self.phase2.motion),
            "motion_rigid": self.motion.rigid,
            "times": [float(t) for t in self.times],
            "ema_started": self.ema_started,
            "motion_adam_steps": steps,
        }}  # fmt: skip
        return tensors, meta

    def restore(self, tensors: dict[str, Tensor], meta: dict) -> None:
        """M_phi (with its held objects), its optimizer and the Phase 2 loop state."""
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

    # -- export ---------------------------------------------------------------------------------
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
            x = self.trainer.model.at_time(float(t))[0].double().numpy()
            for j in range(k):
                sel = labels == j
                if sel.any():
                    cent[j, i] = x[sel].mean(0)
        vel = np.gradient(cent, self.times, axis=1) if nt > 1 else np.zeros_like(cent)
        return {
            "rotations": a, "translations": b, "centroids": cent, "velocities": vel,
            "times": self.times.copy(), "labels": labels.astype(np.int64),
        }  # fmt: skip
