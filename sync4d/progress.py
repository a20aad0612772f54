"""A dependency-free progress bar for long loops: iteration count, a bar, caller-supplied
statistics (loss, PSNR, #Gaussians, ...), seconds per iteration and ETA.

On a terminal it redraws one line; when stderr is not a terminal (logs, CI) it prints a full
line every `log_every` updates so logs stay readable.

`TerminalRenderer` is the command line's subscriber to `sync4d.events`: it prints the
pipeline's notes and draws its loops as `Progress` bars.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Mapping
from typing import TextIO

from sync4d.events import (
    Advanced,
    Assigned,
    Evaluated,
    Event,
    Finished,
    FitStarted,
    Note,
    PhaseDone,
    Resumed,
    Skipped,
    Started,
    Subscription,
    subscribe,
)

__all__ = ["Progress", "TerminalRenderer", "format_duration"]


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


#: How the renderer shows a loop's statistics (`Advanced.stats`): label and format.
STAT_FORMATS = {"loss": ("loss", ".4f"), "psnr": ("PSNR", ".2f"), "gaussians": ("#G", "d"),
                "rho": ("rho", ".3f")}  # fmt: skip


def format_stats(stats: Mapping[str, float]) -> dict[str, str]:
    """A loop's statistics as the bar shows them (``{"PSNR": "24.51", "#G": "18000"}``)."""
    out = {}
    for key, value in stats.items():
        label, spec = STAT_FORMATS.get(key, (key, ".4g"))
        out[label] = format(int(value), spec) if spec == "d" else format(value, spec)
    return out


def _or_na(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


class TerminalRenderer:
    """Renders `sync4d.events` as the commands print them: a `Note` as its lines on its stream
    (sys.stdout or sys.stderr at that moment; on stderr through the open bar, so a terminal's
    bar is not broken), `Started` / `Advanced` / `Finished` as a `Progress` bar on stderr with
    the statistics formatted (`format_stats`), and the typed events (`Evaluated`,
    `FitStarted`, `Resumed`, `Assigned`, `PhaseDone` of a whole fit) as the lines `fit`
    prints: the library emits numbers, the words are written here. With `details` False the
    notes marked `detail` (tables, "wrote ..." lines) and the results' lines on stdout are
    left out, as ``bench fit`` shows its runs.

    ``with renderer.installed(): ...`` (or ``with subscribe(renderer)``) renders what the block
    emits."""

    def __init__(self, details: bool = True) -> None:
        self.details = details
        self.bars: dict[str, Progress] = {}

    def installed(self) -> Subscription:
        """Subscribe this renderer; the subscription ends it (a context manager)."""
        return subscribe(self)

    def _line(self, text: str, stream: str = "err") -> None:
        if stream == "err" and self.bars:
            next(reversed(self.bars.values())).message(text)
        else:
            print(text, file=sys.stderr if stream == "err" else sys.stdout)

    def __call__(self, event: Event) -> None:
        if isinstance(event, Note):
            if event.detail and not self.details:
                return
            self._line(event.text, event.stream)
        elif isinstance(event, Started):
            self.bars[event.task] = Progress(
                event.total, start=event.start, desc=event.task, log_every=event.log_every
            )
        elif isinstance(event, Advanced):
            bar = self.bars.get(event.task)
            if bar is not None:
                bar.update(event.done, format_stats(event.stats))
        elif isinstance(event, Finished):
            bar = self.bars.pop(event.task, None)
            if bar is not None:
                bar.close()
        else:
            text, stream = self.words(event)
            if text and (self.details or stream == "err"):
                self._line(text, stream)

    @staticmethod
    def words(event: Event) -> tuple[str, str]:
        """The line (and its stream) `fit` prints for a typed event; "" for none."""
        if isinstance(event, Evaluated):
            return (f"[eval @ {event.iteration}] test PSNR {event.psnr:.2f} dB, SSIM "
                    f"{_or_na(event.ssim, '.4f')} ({event.frames} frames, {event.gaussians} "
                    f"Gaussians, {format_duration(event.train_seconds)} training)"), "err"
        if isinstance(event, FitStarted):
            return (f"fit: {event.scene}: {event.train} train / {event.test} test frames at "
                    f"{event.width}x{event.height}, {event.iterations} iterations -> "
                    f"{event.run_dir}"), "err"
        if isinstance(event, Resumed):
            return f"fit: resumed {event.path} at iteration {event.iteration}", "err"
        if isinstance(event, Assigned):
            counts = ", ".join(f"{name} {n}" for name, n in event.counts.items())
            return f"fit: {event.source} assignment, K = {event.num_objects}: {counts}", "err"
        if isinstance(event, Skipped):
            return _skipped_words(event), "err"
        if isinstance(event, PhaseDone) and event.phase == "fit":
            s = event.summary
            line = (f"fit: done in {format_duration(float(s['train_seconds']))} of training: "
                    f"test PSNR {s['psnr']:.2f} dB, SSIM {_or_na(s['ssim'], '.4f')}, LPIPS "
                    f"{_or_na(s['lpips'], '.4f')}, {s['gaussians']} Gaussians; run in "
                    f"{s['run_dir']}")  # fmt: skip
            d = s.get("phase2")
            if d:
                line += (f"\nfit: Phase 2: mean rigid share {d['rigid_share']:.3f}, shuffle "
                         f"ratio {d['shuffle_ratio']:.2f}, {d['objects']} labels "
                         f"({d['assignment']})")  # fmt: skip
            return line, "out"
        return "", "err"


def _skipped_words(event: Skipped) -> str:
    """The lines `fit` prints for what a phase skipped (one per switch that is on)."""
    c = event.counts
    if event.phase == "phase2":
        updates = c["motion_updates"] + c["motion_updates_skipped"]
        visits = c["refine_visits"] + c["refine_visits_skipped"]
        line = (f"fit: Phase 2 held {c['held']} of {c['objects']} objects at a constant "
                f"transform: skipped {c['motion_updates_skipped']} of {updates} M_phi object "
                f"updates and {c['refine_visits_skipped']} of {visits} refinement visits "
                "(static objects)")  # fmt: skip
        if c["loop_skipped"]:
            line += f"; its loop of {c['loop_skipped']} iterations skipped: no object moves"
        return line
    lines = []
    if "nodes" in c:
        lines.append(f"fit: Phase 1 moved {c['gaussians']} Gaussians by {c['nodes']} control "
                     f"nodes from iteration {c['nodes_from']} (D_theta on the nodes, not the "
                     f"Gaussians; nodes added {c['nodes_added']}, removed "
                     f"{c['nodes_removed']})")  # fmt: skip
    elif "deform_rows" in c:
        evaluations = c["deform_rows"] + c["deform_rows_skipped"]
        line = (f"fit: Phase 1 skipped D_theta on {c['share']:.0%} of the Gaussian evaluations "
                f"({c['deform_rows_skipped']} of {evaluations}); static at the end: "
                f"{c['static']} of {c['gaussians']} Gaussians")  # fmt: skip
        if c["static"] == c["gaussians"]:
            line += "; no Gaussian moves: a static scene, D_theta no longer evaluated"
        lines.append(line)
    if "coarse_iterations" in c:
        lines.append(f"fit: Phase 1 trained its first {c['coarse_iterations']} iterations at "
                     f"{c['coarse_scale']:g}x resolution: {c['pixels_saved']:.0%} fewer pixels "
                     "rendered in all")  # fmt: skip
    if "pruned" in c:
        lines.append(f"fit: Phase 1 pruned {c['pruned']} transparent Gaussians (opacity < "
                     f"{c['prune_opacity']:g}) after densification")  # fmt: skip
    return "\n".join(lines)
