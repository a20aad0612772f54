"""What happens in a long computation, as events, and who hears them.

Design. The library rooms (pipeline, phases) neither print nor build progress bars: they
`emit` small frozen events and front ends `subscribe` to them, the way brush's training
process sends messages that its command line and viewer each render.

- `Note`: a line meant for people, with the stream it belongs on (``"err"``: status,
  warnings; ``"out"``: results) and whether it is a `detail` (tables and "wrote ..." lines,
  which a terse front end such as ``bench fit`` leaves out).
- `Started` / `Advanced` / `Finished`: a long loop (``task``: "fit", "phase2", "eval test",
  "refine M_phi", "phase3 observe"), its length, how far it got and the statistics it shows.
- `PhaseDone`: a stage ended ("phase1", "phase2", "phase3", "eval") with its summary.

The command line subscribes `sync4d.progress.TerminalRenderer`, which prints the notes and
draws the bars exactly as the commands always did; the viewer of a later issue subscribes to
the same stream.

Without a subscriber an event is dropped: library use (tests, scripts, ``bench phase3``) is
silent unless someone listens, so there is no `quiet` or `progress` switch to thread through.
Delivery is synchronous, in the emitting thread and in subscription order, so a renderer's
lines interleave with a front end's own prints exactly as prints did. The subscribers are one
process-wide list, not a context variable, so a viewer thread hears a training thread;
subscribing and unsubscribing take a lock, `emit` reads a snapshot. A subscriber's exception
reaches the emitter. This module is the lowest floor: every room may emit.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

__all__ = [
    "Advanced",
    "Event",
    "Finished",
    "Note",
    "PhaseDone",
    "Started",
    "Subscription",
    "emit",
    "note",
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
    are the loop's statistics as shown (``{"loss": "0.0123", "PSNR": "24.51"}``)."""

    task: str
    done: int
    stats: Mapping[str, str] = field(default_factory=dict)


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


Event = Note | Started | Advanced | Finished | PhaseDone

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
    """Emit a `Note`: ``note(f"fit: resumed {path}")`` where a library used to print."""
    if _subscribers:
        emit(Note(text, stream, detail))
