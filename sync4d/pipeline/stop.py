"""How a run stops: Ctrl-C (SIGINT), SIGTERM, a hang-up (SIGHUP) and every other catchable
signal whose default would end the process (SIGQUIT, SIGUSR1, SIGUSR2, SIGXCPU: a batch
scheduler's CPU limit) end training the same way, with a checkpoint of the last completed
iteration. Timer signals (SIGALRM, SIGPROF, SIGVTALRM) are left to the libraries that use them;
Python itself ignores SIGPIPE and SIGXFSZ (a write then fails as an error instead).

While `StopSignals` is installed, a signal in a training loop only sets `requested`: the loop
finishes its iteration (a half-applied optimiser or densification step is never saved) and
stops. A signal during a save is held until the save has finished, so a second Ctrl-C never
tears a checkpoint. Outside those, in the long steps between loops (Phase 2's assignment and
photometric refinement, the final evaluation), the first signal raises `KeyboardInterrupt`
at once: the last checkpoint is already on disk. Further signals after the first are ignored
while the run winds down.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator
from types import FrameType

__all__ = ["STOP_SIGNALS", "StopSignals"]

#: The signals that end a run like Ctrl-C.
STOP_SIGNALS = (
    signal.SIGINT,
    signal.SIGTERM,
    signal.SIGHUP,
    signal.SIGQUIT,
    signal.SIGUSR1,
    signal.SIGUSR2,
    signal.SIGXCPU,
)


class StopSignals:
    """Signal handlers for one run (`with StopSignals() as stop:`); restores the previous
    handlers on exit. Must be entered from the main thread."""

    def __init__(self) -> None:
        #: The first stop signal's number once one arrived, else None.
        self.requested: int | None = None
        self._defer = 0
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:  # noqa: ARG002
        if self.requested is not None:
            return  # already stopping: the save or clean-up under way finishes
        self.requested = signum
        if not self._defer:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def deferred(self) -> Iterator[None]:
        """A block (a training loop, a save) that a signal does not interrupt: it only sets
        `requested`, which the block checks."""
        self._defer += 1
        try:
            yield
        finally:
            self._defer -= 1

    def __enter__(self) -> StopSignals:
        for s in STOP_SIGNALS:
            self._previous[s] = signal.signal(s, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)  # type: ignore[arg-type]
        self._previous.clear()
