"""Phase 1's motion as a plug-in: what moves the canonical Gaussians to time t, one registered
implementation per value of `Phase1Config.motion`, with the hooks Phase 2's motion strategy
already has (the state at t, parameter groups, rates, a regulariser, after the optimizer and
after densification, state and restore, counts).

Design. `DeformableGaussians` holds one `Motion` (``model.motion_model``) and asks it for the
deformed state (`Motion.deformed`); `Phase1Trainer` and the densifier call its hooks at fixed
points of the step and never test which motion it is. Two are registered:

* ``"gaussians"`` (`per_gaussian.GaussianMotion`): D_theta on every moving Gaussian (the
  paper), static Gaussians skipped (`sync4d.phase1.static`);
* ``"nodes"`` (`control_nodes.NodesMotion`): a coarse stage of the former, then a few hundred
  control nodes whose rigid motions each Gaussian blends (`sync4d.phase1.nodes`).

A new motion model is a subclass of `Motion` in one file and one `register_motion` row; the
config accepts every registered name. A checkpoint records ``"motion"`` (absent: the
per-Gaussian model) and whatever the motion's `state` adds; `motion_from_state` rebuilds it.
"""

from sync4d.phase1.motion.base import (
    MOTIONS,
    ControlPoints,
    Motion,
    motion_for,
    motion_from_state,
    register_motion,
)
from sync4d.phase1.motion.control_nodes import NodesMotion
from sync4d.phase1.motion.per_gaussian import GaussianMotion

register_motion(GaussianMotion)
register_motion(NodesMotion)

__all__ = [
    "MOTIONS",
    "ControlPoints",
    "GaussianMotion",
    "Motion",
    "NodesMotion",
    "motion_for",
    "motion_from_state",
    "register_motion",
]
