"""Trainer plug-ins: what a later phase adds to Phase 1's training step, without a subclass
(gsplat's strategies are the model: an object with hooks around the step).

`Phase1Trainer` owns the loop body (frame, render, photometric loss, backward, Adam, the
watchdog, densification); each plug-in it holds (`Phase1Trainer.plug`) is called at fixed
points of every step, in the order they were plugged:

1. `update_learning_rates`, after Phase 1's rates are set;
2. `loss(frame, means)`, before the backward pass: terms added to the photometric loss, and
   scalars to report;
3. `watched`: parameters whose gradients and values the watchdog checks with Phase 1's;
4. `after_step`, after Phase 1's optimizer, node and densification steps: the plug-in's own
   optimizer step;
5. `on_gaussians_changed`, when densification changed the number of Gaussians.

A checkpoint holds the plug-ins' `state` beside Phase 1's, under the `kind` and `phase_name`
of the last plug-in that names one (Phase 2's motion strategy: "sync4d.phase2").
"""

from __future__ import annotations

from enum import StrEnum
from typing import TYPE_CHECKING

from torch import Tensor

if TYPE_CHECKING:
    from sync4d.data.scene import Frame

__all__ = ["CheckpointKind", "TrainerPlugin"]


class CheckpointKind(StrEnum):
    """What trained a checkpoint, as its header's ``kind`` records it (a `str`: the header
    holds the value itself)."""

    PHASE1 = "sync4d.phase1"
    PHASE2 = "sync4d.phase2"


class TrainerPlugin:
    """A plug-in of `Phase1Trainer`: every hook does nothing unless overridden."""

    #: The checkpoint kind a trainer with this plug-in writes (None: Phase 1's).
    kind: CheckpointKind | None = None
    #: The name the watchdog gives the failures of a trainer with this plug-in (None: Phase 1).
    phase_name: str | None = None

    def update_learning_rates(self) -> None:
        """Set the plug-in's own optimizers' rates for this iteration."""

    def loss(self, frame: Frame, means: Tensor) -> tuple[Tensor | None, dict[str, float]]:
        """Loss terms added to the photometric loss for `frame`, given the deformed means
        [N, 3] the render used, and scalars to report."""
        return None, {}

    def watched(self) -> tuple[dict[str, Tensor], dict[str, str]]:
        """Parameters the watchdog checks (name -> tensor) and the unit of their rows."""
        return {}, {}

    def after_step(self) -> None:
        """The plug-in's own update, after Phase 1's optimizer and densification steps."""

    def on_gaussians_changed(self) -> None:
        """Densification changed the number of Gaussians."""

    def state(self) -> tuple[dict[str, Tensor], dict]:
        """Tensors and JSON-ready settings added to the trainer's checkpoint."""
        return {}, {}

    def restore(self, tensors: dict[str, Tensor], meta: dict) -> None:
        """Load what `state` saved (the trainer's own state is restored first)."""
