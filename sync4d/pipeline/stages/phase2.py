"""Phase 2 as a stage: Phase 1's checkpoint kept as ``phase1.safetensors``, the object
assignment, M_phi's start and the photometric refinement on Phase 1's model, then the trainer
with the motion strategy plugged in; at the end its diagnostics (``phase2.json``) and the
trajectory plot. `restart_phase2` puts Phase 1's checkpoint back for ``--phases 2``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from sync4d.config import ConfigError, RunConfig
from sync4d.events import (
    Assigned,
    Diagnostics,
    MotionDiagnosed,
    NothingMoves,
    ObjectCount,
    Phase2Starting,
    Wrote,
    emit,
)
from sync4d.files import write_atomic, write_text_atomic
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.phase2.diagnostics import diagnostics
from sync4d.phase2.strategy import MotionStrategy
from sync4d.phase2.trainer import phase2_from_state, phase2_trainer
from sync4d.pipeline.stages.base import FitState, TrainingStage
from sync4d.report import plot_object_trajectories
from sync4d.runs import (
    CHECKPOINT_NAME,
    FIELD_DIR,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    TRAJECTORY_PLOT,
    CheckpointKind,
    checkpoint_kind,
    load_model,
)

__all__ = ["PHASE2", "Phase2Stage", "motion_strategy", "restart_phase2"]


def motion_strategy(trainer: Phase1Trainer | None) -> MotionStrategy | None:
    """The Phase 2 motion strategy plugged into `trainer` (None: a Phase 1 trainer)."""
    plugins = [] if trainer is None else trainer.plugins
    return next((p for p in plugins if isinstance(p, MotionStrategy)), None)


class Phase2Stage(TrainingStage):
    """Phase 2: the motion decomposition on Phase 1's model, for `phase2.iterations`."""

    phase = 2
    name = "phase2"
    task = "phase2"
    kind = CheckpointKind.PHASE2
    summary_counts = "phase2_skipped"

    def iterations(self, cfg: RunConfig) -> int:
        return cfg.phase2.iterations

    def start(self, fit: FitState) -> None:
        """Keep the Phase 1 checkpoint as ``phase1.safetensors`` and build Phase 2's trainer
        from its model (the assignment, M_phi's start and the photometric refinement run
        here)."""
        cfg, run_dir = fit.cfg, fit.run_dir
        ckpt = run_dir / CHECKPOINT_NAME
        kept = run_dir / PHASE1_CHECKPOINT_NAME
        write_atomic(kept, lambda tmp: shutil.copyfile(ckpt, tmp))
        trainer = fit.trainer
        model = trainer.model if trainer is not None else load_model(ckpt, cfg.phase1.near)[0]
        emit(Phase2Starting(cfg.phase2.iterations, str(kept)))
        try:
            p2 = phase2_trainer(model, fit.scene, cfg.phase1, cfg.phase2, cfg.phase2.iterations,
                                fit.n_threads)  # fmt: skip
        except ValueError as e:  # bad assignment input
            raise ConfigError(str(e)) from None
        names = p2.assignment.names
        counts = {str(names.get(k, k)): int(n) for k, n in p2.assignment.counts().items()}
        emit(Assigned(p2.assignment.source, p2.assignment.num_objects,
                      tuple(ObjectCount(name, n) for name, n in counts.items())))
        fit.trainer = p2.trainer

    def resume(self, tensors, meta, scene, *, config=None, phase2=None,
               total_iterations=None, threads=None, near=None) -> Phase1Trainer:  # fmt: skip
        return phase2_from_state(tensors, meta, scene, phase2=phase2, config=config,
                                 total_iterations=total_iterations, threads=threads,
                                 near=near).trainer  # fmt: skip

    def before_loop(self, fit: FitState) -> None:
        p2 = motion_strategy(fit.trainer)
        if p2.skip_loop(fit.cfg.phase2.iterations):
            emit(NothingMoves(p2.assignment.num_objects))

    def counts(self, fit: FitState) -> dict:
        return motion_strategy(fit.trainer).skip_counts()

    def finish(self, fit: FitState, summary: dict) -> None:
        """Phase 2's diagnostics (``phase2.json``, with the object trajectories) and the
        trajectory plot."""
        p2 = motion_strategy(fit.trainer)
        run_dir = fit.run_dir
        diag = diagnostics(p2)
        export = p2.motion_export()
        cent = export["centroids"]
        diag["trajectories"] = {
            "times": export["times"].tolist(),
            "centroids": {str(k): cent[k].tolist() for k in range(len(cent))},
        }
        write_text_atomic(run_dir / PHASE2_FILE, json.dumps(diag, indent=2) + "\n")
        plot = plot_object_trajectories(
            export, p2.assignment.names, run_dir / TRAJECTORY_PLOT,
            f"{fit.scene.name}: object centroids after Phase 2 ({diag['assignment']} assignment)",
        )  # fmt: skip
        summary["phase2"] = diag
        emit(MotionDiagnosed(Diagnostics.of(diag)))
        emit(Wrote("fit", (str(run_dir / PHASE2_FILE), str(plot))))


def restart_phase2(run_dir: Path) -> None:
    """Put the run's Phase 1 checkpoint back in place so Phase 2 starts over from it; the
    language field of the old Phase 2 goes (it describes a model that will not exist)."""
    ckpt = run_dir / CHECKPOINT_NAME
    kept = run_dir / PHASE1_CHECKPOINT_NAME
    if kept.exists():
        write_atomic(ckpt, lambda tmp: shutil.copyfile(kept, tmp))
    elif checkpoint_kind(ckpt) != CheckpointKind.PHASE1:
        raise ConfigError(
            f"{run_dir}: --phases 2 needs a Phase 1 checkpoint ({CHECKPOINT_NAME} or "
            f"{PHASE1_CHECKPOINT_NAME}); fit Phase 1 first"
        )
    shutil.rmtree(run_dir / FIELD_DIR, ignore_errors=True)


#: The Phase 2 stage.
PHASE2 = Phase2Stage()
