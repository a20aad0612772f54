"""The pipeline: fits Phases 1, 2 and 3 into a run folder and owns the resume policy.

Above the phases, the config and the run folder; below the command line, which only parses,
calls these and prints. `fit` runs Phase 1 then Phase 2 (checkpoints, resume, Ctrl-C),
`phase3` builds the language field of a run, `record` holds the run record (dataset
fingerprint, stored config) and the checks that decide whether a run may continue,
`evaluate` the image metrics of a run, `stop` the signals that end a loop between iterations.
"""

from sync4d.pipeline.evaluate import evaluate_frames, evaluate_run, summarize
from sync4d.pipeline.fit import (
    FitInterrupted,
    TrainingDiverged,
    resolve_data,
    restart_phase2,
    resume_trainer,
    run_fit,
    set_threads,
    with_initial_points,
)

__all__ = [
    "FitInterrupted",
    "TrainingDiverged",
    "evaluate_frames",
    "evaluate_run",
    "resolve_data",
    "restart_phase2",
    "resume_trainer",
    "run_fit",
    "set_threads",
    "summarize",
    "with_initial_points",
]
