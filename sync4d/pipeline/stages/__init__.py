"""The phases of a fit as stage values: `run_stages` (`sync4d.pipeline.fit`) loops over the
selected ones and never asks which phase it is running.

A `Stage` says what its phase needs from the loop: its number in ``--phases``, the name of its
progress task and of its events, how to `start` and what it skipped (`counts`). One that
trains is a `TrainingStage`: the checkpoint `kind` its training writes, its `iterations`,
whether it starts a new model (`fresh`) or one on the previous stage's, how to `resume` its
checkpoint and what it adds at the end (`finish`). A stage that trains nothing (Phase 3's
language field) builds its result after the fit's summary.
Each phase's module holds its one value (`PHASE1`, `PHASE2`, `PHASE3`); `STAGES` lists them in
the order they run, and a new stage joins by being added there.
"""

from sync4d.pipeline.stages.base import FitData, FitState, Stage, TrainingStage
from sync4d.pipeline.stages.phase1 import PHASE1, length_advice, phase1_skips
from sync4d.pipeline.stages.phase2 import PHASE2, motion_strategy, restart_phase2
from sync4d.pipeline.stages.phase3 import PHASE3
from sync4d.runs import CheckpointKind

#: Every stage, in the order a fit runs them.
STAGES: tuple[Stage, ...] = (PHASE1, PHASE2, PHASE3)

__all__ = ["PHASE1", "PHASE2", "PHASE3", "STAGES", "FitData", "FitState", "Stage", "TrainingStage",
           "length_advice", "motion_strategy", "phase1_skips", "restart_phase2",
           "stage_of_kind", "stages_for"]  # fmt: skip


def stages_for(phases: tuple[int, ...]) -> list[Stage]:
    """The stages of `phases` (``--phases``, parsed), in the order they run."""
    return [s for s in STAGES if s.phase in phases]


def stage_of_kind(kind: CheckpointKind) -> TrainingStage:
    """The stage whose training writes checkpoints of `kind`."""
    return next(s for s in STAGES if isinstance(s, TrainingStage) and s.kind == kind)
