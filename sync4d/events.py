"""What happens in a long computation, as events, and who hears them.

Design. The library rooms (pipeline, phases) neither print nor build progress bars: they
`emit` small frozen events and front ends `subscribe` to them, the way brush's training
process sends messages that its command line and viewer each render.

- `Note`: a script's own line for people, with the stream it belongs on (``"err"``: status,
  warnings; ``"out"``: results) and whether it is a `detail` that a terse front end leaves
  out. The library emits none: its events carry numbers.
- `Started` / `Advanced` / `Finished`: a long loop (``task``: "fit", "phase2", "eval test",
  "refine M_phi", "phase3 observe"), its length, how far it got and its statistics, as
  numbers (``{"loss": 0.0123, "psnr": 24.51, "gaussians": 18000}``).
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
from typing import Literal

__all__ = [
    "Advanced",
    "Assigned",
    "DatasetChosen",
    "Evaluated",
    "Event",
    "EventLog",
    "FieldBuilt",
    "Finished",
    "FitStarted",
    "FramesEvaluated",
    "GeneratingScene",
    "InitialPoints",
    "Interrupted",
    "MetricUnavailable",
    "MotionDiagnosed",
    "NothingMoves",
    "Note",
    "Phase2Starting",
    "Phase3Started",
    "PhaseDone",
    "Resumed",
    "ScaleAdvice",
    "SettingChanged",
    "Skipped",
    "Started",
    "Subscription",
    "Triangulating",
    "Wrote",
    "emit",
    "note",
    "read_events",
    "subscribe",
]


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
    are the loop's statistics as numbers (``{"loss": 0.0123, "psnr": 24.51}``: a training
    loop's moving averages; "gaussians" a count)."""

    task: str
    done: int
    stats: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Finished:
    """The loop `task` ended (finished, stopped by a signal, or left by an exception)."""

    task: str


@dataclass(frozen=True)
class PhaseDone:
    """The stage `phase` ended ("phase1", "phase2": its loop ran to the end; "phase3": a
    language field was built; "eval": a split was evaluated); `summary`: its numbers."""

    phase: str
    summary: Mapping[str, object] = field(default_factory=dict)


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
    "trajectories"); `counts`: Gaussians per object name."""

    source: str
    num_objects: int
    counts: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Skipped:
    """What `phase` ("phase1", "phase2", "phase3") skipped in this process, as counts
    (`phase1_skips`, `MotionStrategy.skip_counts` in the pipeline: D_theta rows, node counts,
    coarse pixels, pruned Gaussians; held objects, M_phi updates, refinement visits, loop
    iterations; Phase 3's `Field.counts`: crops encoded and skipped, encoder calls, relational
    features)."""

    phase: str
    counts: Mapping[str, float] = field(default_factory=dict)


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
    lengths' defaults are for; `settings`: the overrides that scale them with it."""

    ratio: float
    extent: float
    reference: float
    settings: Mapping[str, float] = field(default_factory=dict)


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

    diagnostics: Mapping[str, object] = field(default_factory=dict)


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
    None where a metric could not run), their mean (`mean`) and the background they were
    scored on (`background`: "black", say; empty where only one was)."""

    frames: tuple[Mapping[str, object], ...]
    mean: Mapping[str, object] = field(default_factory=dict)
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
    seconds, ...fields}``) to `path`, appended and flushed per line, so another process can
    follow a run. `Advanced` is written every `Started.log_every` steps of its task (and the
    last), not every step; `Note` lines are left out unless `notes`."""

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
                  **dataclasses.asdict(event)}  # fmt: skip
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
