"""The words of `sync4d.events`: how the command line writes what the library reports.

The library emits numbers (typed events); this module holds, for each event, the rule that
turns it into the lines a command prints (`WORDS`, one rule an event), and the subscriber that
prints them (`TerminalRenderer`). A rule returns a `Line`: the text (several lines, or "" for
none), its stream ("err": status, warnings; "out": results) and whether it is a `detail` (the
tables and "wrote ..." lines that a terse front end such as ``bench fit`` leaves out). The
rules read the events' typed payloads (`sync4d.events.Stats`, `FitSummary`, `Phase1Skips`,
...) by attribute: an optional field is None where the library had nothing to say.
`Started` / `Advanced` / `Finished` have no words: they draw a `sync4d.progress.Progress` bar.

A front end that wants other words (a GUI, another language) subscribes its own renderer to
the same events; `sync4d.events.EventLog` writes them as JSON lines for another process.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from sync4d.events import (
    Advanced,
    Assigned,
    DatasetChosen,
    Diagnostics,
    Evaluated,
    Event,
    FieldBuilt,
    Finished,
    FitStarted,
    FitSummary,
    FrameScore,
    FramesEvaluated,
    GeneratingScene,
    InitialPoints,
    Interrupted,
    Means,
    MetricUnavailable,
    MotionDiagnosed,
    Note,
    NothingMoves,
    Phase1Skips,
    Phase2Skips,
    Phase2Starting,
    Phase3Skips,
    Phase3Started,
    PhaseDone,
    Resumed,
    ScaleAdvice,
    SettingChanged,
    Skipped,
    Started,
    Stats,
    Subscription,
    Triangulating,
    Wrote,
    subscribe,
)
from sync4d.progress import Progress, format_duration
from sync4d.report import align_table

__all__ = ["BARS", "WORDS", "Line", "TerminalRenderer", "format_diagnostics", "format_metrics",
           "format_stats", "words"]  # fmt: skip


class Line(NamedTuple):
    """What a command prints for one event: `text` ("" for nothing) on `stream`; a `detail`
    is left out by a terse renderer."""

    text: str
    stream: str = "err"
    detail: bool = False


#: The events that draw a progress bar instead of words.
BARS = (Started, Advanced, Finished)

def format_stats(stats: Stats) -> dict[str, str]:
    """A loop's statistics as the bar shows them (``{"PSNR": "24.51", "#G": "18000"}``), those
    it has, in the order loss, PSNR, Gaussians, rho."""
    shown = (("loss", stats.loss, ".4f"), ("PSNR", stats.psnr, ".2f"),
             ("#G", None if stats.gaussians is None else int(stats.gaussians), "d"),
             ("rho", stats.rho, ".3f"))  # fmt: skip
    return {label: format(value, spec) for label, value, spec in shown if value is not None}


def _or(value: Any, spec: str, none: str = "n/a") -> str:
    return none if value is None else format(value, spec)


def format_metrics(frames: Sequence[FrameScore], mean: Means, background: str = "") -> str:
    """The evaluation's per-frame table (`frames`: name, time, psnr, ssim, lpips) and its
    mean row, under "on BACKGROUND:" when `background` is named."""
    rows = [[m.name, f"{m.time:.3f}", _or(m.psnr, ".2f", "-"), _or(m.ssim, ".4f", "-"),
             _or(m.lpips, ".4f", "-")] for m in frames]  # fmt: skip
    rows.append(["mean", "", _or(mean.psnr, ".2f", "-"), _or(mean.ssim, ".4f", "-"),
                 _or(mean.lpips, ".4f", "-")])  # fmt: skip
    table = align_table(["frame", "time", "PSNR dB", "SSIM", "LPIPS"], rows)
    return f"on {background}:\n{table}" if background else table


def format_diagnostics(diag: Diagnostics) -> str:
    """Phase 2's diagnostics (Appendix C) as a table plus a summary line."""
    rows = [
        [str(o.label), o.name, f"{o.gaussians:,}", "held" if o.held else "yes" if o.static
         else "", f"{o.rigid_share:.3f}", f"{o.residual_mean:.4f}", f"{o.motion_variance:.2e}"]
        for o in diag.objects
    ]  # fmt: skip
    table = align_table(
        ["k", "object", "Gaussians", "static", "rigid share", "residual", "motion var"], rows,
        left=(1,),
    )  # fmt: skip
    text = (f"{table}\nmean rigid share {diag.rigid_share:.3f}, residual energy "
            f"{diag.residual_energy:.2e}, modulated fraction {diag.modulated_fraction:.3f}, "
            f"shuffle ratio {diag.shuffle_ratio:.2f} ({diag.assignment} assignment)")
    if diag.mask_agreement_ari is not None:
        text += (f"\nagreement with mask voting: adjusted Rand index "
                 f"{diag.mask_agreement_ari:.3f} ({diag.num_objects - 1} clusters vs "
                 f"{diag.mask_objects} mask objects)")  # fmt: skip
    return text


def _evaluated(e: Evaluated) -> Line:
    return Line(f"[eval @ {e.iteration}] test PSNR {e.psnr:.2f} dB, SSIM {_or(e.ssim, '.4f')} "
                f"({e.frames} frames, {e.gaussians} Gaussians, "
                f"{format_duration(e.train_seconds)} training)")  # fmt: skip


def _fit_started(e: FitStarted) -> Line:
    return Line(f"fit: {e.scene}: {e.train} train / {e.test} test frames at {e.width}x"
                f"{e.height}, {e.iterations} iterations -> {e.run_dir}")  # fmt: skip


def _phase_done(e: PhaseDone) -> Line:
    """Only the whole fit's end has words (a stage's end shows in its bar and tables)."""
    s = e.summary
    if e.phase != "fit" or not isinstance(s, FitSummary):
        return Line("")
    on = f" on {s.background}" if s.background else ""
    text = (f"fit: done in {format_duration(float(s.train_seconds))} of training: test PSNR"
            f"{on} {s.psnr:.2f} dB, SSIM {_or(s.ssim, '.4f')}, LPIPS {_or(s.lpips, '.4f')}, "
            f"{s.gaussians} Gaussians; run in {s.run_dir}")  # fmt: skip
    for b in s.backgrounds or ():
        m = b.scores
        text += (f"\nfit: on {b.name}: test PSNR {m.psnr:.2f} dB, SSIM {_or(m.ssim, '.4f')}, "
                 f"LPIPS {_or(m.lpips, '.4f')}")  # fmt: skip
    d = s.phase2
    if d:
        text += (f"\nfit: Phase 2: mean rigid share {d.rigid_share:.3f}, shuffle ratio "
                 f"{d.shuffle_ratio:.2f}, {d.objects} labels ({d.assignment})")
    return Line(text, "out", detail=True)


def _assigned(e: Assigned) -> Line:
    counts = ", ".join(f"{c.name} {c.gaussians}" for c in e.counts)
    return Line(f"fit: {e.source} assignment, K = {e.num_objects}: {counts}")


def _skipped(e: Skipped) -> Line:
    """The lines `fit` prints for what a phase skipped (one per switch that is on)."""
    c = e.counts
    if isinstance(c, Phase1Skips):
        return Line(_phase1_skipped(c))
    if isinstance(c, Phase2Skips):
        return Line(_phase2_skipped(c))
    if isinstance(c, Phase3Skips):
        return Line(_phase3_skipped(c))
    if e.phase == "phase3":  # NoCounts
        return Line("fit: Phase 3 skipped nothing that it counted (a field built before the "
                    "counters)")  # fmt: skip
    return Line("")


def _phase1_skipped(c: Phase1Skips) -> str:
    lines = []
    if c.nodes is not None:
        lines.append(f"fit: Phase 1 moved {c.gaussians} Gaussians by {c.nodes} control nodes "
                     f"from iteration {c.nodes_from} (D_theta on the nodes, not the Gaussians; "
                     f"nodes added {c.nodes_added}, removed {c.nodes_removed})")  # fmt: skip
    elif c.deform_rows is not None:
        evaluations = c.deform_rows + c.deform_rows_skipped
        line = (f"fit: Phase 1 skipped D_theta on {c.share:.0%} of the Gaussian evaluations "
                f"({c.deform_rows_skipped} of {evaluations}); static at the end: "
                f"{c.static} of {c.gaussians} Gaussians")  # fmt: skip
        if c.static == c.gaussians:
            line += "; no Gaussian moves: a static scene, D_theta no longer evaluated"
        lines.append(line)
    if c.coarse_iterations is not None:
        lines.append(f"fit: Phase 1 trained its first {c.coarse_iterations} iterations at "
                     f"{c.coarse_scale:g}x resolution: {c.pixels_saved:.0%} fewer pixels "
                     "rendered in all")  # fmt: skip
    if c.pruned is not None:
        lines.append(f"fit: Phase 1 pruned {c.pruned} transparent Gaussians (opacity < "
                     f"{c.prune_opacity:g}) after densification")  # fmt: skip
    return "\n".join(lines)


def _phase2_skipped(c: Phase2Skips) -> str:
    updates = c.motion_updates + c.motion_updates_skipped
    visits = c.refine_visits + c.refine_visits_skipped
    line = (f"fit: Phase 2 held {c.held} of {c.objects} objects at a constant transform: "
            f"skipped {c.motion_updates_skipped} of {updates} M_phi object updates and "
            f"{c.refine_visits_skipped} of {visits} refinement visits (static objects)")
    if c.loop_skipped:
        line += f"; its loop of {c.loop_skipped} iterations skipped: no object moves"
    return line


def _phase3_skipped(c: Phase3Skips) -> str:
    """What Phase 3 encoded and skipped (`sync4d.phase3.store.Field.counts`)."""
    calls = c.encoder_calls
    line = (f"fit: Phase 3 encoded {c.crops_encoded} of {c.object_frames} object-frames "
            f"in {calls} encoder call{'' if calls == 1 else 's'}")  # fmt: skip
    if c.extra_crops:
        line += (f" ({c.extra_crops} unobserved ones encoded and discarded: "
                 f"phase3.skip_unobserved is off; {c.invisible} invisible, "
                 f"{c.below_threshold} below min_visible/min_box)")  # fmt: skip
    else:
        line += (f" ({c.invisible} invisible and {c.below_threshold} below "
                 "min_visible/min_box skipped)")  # fmt: skip
    line += f"; relational features on {c.relational} object-frames"
    if c.relational_skipped:
        line += f" ({c.relational_skipped} without another object left at 0)"
    if c.relational_unobserved:
        line += (f" ({c.relational_unobserved} at frames with an unobserved object, "
                 "kept: the prediction there reads them)")  # fmt: skip
    return line


def _dataset_chosen(e: DatasetChosen) -> Line:
    return Line("fit: no dataset given; using the embedded synthetic scene" if e.embedded
                else "")  # fmt: skip


def _generating_scene(e: GeneratingScene) -> Line:
    if e.seconds is None:
        return Line(f"generating the synthetic scene in {e.path} ...")
    return Line(f"  done in {e.seconds:.1f}s")


def _initial_points(e: InitialPoints) -> Line:
    if e.source == "dome":
        return Line(f"fit: {e.count} initial points on the dome's wall", detail=True)
    how = "cached" if e.cached else f"{e.seconds:.0f} s"
    return Line(f"fit: {e.count} initial points from {e.views} views at t={e.time:g} ({how})",
                detail=True)  # fmt: skip


def _scale_advice(e: ScaleAdvice) -> Line:
    sets = " ".join(f"--set {o.setting}={o.value:.3g}" for o in e.settings)
    return Line(f"fit: this scene is {e.ratio:.3g} times the size the absolute lengths' defaults "
                f"are for (extent {e.extent:.3g} world units against {e.reference}); to train "
                f"it as the default-sized scene trains, scale them with it: {sets}")


def _field_built(e: FieldBuilt) -> Line:
    return Line(f"fit: Phase 3: {e.objects} objects x {e.frames} frames, {e.crops} crops "
                f"({100 * e.observed:.0f} % observed), built in {e.total_s:.1f} s (observe "
                f"{e.observe_s:.1f}, encode {e.encode_s:.1f}); field in {e.folder}", "out")


def _phase3_started(e: Phase3Started) -> Line:
    closed = ", closed-vocabulary" if e.closed_vocabulary else ""
    return Line(f"fit: Phase 3 (language field) with the {e.kind} encoder ({e.dim}-d{closed}) "
                "...")


def _interrupted(e: Interrupted) -> Line:
    where = ("; the last checkpoint is" if e.iteration is None
             else f" at iteration {e.iteration}; checkpoint saved to")  # fmt: skip
    return Line(f"fit: interrupted{where} {e.checkpoint}.\n     continue with: {e.resume}")


#: One rule an event: the `Line` a command prints for it.
WORDS: dict[type, Callable[[Any], Line]] = {
    Note: lambda e: Line(e.text, e.stream, e.detail),
    Evaluated: _evaluated,
    FitStarted: _fit_started,
    Resumed: lambda e: Line(f"fit: resumed {e.path} at iteration {e.iteration}"),
    Assigned: _assigned,
    Skipped: _skipped,
    PhaseDone: _phase_done,
    DatasetChosen: _dataset_chosen,
    GeneratingScene: _generating_scene,
    SettingChanged: lambda e: Line(f"fit: {e.key}: {e.old} -> {e.new}"),
    Triangulating: lambda e: Line("fit: triangulating initial points (pycolmap, fixed poses)...",
                                  detail=True),
    InitialPoints: _initial_points,
    ScaleAdvice: _scale_advice,
    Phase2Starting: lambda e: Line(f"fit: Phase 2 ({e.iterations} iterations) from {e.kept}: "
                                   "assigning Gaussians to objects ..."),
    NothingMoves: lambda e: Line(f"fit: Phase 2 skipped: no object moves ({e.objects} static "
                                 "objects)"),
    MotionDiagnosed: lambda e: Line(format_diagnostics(e.diagnostics), "out", detail=True),
    Phase3Started: _phase3_started,
    FieldBuilt: _field_built,
    FramesEvaluated: lambda e: Line(format_metrics(e.frames, e.mean, e.background), "out",
                                    detail=True),
    MetricUnavailable: lambda e: Line(f"eval: {e.metric} n/a: {e.reason}"),
    Wrote: lambda e: Line(f"{e.stage}: wrote {' and '.join(e.paths)}", "out", detail=True),
    Interrupted: _interrupted,
}


def words(event: Event) -> Line:
    """The `Line` a command prints for `event` (empty text for a bar's event)."""
    rule = WORDS.get(type(event))
    return Line("") if rule is None else rule(event)


class TerminalRenderer:
    """Renders `sync4d.events` as the commands print them: `Started` / `Advanced` / `Finished`
    as a `Progress` bar on stderr with the statistics formatted (`format_stats`), every other
    event as its `words` on its stream (sys.stdout or sys.stderr at that moment; on stderr
    through the open bar, so a terminal's bar is not broken). With `details` False the lines
    marked `detail` (tables, "wrote ..." lines, the fit's result lines) are left out, as
    ``bench fit`` shows its runs.

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
        if isinstance(event, Started):
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
            line = words(event)
            if line.text and (self.details or not line.detail):
                self._line(line.text, line.stream)
