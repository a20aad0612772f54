"""Runs: the run folder alone. `names` holds every file name in it (Phase 3's included),
`folder` gives `load_run`, the read-only view later stages use, and `checkpoint` the
checkpoint format. Above the phases 1 and 2 (a run holds their models) and below Phase 3 and
the pipeline, which fill it. Names are imported on first use, so `sync4d.runs.names` loads
without torch (a query needs none).
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each.
_EXPORTS = {
    **dict.fromkeys(
        ("CheckpointError", "CheckpointKind", "camera_records", "checkpoint_kind", "load_model",
         "read_checkpoint", "save_checkpoint", "write_checkpoint"), "checkpoint"),
    **dict.fromkeys(
        ("CHECKPOINT_NAME", "EVAL_FILE", "EVENTS_FILE", "FIELD_DIR", "METRICS_FILE",
         "PHASE1_CHECKPOINT_NAME",
         "PHASE2_FILE", "RENDERS_DIR", "RUN_FILE", "TRAJECTORY_PLOT"), "names"),
    **dict.fromkeys(("Run", "RunError", "load_run"), "folder"),
    **dict.fromkeys(("RenderFailed", "render_rgb"), "render"),
}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
