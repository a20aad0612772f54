"""The pipeline: fits Phases 1, 2 and 3 into a run folder and owns the resume policy.

Above the phases, the config and the run folder; below the command line, which only parses,
calls these and prints. `stages` holds each phase as a stage value (Phase 1, Phase 2 from
its model, Phase 3's language field), `fit` loops over the selected stages (checkpoints,
resume, Ctrl-C), `phase3` builds the language field of a run, `record` holds the run record (dataset
fingerprint, stored config) and the checks that decide whether a run may continue,
`evaluate` the image metrics of a run, `stop` the signals that end a loop between iterations,
`request` what `sync4d fit` asks of a run folder and the resume policy that answers it. A
dataset travels with its scene (`FitData`).
"""

from sync4d.pipeline.evaluate import evaluate_frames, evaluate_run, summarize
from sync4d.pipeline.fit import (
    FitData,
    FitInterrupted,
    TrainingDiverged,
    resolve_data,
    restart_phase2,
    resume_trainer,
    run_fit,
    set_threads,
)
from sync4d.pipeline.request import FitRequest, fit_request

__all__ = [
    "FitData",
    "FitInterrupted",
    "FitRequest",
    "TrainingDiverged",
    "evaluate_frames",
    "evaluate_run",
    "fit_request",
    "resolve_data",
    "restart_phase2",
    "resume_trainer",
    "run_fit",
    "set_threads",
    "summarize",
]
