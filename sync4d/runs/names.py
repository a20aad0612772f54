"""Every file name of a run folder (docs/run-folder.md), Phase 3's included, in one place.

Torch-free on purpose: Phase 3's queries read and write the run folder without loading torch.
`sync4d.runs.folder` re-exports the names that `load_run` reads.
"""

from __future__ import annotations

from sync4d.files import LOCK_FILE

__all__ = [
    "BACKGROUNDS",
    "CHECKPOINT_NAME",
    "EMBEDDED_QUERIES_FILE",
    "EVAL_FILE",
    "EVENTS_FILE",
    "FIELD_DIR",
    "FIELD_FILE",
    "FIELD_META",
    "LOCK_FILE",
    "METRICS_FILE",
    "PHASE1_CHECKPOINT_NAME",
    "PHASE2_FILE",
    "RENDERS_DIR",
    "RUN_FILE",
    "TEXT_CACHE",
    "TRAJECTORY_PLOT",
    "background_tag",
    "eval_file",
    "query_eval_files",
    "query_eval_summary",
    "query_plot",
    "render_frame",
    "render_sweep",
]

#: The latest checkpoint (Phase 1's, then Phase 2's once it runs).
CHECKPOINT_NAME = "checkpoint.safetensors"
#: Copy of the Phase 1 checkpoint kept when Phase 2 starts (Phase 2 can restart from it).
PHASE1_CHECKPOINT_NAME = "phase1.safetensors"
#: Phase 2 diagnostics (Appendix C) of the final model.
PHASE2_FILE = "phase2.json"
#: Phase 2's per-object centroid curves (x, y, z against time).
TRAJECTORY_PLOT = "phase2-trajectories.png"
#: The run's settings: dataset, resolution, split, the whole config, threads.
RUN_FILE = "run.json"
#: One JSON record per logged iteration, periodic evaluation and the final summary.
METRICS_FILE = "metrics.jsonl"
#: What the fit reported, as typed events, one JSON line each (`sync4d.events.EventLog`):
#: what another process (the viewer, a sweep) follows.
EVENTS_FILE = "events.jsonl"
#: The last evaluation (`eval`, or the end of `fit`): per-frame and mean metrics, and what each
#: metric is (docs/metrics.md).
EVAL_FILE = "eval.json"
#: Folder of the evaluation's side-by-side renders, one subfolder per split.
RENDERS_DIR = "renders"

#: Phase 3's folder: the language field and everything queries write.
FIELD_DIR = "phase3"
#: The field's arrays (safetensors) ...
FIELD_FILE = "field.safetensors"
#: ... and its JSON header (encoder, names, times, the checkpoint it was built from).
FIELD_META = "field.json"
#: Text embeddings of past queries, per encoder.
TEXT_CACHE = "texts.json"
#: The embedded synthetic scene's queries, written for `eval --queries` of a synthetic run.
EMBEDDED_QUERIES_FILE = "queries-embedded.json"


#: The background colours known by name (`eval --background`, `background_tag`).
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def background_tag(rgb: tuple[float, ...] | list[float]) -> str:
    """The file tag of an evaluation on background `rgb`: ``white``, ``black`` or
    ``bg-R-G-B`` (``eval-black.json``, ``renders/black/``)."""
    for name, value in BACKGROUNDS.items():
        if tuple(rgb) == value:
            return name
    return "bg-" + "-".join(f"{v:g}" for v in rgb)


def eval_file(tag: str | None = None) -> str:
    """The evaluation's file: `EVAL_FILE` for the run's test split, ``eval-<tag>.json`` for
    another split or dataset (``train``, ``<dataset>-<split>``)."""
    return EVAL_FILE if tag is None else f"eval-{tag}.json"


def render_frame(stem: str, time: float) -> str:
    """PNG name (inside `RENDERS_DIR` or `render --out`) of camera `stem` at `time`."""
    return f"{stem}_t{time:.3f}.png"


def render_sweep(stem: str) -> str:
    """GIF name of camera `stem`'s time sweep."""
    return f"{stem}_sweep.gif"


def query_plot(slug: str) -> str:
    """File name (inside `FIELD_DIR`) of the activation plot of the query named `slug`."""
    return f"query-{slug}.png"


def query_eval_files(name: str, scorer: str) -> tuple[str, str]:
    """File names (inside `FIELD_DIR`) of the per-query rows of annotation set `name` under
    `scorer`: CSV and JSON."""
    return f"eval-{name}-{scorer}.csv", f"eval-{name}-{scorer}.json"


def query_eval_summary(name: str) -> str:
    """File name (inside `FIELD_DIR`) of annotation set `name`'s summary over scorers."""
    return f"eval-{name}.json"
