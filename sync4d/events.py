"""What happens in a long computation, as events, and who hears them.

Design. The library rooms (pipeline, phases) neither print nor build progress bars: they
`emit` small frozen events and front ends `subscribe` to them, the way brush's training
process sends messages that its command line and viewer each render.

- `Note`: a script's own line for people, with the stream it belongs on (``"err"``: status,
  warnings; ``"out"``: results) and whether it is a `detail` that a terse front end leaves
  out. The library emits none: its events carry numbers.
- `Started` / `Advanced` / `Finished`: a long loop (``task``: "fit", "phase2", "eval test",
  "refine M_phi", "phase3 observe"), its length, how far it got and its statistics, as
  numbers (`Stats`: ``Stats(loss=0.0123, psnr=24.51, gaussians=18000)``).
- `Evaluated`: a periodic evaluation during training, its metrics as numbers.
- `FitStarted`, `Resumed`, `Assigned`, `Skipped`: what a fit trains on, where it resumed,
  Phase 2's object assignment, what each phase skipped (counts).
- `PhaseDone`: a stage ended ("phase1", "phase2", "phase3", "eval", and "fit": the whole
  run, with its test metrics) with its summary.
- What a fit meets on its way, each with its numbers: `DatasetChosen`, `GeneratingScene`,
  `SettingChanged` (a resumed run's free setting), `Triangulating` / `InitialPoints`,
  `ScaleAdvice`, `Phase2Starting`, `NothingMoves`, `MotionDiagnosed` (Phase 2's table),
  `Phase3Started` / `FieldBuilt`, `FramesEvaluated` (the evaluation's table),
  `MetricUnavailable`, `Wrote` (result files) and `Interrupted` (with the command that
  continues the run).

Payloads are typed: an event's numbers are fields, never a dict of string keys. What an event
carries beyond a few scalars is a frozen `Payload` dataclass: a loop's `Stats`; a stage's
summary (`LoopSummary`, `EvalSummary`, `FieldSummary`, `FitSummary`); what a phase skipped
(`Phase1Skips`, `Phase2Skips`, `Phase3Skips`, or `NoCounts`); Phase 2's `Diagnostics`; an
evaluation's `FrameScore` rows and `Means`. Names chosen at run time (objects, backgrounds,
settings) are tuples of two-field payloads (`ObjectCount`, `BackgroundScore`, `Override`),
in their order. A renderer reads attributes, so a typo is an AttributeError at once, not a
missing key in a rare branch.

`to_json` is each event's JSON form, the dict `EventLog` writes: its fields in order, a
payload as its fields (a field declared `_optional()` left out when None: a switch that was
off), a tuple of `_pairs()` as an object ``{name: value}``; `EvalSummary` and `FieldSummary`
flatten their parts into one object. That is the form the events had when they carried
dicts, key for key and in the same order, so ``events.jsonl`` of a run is unchanged by the
typing (issue 63: bit-identical) and its readers (`read_events`: the viewer, a sweep) read
plain dicts as before.

The library emits numbers; the words are the renderer's. The command line subscribes
`sync4d.terminal.TerminalRenderer`, which writes each typed event as its lines and draws the
bars. `Note` is for scripts' own text: the library emits none. `EventLog` writes the same
events as JSON lines into the run folder (``events.jsonl``, `sync4d.runs.EVENTS_FILE`), which
another process follows with `read_events`: the viewer's status line of a run still training,
a sweep's table.

Without a subscriber an event is dropped: library use (tests, scripts, ``bench phase3``) is
silent unless someone listens, so there is no `quiet` or `progress` switch to thread through.
Delivery is synchronous, in the emitting thread and in subscription order, so a renderer's
lines interleave with a front end's own prints exactly as prints did. The subscribers are one
process-wide list, not a context variable, so a viewer thread hears a training thread;
subscribing and unsubscribing take a lock, `emit` reads a snapshot. A subscriber's exception
reaches the emitter. This module is the lowest floor: every room may emit.
"""

from __future__ import annotations

import dataclasses
import json
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

__all__ = [
    "Advanced",
    "Assigned",
    "BackgroundScore",
    "DatasetChosen",
    "Diagnostics",
    "EvalSummary",
    "Evaluated",
    "Event",
    "EventLog",
    "FieldBuilt",
    "FieldSummary",
    "FieldTimings",
    "Finished",
    "FitStarted",
    "FitSummary",
    "FrameScore",
    "FramesEvaluated",
    "GeneratingScene",
    "InitialPoints",
    "Interrupted",
    "LoopSummary",
    "Means",
    "MetricUnavailable",
    "MotionDiagnosed",
    "NoCounts",
    "Note",
    "NothingMoves",
    "ObjectCount",
    "ObjectDiagnostics",
    "Override",
    "Payload",
    "Phase1Skips",
    "Phase2Brief",
    "Phase2Skips",
    "Phase2Starting",
    "Phase3Skips",
    "Phase3Started",
    "PhaseDone",
    "Resumed",
    "ScaleAdvice",
    "Scores",
    "SettingChanged",
    "Skipped",
    "Started",
    "Stats",
    "Subscription",
    "Triangulating",
    "Wrote",
    "emit",
    "note",
    "read_events",
    "subscribe",
    "to_json",
]


# -- payloads: what an event carries beyond its scalars, typed --------------------------------

#: Field metadata: the field is left out of the JSON when it is None (a switch that was off).
_OMIT = "sync4d.events.omit_none"
#: Field metadata: a tuple of two-field payloads, written as the JSON object {first: second}.
_PAIRS = "sync4d.events.pairs"


def _optional() -> Any:
    """A payload field that may be absent: None, and then left out of the JSON."""
    return field(default=None, metadata={_OMIT: True})


def _pairs(optional: bool = False) -> Any:
    """A tuple of two-field payloads (a name and its value) that the JSON writes as an object
    ``{name: value}``, in order; `optional`: None, and then left out."""
    if optional:
        return field(default=None, metadata={_PAIRS: True, _OMIT: True})
    return field(default=(), metadata={_PAIRS: True})


def to_json(value: object) -> object:
    """`value` (an event, a payload, or what they hold) as the event log writes it: a payload
    as its `to_json()`, an event as a dict of its fields in order; tuples and lists as lists,
    dicts as dicts, anything else as it is."""
    if isinstance(value, Payload):
        return value.to_json()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _fields_json(value)
    if isinstance(value, tuple | list):
        return [to_json(v) for v in value]
    if isinstance(value, dict):
        return {k: to_json(v) for k, v in value.items()}
    return value


def _fields_json(obj: Any) -> dict[str, object]:
    """The fields of the dataclass `obj` in order, as JSON: `_optional` ones left out when
    None, `_pairs` as an object."""
    out: dict[str, object] = {}
    for f in dataclasses.fields(obj):
        item = getattr(obj, f.name)
        if item is None and f.metadata.get(_OMIT):
            continue
        if f.metadata.get(_PAIRS):
            pairs = (tuple(getattr(p, g.name) for g in dataclasses.fields(p)) for p in item)
            out[f.name] = {k: to_json(v) for k, v in pairs}
        else:
            out[f.name] = to_json(item)
    return out


class Payload:
    """A typed part of an event: a frozen dataclass of numbers (and names), never a dict."""

    def to_json(self) -> dict[str, object]:
        """The dict the event log writes for it: its fields in order (`_optional` ones left
        out when None, `_pairs` as an object)."""
        return _fields_json(self)


@dataclass(frozen=True)
class Stats(Payload):
    """A loop's statistics (`Advanced.stats`), each None where the loop has none: the training
    loop's moving averages of `loss`, `psnr` (dB) and `rho` (Phase 2's rigid share, when it
    reports one) and its Gaussian count; an evaluation's per-frame `psnr`; the refinement's
    `loss`."""

    loss: float | None = _optional()
    psnr: float | None = _optional()
    gaussians: int | None = _optional()
    rho: float | None = _optional()


@dataclass(frozen=True)
class LoopSummary(Payload):
    """The end of a phase's loop (`PhaseDone` "phase1", "phase2"): its last `iteration`, the
    training seconds so far, the Gaussian count."""

    iteration: int
    train_seconds: float
    gaussians: int


@dataclass(frozen=True)
class Means(Payload):
    """An evaluation's means over its `frames`: PSNR (dB), SSIM, the 3x3 box SSIM, LPIPS;
    None where a metric could not run on every frame (`sync4d.pipeline.evaluate.summarize`)."""

    psnr: float | None
    ssim: float | None
    ssim_box3: float | None
    lpips: float | None
    frames: int


@dataclass(frozen=True)
class FrameScore(Payload):
    """One evaluated frame (`FramesEvaluated.frames`): its index and name, its time, PSNR,
    SSIM (None: too small), the 3x3 box SSIM and LPIPS (None: could not run)."""

    index: int
    name: str
    time: float
    psnr: float
    ssim: float | None
    ssim_box3: float
    lpips: float | None = None


@dataclass(frozen=True)
class EvalSummary(Payload):
    """A split evaluated (`PhaseDone` "eval"): the `split`, the results `file` and the
    `mean`s; its JSON is one object (split, file, then the means' fields)."""

    split: str
    file: str
    mean: Means

    def to_json(self) -> dict[str, object]:
        return {"split": self.split, "file": self.file, **self.mean.to_json()}


@dataclass(frozen=True)
class Phase1Skips(Payload):
    """What Phase 1 skipped in this process (`sync4d.pipeline.stages.phase1.phase1_skips`),
    a group of fields for each switch that is on (None: off): `gaussians` the count now;
    control nodes carrying the motion (`nodes`, from iteration `nodes_from`, `nodes_added`,
    `nodes_removed`) or D_theta skipped on static Gaussians (`deform_rows` evaluated,
    `deform_rows_skipped`, their `share` skipped, `static` Gaussians now); the coarse
    iterations (`coarse_iterations` at `coarse_scale`, `pixels_saved`: a fraction); the
    transparent Gaussians `pruned` after densification (opacity under `prune_opacity`)."""

    gaussians: int
    nodes: int | None = _optional()
    nodes_from: int | None = _optional()
    nodes_added: int | None = _optional()
    nodes_removed: int | None = _optional()
    deform_rows: int | None = _optional()
    deform_rows_skipped: int | None = _optional()
    share: float | None = _optional()
    static: int | None = _optional()
    coarse_iterations: int | None = _optional()
    coarse_scale: float | None = _optional()
    pixels_saved: float | None = _optional()
    pruned: int | None = _optional()
    prune_opacity: float | None = _optional()


@dataclass(frozen=True)
class Phase2Skips(Payload):
    """What Phase 2 skipped in this process (`MotionStrategy.skip_counts`): `held` of its
    `objects` objects at a constant transform, M_phi object-row updates done and skipped,
    refinement visits done and skipped, and the loop iterations skipped (nothing moves)."""

    objects: int
    held: int
    motion_updates: int
    motion_updates_skipped: int
    refine_visits: int
    refine_visits_skipped: int
    loop_skipped: int


@dataclass(frozen=True)
class Phase3Skips(Payload):
    """What Phase 3 encoded and skipped (`sync4d.phase3.store.Field.counts`): of the
    `object_frames` (K T), those `observed`, `invisible` and `below_threshold`; the `crops`
    kept and the `extra_crops` encoded and discarded (skip_unobserved off); the images
    loaded; crops encoded in `encoder_calls` calls; the object-frames with `relational`
    features, those left at 0 (`relational_skipped`: no other object) and those computed at
    a frame with an unobserved object (`relational_unobserved`)."""

    object_frames: int
    observed: int
    invisible: int
    below_threshold: int
    crops: int
    extra_crops: int
    images_loaded: int
    crops_encoded: int
    encoder_calls: int
    relational: int
    relational_skipped: int
    relational_unobserved: int


@dataclass(frozen=True)
class NoCounts(Payload):
    """A phase that counted nothing it skipped (a language field built before the counters);
    ``{}`` in JSON."""


@dataclass(frozen=True)
class FieldTimings(Payload):
    """A language field's build seconds (observe, encode, the field maths, in all) and its
    `crops` (`sync4d.phase3.store.Field.timings`)."""

    observe_s: float
    encode_s: float
    field_s: float
    total_s: float
    crops: int


@dataclass(frozen=True)
class FieldSummary(Payload):
    """A language field built (`PhaseDone` "phase3"): `objects` x `frames`, its `timings` and
    `counts`; its JSON is one object (objects, frames, the timings' fields, the counts')."""

    objects: int
    frames: int
    timings: FieldTimings
    counts: Phase3Skips

    def to_json(self) -> dict[str, object]:
        return {"objects": self.objects, "frames": self.frames, **self.timings.to_json(),
                **self.counts.to_json()}  # fmt: skip


@dataclass(frozen=True)
class Scores(Payload):
    """Mean test PSNR (dB), SSIM and LPIPS on one background (None: could not run)."""

    psnr: float | None
    ssim: float | None
    lpips: float | None


@dataclass(frozen=True)
class BackgroundScore(Payload):
    """The `scores` on the background `name` ("black", say)."""

    name: str
    scores: Scores


@dataclass(frozen=True)
class Phase2Brief(Payload):
    """Phase 2 in a fit's summary: mean rigid share, shuffle ratio, its `objects` (labels)
    and the assignment's source."""

    rigid_share: float
    shuffle_ratio: float
    objects: int
    assignment: str


@dataclass(frozen=True)
class FitSummary(Payload):
    """A whole fit (`PhaseDone` "fit"): test PSNR, SSIM, LPIPS (None: could not run), the
    Gaussians, iterations, training seconds, the run folder; for RGBA test frames the
    `background` scored first (the run's) and the scores on the others (`backgrounds`);
    `phase2` when Phase 2 ran."""

    psnr: float | None
    ssim: float | None
    lpips: float | None
    gaussians: int | None
    iterations: int | None
    train_seconds: float | None
    run_dir: str
    background: str | None = _optional()
    backgrounds: tuple[BackgroundScore, ...] | None = _pairs(optional=True)
    phase2: Phase2Brief | None = _optional()


@dataclass(frozen=True)
class ObjectCount(Payload):
    """An object's `name` and its Gaussians."""

    name: str
    gaussians: int


@dataclass(frozen=True)
class Override(Payload):
    """A setting (``phase1.near``) and the value advised for it."""

    setting: str
    value: float


@dataclass(frozen=True)
class ObjectDiagnostics(Payload):
    """One object's row of Phase 2's diagnostics: its `label` and `name`, its Gaussians,
    whether it is static and whether it was held, its mean rigid share, residual mean and
    motion variance."""

    label: int
    name: str
    gaussians: int
    static: bool
    held: bool
    rigid_share: float
    residual_mean: float
    motion_variance: float


@dataclass(frozen=True)
class Diagnostics(Payload):
    """Phase 2's diagnostics (Appendix C; `sync4d.phase2.diagnostics.diagnostics` without
    the trajectories): per object, the mean rigid share, residual energy, modulated fraction,
    the shuffle test (its ratio, mean of `shuffle_ratios`), the assignment's source and K;
    for trajectory clusters of a scene with masks, their adjusted Rand index against mask
    voting and the mask objects."""

    objects: tuple[ObjectDiagnostics, ...]
    rigid_share: float
    residual_energy: float
    modulated_fraction: float
    shuffle_ratio: float
    shuffle_ratios: tuple[float, ...]
    assignment: str
    num_objects: int
    mask_agreement_ari: float | None = _optional()
    mask_objects: int | None = _optional()

    @classmethod
    def of(cls, diag: Mapping[str, Any]) -> Diagnostics:
        """The payload of the dict `diagnostics` returns (its trajectories left out)."""
        rest = {k: v for k, v in diag.items()
                if k not in ("objects", "shuffle_ratios", "trajectories")}  # fmt: skip
        return cls(objects=tuple(ObjectDiagnostics(**o) for o in diag["objects"]),
                   shuffle_ratios=tuple(diag["shuffle_ratios"]), **rest)  # fmt: skip


@dataclass(frozen=True)
class Note:
    """A line for people: `text` (may hold several lines) on `stream` ("err" or "out");
    `detail`: a table or a "wrote ..." line that a terse front end leaves out."""

    text: str
    stream: Literal["err", "out"] = "err"
    detail: bool = False


@dataclass(frozen=True)
class Started:
    """A long loop `task` of `total` steps begins, `start` of them already done (a resumed
    run); `log_every`: how often a line-per-update log (not a terminal) shows an update."""

    task: str
    total: int
    start: int = 0
    log_every: int = 100


@dataclass(frozen=True)
class Advanced:
    """`done` steps of `task` are done (counted from 0, not from `Started.start`); `stats`
    are the loop's statistics (`Stats`: a training loop's moving averages of loss and PSNR
    and its Gaussian count; none for a loop without them)."""

    task: str
    done: int
    stats: Stats = field(default_factory=Stats)


@dataclass(frozen=True)
class Finished:
    """The loop `task` ended (finished, stopped by a signal, or left by an exception)."""

    task: str


@dataclass(frozen=True)
class PhaseDone:
    """The stage `phase` ended ("phase1", "phase2": its loop ran to the end, `LoopSummary`;
    "phase3": a language field was built, `FieldSummary`; "eval": a split was evaluated,
    `EvalSummary`; "fit": the whole run, `FitSummary`); `summary`: its numbers."""

    phase: str
    summary: LoopSummary | FieldSummary | EvalSummary | FitSummary


@dataclass(frozen=True)
class Evaluated:
    """A periodic evaluation during `task` at `iteration`: mean test PSNR (dB), SSIM (None for
    images too small for it), the frames evaluated, the Gaussian count and the training
    seconds so far."""

    task: str
    iteration: int
    psnr: float
    ssim: float | None
    frames: int
    gaussians: int
    train_seconds: float


@dataclass(frozen=True)
class FitStarted:
    """A fit trains `iterations` Phase 1 iterations on scene `scene` (`train` / `test` frames
    of `width` x `height` pixels) into the run folder `run_dir`."""

    scene: str
    train: int
    test: int
    width: int
    height: int
    iterations: int
    run_dir: str


@dataclass(frozen=True)
class Resumed:
    """Training continues the checkpoint `path` at `iteration`."""

    path: str
    iteration: int


@dataclass(frozen=True)
class Assigned:
    """Phase 2 assigned the Gaussians to `num_objects` objects from `source` ("masks",
    "trajectories"); `counts`: Gaussians per object, by name (``{name: count}`` in JSON)."""

    source: str
    num_objects: int
    counts: tuple[ObjectCount, ...] = _pairs()


@dataclass(frozen=True)
class Skipped:
    """What `phase` ("phase1", "phase2", "phase3") skipped in this process, as counts:
    `Phase1Skips` (D_theta rows, node counts, coarse pixels, pruned Gaussians),
    `Phase2Skips` (held objects, M_phi updates, refinement visits, loop iterations),
    `Phase3Skips` (crops encoded and skipped, encoder calls, relational features), or
    `NoCounts` (a field built before the counters)."""

    phase: str
    counts: Phase1Skips | Phase2Skips | Phase3Skips | NoCounts = field(default_factory=NoCounts)

    @classmethod
    def of(cls, phase: str, counts: Mapping[str, Any]) -> Skipped:
        """The event for the counts a stage returns (`Stage.counts`: `phase1_skips`,
        `MotionStrategy.skip_counts`, `Field.counts`; empty: `NoCounts`)."""
        kinds = {"phase1": Phase1Skips, "phase2": Phase2Skips, "phase3": Phase3Skips}
        return cls(phase, kinds[phase](**counts) if counts else NoCounts())


@dataclass(frozen=True)
class DatasetChosen:
    """A fit trains on the dataset folder `path`; `embedded`: the embedded synthetic scene,
    taken because no dataset was given."""

    path: str
    embedded: bool


@dataclass(frozen=True)
class GeneratingScene:
    """The embedded synthetic scene is being written into `path` (`seconds` None), or was,
    in `seconds`."""

    path: str
    seconds: float | None = None


@dataclass(frozen=True)
class SettingChanged:
    """A resumed run's free setting `key` (a phase's length, a cadence) goes from `old` to
    `new`."""

    key: str
    old: object
    new: object


@dataclass(frozen=True)
class Triangulating:
    """Phase 1's initial points of scene `scene` are being triangulated (fixed poses)."""

    scene: str


@dataclass(frozen=True)
class InitialPoints:
    """`count` initial points came from `source`: "triangulation" (from `views` views at time
    `time`, in `seconds`, or read from its cache: `cached`) or "dome" (on the capture dome's
    wall)."""

    source: str
    count: int
    views: int = 0
    time: float = 0.0
    seconds: float = 0.0
    cached: bool = False


@dataclass(frozen=True)
class ScaleAdvice:
    """The scene's extent (world units) is `ratio` times the `reference` extent the absolute
    lengths' defaults are for; `settings`: the overrides that scale them with it
    (``{setting: value}`` in JSON)."""

    ratio: float
    extent: float
    reference: float
    settings: tuple[Override, ...] = _pairs()


@dataclass(frozen=True)
class Phase2Starting:
    """Phase 2 (`iterations` iterations) starts from the Phase 1 checkpoint kept in `kept`:
    the assignment of Gaussians to objects comes first."""

    iterations: int
    kept: str


@dataclass(frozen=True)
class NothingMoves:
    """Phase 2's loop is skipped: each of its `objects` objects is static."""

    objects: int


@dataclass(frozen=True)
class MotionDiagnosed:
    """Phase 2's diagnostics (Appendix C; `sync4d.phase2.diagnostics.diagnostics`, as written
    to ``phase2.json`` without the trajectories): per object and overall."""

    diagnostics: Diagnostics


@dataclass(frozen=True)
class Phase3Started:
    """Phase 3 builds the language field with encoder `kind` (`dim`-dimensional; a
    closed-vocabulary one scores only its own labels)."""

    kind: str
    dim: int
    closed_vocabulary: bool


@dataclass(frozen=True)
class FieldBuilt:
    """The language field of `objects` objects x `frames` frames is in `folder`: `crops`
    crops, `observed` the share (0-1) of object-frames observed, and its build's seconds
    (`total_s`, `observe_s`, `encode_s`)."""

    objects: int
    frames: int
    crops: int
    observed: float
    total_s: float
    observe_s: float
    encode_s: float
    folder: str


@dataclass(frozen=True)
class FramesEvaluated:
    """The per-frame test metrics of an evaluation (`frames`: name, time, psnr, ssim, lpips;
    None where a metric could not run), their `mean` and the background they were scored on
    (`background`: "black", say; empty where only one was)."""

    frames: tuple[FrameScore, ...]
    mean: Means
    background: str = ""


@dataclass(frozen=True)
class MetricUnavailable:
    """The metric `metric` ("SSIM", "LPIPS") cannot run on this evaluation, for `reason`."""

    metric: str
    reason: str


@dataclass(frozen=True)
class Wrote:
    """`stage` ("fit", "eval") wrote its results to `paths` (a folder ends with "/")."""

    stage: str
    paths: tuple[str, ...]


@dataclass(frozen=True)
class Interrupted:
    """A fit stopped on Ctrl-C, SIGTERM or SIGHUP at `iteration` (None: between its loops)
    with its state in `checkpoint`; `resume`: the command that continues it."""

    checkpoint: str
    resume: str
    iteration: int | None = None


Event = (Note | Started | Advanced | Finished | PhaseDone | Evaluated | FitStarted | Resumed
         | Assigned | Skipped | DatasetChosen | GeneratingScene | SettingChanged | Triangulating
         | InitialPoints | ScaleAdvice | Phase2Starting | NothingMoves | MotionDiagnosed
         | Phase3Started | FieldBuilt | FramesEvaluated | MetricUnavailable | Wrote
         | Interrupted)

_lock = threading.Lock()
_subscribers: tuple[Callable[[Event], None], ...] = ()


class Subscription:
    """A subscriber's registration: `close()` (or leaving its ``with`` block) ends it."""

    def __init__(self, callback: Callable[[Event], None]) -> None:
        self.callback = callback
        self.active = True

    def close(self) -> None:
        """Stop delivering events to the callback (once; later calls do nothing)."""
        global _subscribers
        with _lock:
            if self.active:
                self.active = False
                subs = list(_subscribers)
                subs.remove(self.callback)
                _subscribers = tuple(subs)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def subscribe(callback: Callable[[Event], None]) -> Subscription:
    """Deliver every event emitted from now on to `callback`, until the returned
    subscription is closed: ``with subscribe(TerminalRenderer()): run_fit(...)``."""
    global _subscribers
    with _lock:
        _subscribers = (*_subscribers, callback)
    return Subscription(callback)


def emit(event: Event) -> None:
    """Hand `event` to every current subscriber in turn; nothing happens without one."""
    for callback in _subscribers:
        callback(event)


def note(text: str, stream: Literal["err", "out"] = "err", detail: bool = False) -> None:
    """Emit a `Note`: a script's own line for people (the library emits typed events)."""
    if _subscribers:
        emit(Note(text, stream, detail))


class EventLog:
    """A subscriber writing each event as one JSON line (``{"event": "Advanced", "time": unix
    seconds, ...fields}``, the fields as `to_json` writes them) to `path`, appended and
    flushed per line, so another process can follow a run. `Advanced` is written every
    `Started.log_every` steps of its task (and the last), not every step; `Note` lines are
    left out unless `notes`."""

    def __init__(self, path: Path, notes: bool = False) -> None:
        self.path = Path(path)
        self.notes = notes
        self._every: dict[str, tuple[int, int]] = {}
        self._file = self.path.open("a", encoding="utf-8")

    def __call__(self, event: Event) -> None:
        if isinstance(event, Note) and not self.notes:
            return
        if isinstance(event, Started):
            self._every[event.task] = (max(1, event.log_every), event.total)
        if isinstance(event, Advanced):
            every, total = self._every.get(event.task, (1, 0))
            if event.done % every and event.done != total:
                return
        record = {"event": type(event).__name__, "time": round(time.time(), 3),
                  **_fields_json(event)}  # fmt: skip
        self._file.write(json.dumps(record, default=str) + "\n")
        self._file.flush()

    def close(self) -> None:
        """Close the file."""
        self._file.close()


def read_events(path: Path, kinds: tuple[str, ...] = ()) -> list[dict]:
    """The events an `EventLog` wrote to `path` (only those of `kinds`, by class name, when
    given), oldest first; [] when there is no such file. A line cut short by a writer still
    at work is skipped."""
    try:
        lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return []
    out = []
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:
            continue
        if isinstance(record, dict) and (not kinds or record.get("event") in kinds):
            out.append(record)
    return out
