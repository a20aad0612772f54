"""What every stage is (`Stage`) and what the stages of one fit share (`FitState`): the
dataset, the config, the run folder, the threads, the trainer the last stage left and the
training time so far. `sync4d.pipeline.fit.run_stages` fills it and loops over the stages.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from sync4d.config import RunConfig
from sync4d.data import Scene, load_scene
from sync4d.runs import CHECKPOINT_NAME, CheckpointKind

if TYPE_CHECKING:
    from torch import Tensor

    from sync4d.phase1.trainer import Phase1Trainer
    from sync4d.pipeline.phase3 import Phase3Build

__all__ = ["FitData", "FitState", "Stage", "TrainingStage"]


@dataclass(frozen=True)
class FitData:
    """A run's dataset: its folder `path`, the `scene` loaded from it, and whether it is the
    embedded synthetic scene (`embedded`, kept in the run record)."""

    path: Path
    scene: Scene
    embedded: bool = False

    @classmethod
    def load(cls, path: str | Path, cfg: RunConfig, embedded: bool = False) -> FitData:
        """The dataset in `path`, loaded at `cfg`'s resolution scale and test split."""
        path = Path(path)
        return cls(path, load_scene(path, cfg.resolution_scale, cfg.test_split), embedded)


@dataclass
class FitState:
    """What the stages of one fit share. `scene` is the dataset's (with Phase 1's initial
    points once it started); `trainer` the last stage's (None before any); `data_path` the
    dataset folder a stage that reads images again uses (None: the run's recorded one)."""

    cfg: RunConfig
    run_dir: Path
    n_threads: int
    threads: int | None = None
    scene: Scene | None = None
    data_path: Path | None = None
    trainer: Phase1Trainer | None = None
    train_seconds: float = 0.0
    built: Phase3Build | None = None
    extra: dict = field(default_factory=dict)

    @property
    def checkpoint(self) -> Path:
        """The run's checkpoint file."""
        return self.run_dir / CHECKPOINT_NAME


class Stage(ABC):
    """One phase of a fit, as the loop sees it (`sync4d.pipeline.stages` says how it is used);
    one that trains is a `TrainingStage`."""

    #: Its number in ``--phases``.
    phase: ClassVar[int]
    #: The name of its events (`Skipped`, `PhaseDone`): "phase1", "phase2", "phase3".
    name: ClassVar[str]
    #: The name of its progress task (`Started`, `Advanced`; Phase 1's is "fit").
    task: ClassVar[str]
    #: The checkpoint kind its training writes; None for a stage that trains nothing.
    kind: ClassVar[CheckpointKind | None] = None

    @abstractmethod
    def start(self, fit: FitState) -> None:
        """Begin the stage: make `fit.trainer` its trainer (a stage that trains), or build its
        result (one that does not)."""

    def counts(self, fit: FitState) -> dict:
        """What it skipped (the `Skipped` event's counts)."""
        return {}


class TrainingStage(Stage):
    """A stage that trains: its checkpoints are of its `kind`, and a run holding one resumes
    through it."""

    kind: ClassVar[CheckpointKind]
    #: Whether `start` builds a new model (the run's training time starts from zero) rather
    #: than continuing the run's checkpoint.
    fresh: ClassVar[bool] = False
    #: The key under which the fit's summary keeps `counts` (None: it does not).
    summary_counts: ClassVar[str | None] = None

    @abstractmethod
    def iterations(self, cfg: RunConfig) -> int:
        """How many iterations its training loop runs."""

    def owns(self, trainer: Phase1Trainer | None) -> bool:
        """Whether `trainer` is this stage's (its checkpoint kind is this stage's)."""
        return trainer is not None and trainer.kind == self.kind

    @abstractmethod
    def resume(self, tensors: dict[str, Tensor], meta: dict, scene: Scene, *,
               config=None, phase2=None, total_iterations: int | None = None,
               threads: int | None = None, near: float | None = None) -> Phase1Trainer:  # fmt: skip
        """The trainer a checkpoint of this stage's kind describes."""

    def before_loop(self, fit: FitState) -> None:
        """Called before its training loop, started or resumed (a note on what it will do)."""
        return None

    def finish(self, fit: FitState, summary: dict) -> None:
        """After the final evaluation, when the fit's trainer is this stage's: its own results
        (files, events, `summary` entries)."""
        return None
