"""Phase 2: in-loop motion decomposition (paper Sec. 3.2-3.4, Appendix A "Phase 2", App. C).

Training continues from a Phase 1 model. Every Gaussian i has an object label o(i) (from
`sync4d.phase2.assign`); M_phi predicts where each object carries its Gaussians,
x~_i(t) = M_phi(o(i), t)(x0_i) (Eq. 5), and the residual r_i(t) = x_i(t) - x~_i(t) (Eq. 6)
enters five regularisers plus the identity prior on static objects. Rendering is untouched: it
always uses D_theta's x_i(t).

The regularisers are loss-term objects (`sync4d.phase2.terms`: each its weight and start from
the config), summed by the motion strategy's `loss` in their order;
`phase2_trainer(terms=...)` replaces them. Staged activation (Appendix A): M_phi and the
smoothness, rigid-share and identity terms from iteration `motion_start` (200), velocity
coherence from `velocity_start` (300), the modulated residual energy from `residual_start`
(600), and a linear warm-up of all auxiliary terms over [`warmup_start`, `warmup_end`]
(500-1000). Each of these fields is declared `ranged(..., scales=0)`, so `fit --iters` scales
it (`sync4d.config.phase2_budget`). The
paper's "400-iteration head start lets shared transforms capture the dominant rigid component
first" needs M_phi to learn before the warm-up ends, so the warm-up scales only the gradient
the auxiliary terms send into the scene (D_theta, Gaussians); M_phi always sees them at full
weight from their start iteration. `simultaneous` switches every term on at iteration 0
without warm-up (the paper's failing ablation).

Before the loop, `MotionConfig.init = "fit"` starts the SE(3) table at the closed-form fit of
D_theta's motion, and `refine_steps` > 0 refines it photometrically (not in the paper;
`sync4d.phase2.refine`). The room: `config` (the settings), `assign` (object labels), `motion`
(M_phi), `terms` (the regularisers), `strategy` (the plug-in), `refine`, `diagnostics`
(Appendix C) and this builder.

Still objects (not in the paper): after the assignment and every re-assignment, objects whose
Gaussians D_theta keeps within `still_position` of the extent of their mean positions over the
training times (and which do not turn by more than `still_rotation`) are still. With
`freeze_static` they are held at their constant transform (the closed-form fit of their
canonical Gaussians onto those mean positions): M_phi masks them (no gradient), their Adam
moments are cleared and the refinement skips them. When every object is still the scene has
no motion: with `skip_still_scene` (default) all are held and `skip_loop` marks Phase 2's
iterations done without running them (`sync4d.pipeline.fit` says so). Counters: `skip_counts`.

Shape: Phase 2 is Phase 1's trainer with a plug-in, not a subclass. `phase2_trainer` builds a
`Phase1Trainer` with Phase 2's policies passed in at construction (the densifier's settings,
`phase2_densify`: no pruning after Phase 1's stop, no densification without `densify`; the
`FinishedSchedule`: full resolution, full SH degree, D_theta on at its full rate) and plugs in
the `sync4d.phase2.strategy.MotionStrategy` (M_phi, the assignment, the loss terms, M_phi's
Adam step after Phase 1's); `start_motion` fits and refines M_phi's start; `phase2_from_state`
rebuilds both from a checkpoint. The pipeline's one loop steps the trainer; `refine` and
`diagnostics` read the strategy (and its `trainer`) through public names.
"""

from __future__ import annotations

import numpy as np
from torch import Tensor

from sync4d.data.scene import Scene
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.trainer import FinishedSchedule, Phase1Trainer
from sync4d.phase2.assign import Assignment
from sync4d.phase2.config import Phase2Config
from sync4d.phase2.refine import refine_motion
from sync4d.phase2.strategy import MotionStrategy, phase2_densify
from sync4d.phase2.terms import LossTerm

__all__ = ["phase2_from_state", "phase2_trainer", "start_motion"]


def phase2_trainer(
    model: DeformableGaussians,
    scene: Scene,
    config: Phase1Config | None = None,
    phase2: Phase2Config | None = None,
    total_iterations: int | None = None,
    threads: int | None = None,
    assignment: Assignment | None = None,
    start: bool = True,
    terms: list[LossTerm] | None = None,
) -> MotionStrategy:
    """Phase 1's trainer on `model` (Phase 1's result) with Phase 2's policies and the motion
    strategy plugged in; returns the strategy (its `trainer` runs the loop). `assignment`: the
    object labels (default: `assign_objects`); `start`: hold the still objects and, when
    `MotionConfig.init` is "fit", fit (and refine) M_phi's start (off when a checkpoint's
    state replaces it); `terms`: the regularisers (default: the paper's)."""
    phase2 = phase2 or Phase2Config()
    total = phase2.iterations if total_iterations is None else total_iterations
    densify = phase2_densify((config or Phase1Config()).densify, phase2)
    trainer = Phase1Trainer(model, scene, config, total, threads, densify=densify,
                            schedule=FinishedSchedule())  # fmt: skip
    strategy = MotionStrategy(trainer, phase2, assignment, terms)
    if start:
        start_motion(strategy)
    return strategy


def start_motion(strategy: MotionStrategy) -> None:
    """M_phi's start: hold the still objects, and with `MotionConfig.init` "fit" the
    closed-form fit of D_theta's motion, then the photometric refinement when
    `refine_steps` > 0 (D_theta's positions at the stored frames computed once for both)."""
    mc = strategy.phase2.motion
    fit = mc.init == "fit"
    positions: list[np.ndarray] | None = strategy.frame_positions() if fit else None
    strategy.hold_still_objects(positions)
    if fit:
        strategy.fit_motion(positions)
        if mc.refine_steps > 0:
            refine_motion(strategy)


def phase2_from_state(
    tensors: dict[str, Tensor],
    meta: dict,
    scene: Scene,
    *,
    config: Phase1Config | None = None,
    phase2: Phase2Config | None = None,
    total_iterations: int | None = None,
    threads: int | None = None,
    near: float | None = None,
) -> MotionStrategy:
    """The Phase 2 trainer and strategy a checkpoint's `state` described, with `phase2`'s
    settings (M_phi's start is not fitted again: the stored table replaces it). Raises
    KeyError for a missing tensor or setting, ValueError for one that does not fit."""
    model = DeformableGaussians.from_state(tensors, meta, near)
    info = meta["phase2"]
    labels = tensors["phase2.labels"].numpy().astype("int64")
    if len(labels) != model.num_gaussians:
        raise ValueError("'phase2.labels' does not match the Gaussian count")
    names = {int(k): v for k, v in info["names"].items()}
    assignment = Assignment(labels, int(info["num_objects"]), names, info["assignment"])
    total = total_iterations or meta["total_iterations"]
    strategy = phase2_trainer(model, scene, config, phase2, total, threads, assignment,
                              start=False)  # fmt: skip
    strategy.trainer.restore(tensors, meta)
    strategy.restore(tensors, meta)
    return strategy
