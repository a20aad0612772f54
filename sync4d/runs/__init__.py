"""Runs: the run folder alone. `names` holds every file name in it (Phase 3's included),
`folder` gives `load_run`, the read-only view later stages use, and `checkpoint` the
checkpoint format. Above the phases 1 and 2 (a run holds their models) and below Phase 3 and
the pipeline, which fill it. Names are imported on first use, so `sync4d.runs.names` loads
without torch (a query needs none).
"""

from importlib import import_module

#: Public names and the module that defines each.
_EXPORTS = {
    **dict.fromkeys(
        ("CheckpointError", "camera_records", "checkpoint_kind", "load_model",
         "read_checkpoint", "save_checkpoint", "write_checkpoint"), "checkpoint"),
    **dict.fromkeys(
        ("CHECKPOINT_NAME", "EVAL_FILE", "FIELD_DIR", "METRICS_FILE", "PHASE1_CHECKPOINT_NAME",
         "PHASE2_FILE", "RENDERS_DIR", "RUN_FILE", "TRAJECTORY_PLOT"), "names"),
    **dict.fromkeys(("Run", "RunError", "load_run"), "folder"),
}  # fmt: skip

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):  # noqa: ANN202 - PEP 562 module attribute
    if name not in _EXPORTS:
        raise AttributeError(f"module 'sync4d.runs' has no attribute {name!r}")
    return getattr(import_module(f"sync4d.runs.{_EXPORTS[name]}"), name)
