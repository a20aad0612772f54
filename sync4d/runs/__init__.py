"""Runs: the run folder (`folder`: every file name and `load_run`, the read-only view later
stages use), the checkpoint format (`checkpoint`), the fit loop (`fit`) and evaluation
(`evaluate`). Above the phases and below the command line: `commands` parse arguments, call
these and print.
"""

from sync4d.runs.checkpoint import (
    CheckpointError,
    camera_records,
    checkpoint_kind,
    load_model,
    read_checkpoint,
    save_checkpoint,
    write_checkpoint,
)
from sync4d.runs.evaluate import evaluate_frames, evaluate_run, summarize
from sync4d.runs.fit import (
    FitInterrupted,
    resolve_data,
    restart_phase2,
    resume_trainer,
    run_fit,
    set_threads,
    with_initial_points,
)
from sync4d.runs.folder import (
    CHECKPOINT_NAME,
    EVAL_FILE,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    RENDERS_DIR,
    RUN_FILE,
    TRAJECTORY_PLOT,
    Run,
    RunError,
    load_run,
)

__all__ = [
    "CHECKPOINT_NAME",
    "CheckpointError",
    "EVAL_FILE",
    "FitInterrupted",
    "METRICS_FILE",
    "PHASE1_CHECKPOINT_NAME",
    "PHASE2_FILE",
    "RENDERS_DIR",
    "RUN_FILE",
    "Run",
    "RunError",
    "TRAJECTORY_PLOT",
    "camera_records",
    "checkpoint_kind",
    "evaluate_frames",
    "evaluate_run",
    "load_model",
    "load_run",
    "read_checkpoint",
    "resolve_data",
    "restart_phase2",
    "resume_trainer",
    "run_fit",
    "save_checkpoint",
    "set_threads",
    "summarize",
    "with_initial_points",
    "write_checkpoint",
]
