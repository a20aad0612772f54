"""A dependency-free progress bar for long loops: iteration count, a bar, caller-supplied
statistics (loss, PSNR, #Gaussians, ...), seconds per iteration and ETA.

On a terminal it redraws one line; when stderr is not a terminal (logs, CI) it prints a full
line every `log_every` updates so logs stay readable. `sync4d.terminal.TerminalRenderer` draws
the library's loops (`sync4d.events.Started` / `Advanced` / `Finished`) with it.
"""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO

__all__ = ["Progress", "format_duration"]


def format_duration(seconds: float) -> str:
    """`seconds` as ``1h02m``, ``3m05s`` or ``12.3s``."""
    if not math.isfinite(seconds):
        return "?"
    seconds = max(0.0, seconds)
    if seconds < 60:
        return f"{seconds:.1f}s"
    m, s = divmod(int(round(seconds)), 60)
    if m < 60:
        return f"{m}m{s:02d}s"
    h, m = divmod(m, 60)
    return f"{h}h{m:02d}m"


class Progress:
    """Progress over `total` steps starting at `start` (e.g. a resumed run).

    ``update(step, stats)`` after each step; ``close()`` ends the line. Seconds per iteration is
    an exponential moving average over recent steps, so the ETA follows slow-downs (more
    Gaussians) instead of the run's average."""

    def __init__(
        self,
        total: int,
        start: int = 0,
        desc: str = "",
        stream: TextIO | None = None,
        log_every: int = 100,
        width: int = 24,
    ) -> None:
        self.total = max(1, total)
        self.start = start
        self.desc = desc
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.log_every = max(1, log_every)
        self.width = width
        self.t0 = time.perf_counter()
        self._last_t = self.t0
        self._last_step = start
        self._last_draw = 0.0
        self.sec_per_it = float("nan")
        self._updates = 0

    def update(self, step: int, stats: dict[str, str] | None = None, force: bool = False) -> None:
        """Record that `step` steps (of `total`) are done; `stats` are shown as ``key value``."""
        now = time.perf_counter()
        done = step - self._last_step
        if done > 0:
            rate = (now - self._last_t) / done
            if math.isnan(self.sec_per_it):
                self.sec_per_it = rate
            else:
                self.sec_per_it = 0.9 * self.sec_per_it + 0.1 * rate
            self._last_t, self._last_step = now, step
        self._updates += 1
        last = step >= self.total
        if self.tty:
            if not (force or last or now - self._last_draw > 0.2):
                return
        elif not (force or last or self._updates % self.log_every == 0):
            return
        self._last_draw = now
        frac = min(1.0, step / self.total)
        filled = int(round(frac * self.width))
        bar = "#" * filled + "-" * (self.width - filled)
        eta = self.sec_per_it * (self.total - step)
        parts = [f"{self.desc} " if self.desc else "", f"{step}/{self.total} [{bar}]"]
        for k, v in (stats or {}).items():
            parts.append(f" {k} {v}")
        parts.append(
            f" | {self.sec_per_it:.3f} s/it | elapsed {format_duration(now - self.t0)}"
            f" | ETA {format_duration(eta)}"
        )
        line = "".join(parts)
        if self.tty:
            self.stream.write("\r\x1b[2K" + line)
        else:
            self.stream.write(line + "\n")
        self.stream.flush()

    def message(self, text: str) -> None:
        """Print `text` on its own line without breaking the bar."""
        if self.tty:
            self.stream.write("\r\x1b[2K")
        self.stream.write(text + "\n")
        self.stream.flush()

    def close(self) -> None:
        """Finish the bar's line."""
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
