"""The run folder: every file a run writes (docs/run-folder.md) and `load_run`, the read-only
view of a finished or interrupted run that later stages (evaluation, rendering, Phase 3,
export) use without building a trainer or re-running Phase 2's motion fit.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from sync4d.data import Scene, load_scene
from sync4d.errors import Sync4dError
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.plugin import CheckpointKind
from sync4d.phase2.motion import MotionConfig, ObjectMotion, make_motion
from sync4d.runs.checkpoint import CheckpointError, read_checkpoint, state_errors
from sync4d.runs.names import (
    CHECKPOINT_NAME,
    EVAL_FILE,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    RENDERS_DIR,
    RUN_FILE,
    TRAJECTORY_PLOT,
)

__all__ = [
    "CHECKPOINT_NAME",
    "EVAL_FILE",
    "METRICS_FILE",
    "PHASE1_CHECKPOINT_NAME",
    "PHASE2_FILE",
    "RENDERS_DIR",
    "RUN_FILE",
    "Run",
    "RunError",
    "TRAJECTORY_PLOT",
    "load_run",
]



class RunError(Sync4dError, ValueError):
    """A run directory that cannot be used; the message names the file."""


@dataclass
class Run:
    """A run as its folder holds it, read-only. `model`: the latest checkpoint's Gaussians and
    D_theta (no gradients); for a Phase 2 run also `motion` (M_phi), `labels` [N] (object of
    each Gaussian, 0 = background), `names` (label -> object name), `times` [T] (M_phi's
    stored frames) and `export` (the motion export: rotations [K, T, 3, 3], translations,
    centroids and velocities [K, T, 3], times [T], labels [N]); None for a Phase 1 run."""

    path: Path
    checkpoint: Path
    kind: CheckpointKind
    model: DeformableGaussians
    meta: dict
    background: list[float]
    cameras: list[dict]
    settings: dict
    motion: ObjectMotion | None = None
    labels: np.ndarray | None = None
    names: dict[int, str] = field(default_factory=dict)
    times: np.ndarray | None = None
    export: dict[str, np.ndarray] | None = None

    @property
    def iteration(self) -> int:
        """The iteration the checkpoint was saved at (of its phase)."""
        return int(self.meta.get("iteration", 0))

    def scene(self, data: str | Path | None = None) -> Scene | None:
        """The run's dataset at its resolution and split (`data` if given, else the folder the
        run recorded); None when that folder is gone and `data` was not given."""
        root = data or self.settings.get("data")
        if root is None or (data is None and not Path(root).exists()):
            return None
        return load_scene(
            root,
            float(self.settings.get("resolution_scale", 1.0)),
            self.settings.get("test_split", "test"),
        )


def _motion(meta: dict, tensors: dict[str, torch.Tensor]) -> ObjectMotion:
    """M_phi rebuilt from a Phase 2 checkpoint's tensors and header."""
    info = meta["phase2"]
    stored = info.get("motion_config")
    if stored is None:  # checkpoints before the motion config was stored: the run's config
        stored = meta.get("run", {}).get("config", {}).get("phase2", {}).get("motion", {})
    names = {f.name for f in dataclasses.fields(MotionConfig)}
    mc = MotionConfig(**{k: v for k, v in stored.items() if k in names})
    mc = dataclasses.replace(mc, kind=info["motion_kind"])
    motion = make_motion(mc, int(info["num_objects"]), np.asarray(info["times"]))
    motion.load_state(tensors)
    return motion.requires_grad_(False)


def load_run(run_dir: str | Path) -> Run:
    """The run in `run_dir` (a run folder, or a checkpoint file), read-only."""
    run_dir = Path(run_dir)
    if run_dir.is_file():
        ckpt, run_dir = run_dir, run_dir.parent
    else:
        if not run_dir.is_dir():
            raise RunError(f"{run_dir}: no such run folder or checkpoint (it is missing)")
        ckpt = run_dir / CHECKPOINT_NAME
    tensors, meta = read_checkpoint(ckpt)
    with state_errors(ckpt):
        model = DeformableGaussians.from_state(tensors, meta).requires_grad_(False)
    settings = meta.get("run", {})
    run = Run(
        path=run_dir, checkpoint=ckpt, model=model, meta=meta,
        kind=CheckpointKind(meta.get("kind", CheckpointKind.PHASE1)),
        background=list(meta.get("background", [1.0, 1.0, 1.0])),
        cameras=list(settings.get("cameras", [])), settings=settings,
    )  # fmt: skip
    if run.kind != CheckpointKind.PHASE2:
        return run
    with state_errors(ckpt):
        info = meta["phase2"]
        run.motion = _motion(meta, tensors)
        run.labels = tensors["phase2.labels"].numpy().astype(np.int64)
        run.names = {int(k): v for k, v in info["names"].items()}
        run.times = np.asarray(info["times"], dtype=np.float64)
        run.export = {k.removeprefix("export."): v.numpy() for k, v in tensors.items()
                      if k.startswith("export.")}  # fmt: skip
    if len(run.labels) != model.num_gaussians:
        raise CheckpointError(ckpt, "'phase2.labels' does not match the Gaussian count")
    return run
