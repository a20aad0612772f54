"""The fit loop: the selected stages (`sync4d.pipeline.stages`: Phase 1, then Phase 2 from its
model, then Phase 3's language field) into a run folder, with periodic test evaluation, atomic
checkpoints every K iterations and on Ctrl-C or SIGTERM, resume from the last checkpoint, and
a final evaluation. The loop asks each stage what to do and never which phase it is. It prints
nothing: it reports progress and results as `sync4d.events`, which the command line renders.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from sync4d import watchdog
from sync4d.config import ConfigError, RunConfig, parse_phases, repo_configs
from sync4d.data import Scene
from sync4d.errors import Sync4dError
from sync4d.events import (
    Advanced,
    BackgroundScore,
    DatasetChosen,
    Evaluated,
    EventLog,
    Finished,
    FitSummary,
    Interrupted,
    LoopSummary,
    Phase2Brief,
    PhaseDone,
    Resumed,
    Scores,
    Skipped,
    Started,
    Stats,
    emit,
    subscribe,
)
from sync4d.files import RunLock, write_text_atomic
from sync4d.phase1.motion.per_gaussian import static_skip_counts
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.pipeline.evaluate import evaluate_frames, summarize, with_backgrounds
from sync4d.pipeline.record import continue_command, dataset_fingerprint
from sync4d.pipeline.stages import (
    FitData,
    FitState,
    TrainingStage,
    length_advice,
    restart_phase2,
    stage_of_kind,
    stages_for,
)
from sync4d.pipeline.stop import StopSignals
from sync4d.runs.checkpoint import (
    CheckpointKind,
    camera_records,
    checkpoint_kind,
    read_checkpoint,
    save_checkpoint,
    state_errors,
    write_checkpoint,
)
from sync4d.runs.names import CHECKPOINT_NAME, EVENTS_FILE, METRICS_FILE, RUN_FILE

__all__ = [
    "FitData",
    "FitInterrupted",
    "FitOutcome",
    "TrainingDiverged",
    "event_log",
    "length_advice",
    "resolve_data",
    "restart_phase2",
    "resume_trainer",
    "run_fit",
    "run_stages",
    "set_threads",
]


def set_threads(threads: int | None) -> int:
    """Use `threads` CPU threads (all the process may use when None) and torch's deterministic
    kernels: with a fixed seed, thread count and machine, a run is then bit-identical to the
    last. Without them the backward of indexing with repeated indices (M_phi's `A[labels]`,
    the refinement's per-object gathers) adds from several threads in a timing-dependent
    order and Phase 2 differed run to run at 2 threads (docs/results/phase2-robustness.md)."""
    n = threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(n)
    torch.use_deterministic_algorithms(True, warn_only=True)
    return n


class FitInterrupted(Exception):
    """Training stopped by Ctrl-C, SIGTERM or SIGHUP after saving its checkpoint (no
    `Sync4dError`: nothing to fix, exit status 130)."""


class TrainingDiverged(Sync4dError, RuntimeError):
    """A NaN or inf stopped training (`sync4d.watchdog`); the message says where, what the run
    folder keeps and what to try; exit status 3."""

    exit_code = 3


def _snapshot(trainer: Phase1Trainer) -> tuple[dict[str, torch.Tensor], dict]:
    """A copy of `trainer.state()`: the state a loop started from, saved should the loop
    diverge before it wrote a checkpoint."""
    tensors, meta = trainer.state()
    return {k: v.detach().clone() for k, v in tensors.items()}, json.loads(json.dumps(meta))


def _stopped(e: watchdog.NonFinite, trainer: Phase1Trainer, save, ckpt: Path,
             initial: tuple[dict[str, torch.Tensor], dict] | None = None,
             extra: dict | None = None) -> TrainingDiverged:  # fmt: skip
    """The error for `e`, after saving the trainer's state when it is still the previous
    iteration's (`e.clean`: the optimizer moved nothing), so the run keeps its last good state;
    a state the optimizer already wrote is never saved. Without a checkpoint on disk, the
    state the loop started from (`initial`, finite) is saved instead."""
    if e.clean:
        trainer.iteration -= 1  # the failed iteration did not happen
        trainer.optimizer.zero_grad(set_to_none=True)
        save()
        kept = f"its state after iteration {trainer.iteration} is saved in {ckpt}"
    elif ckpt.exists():
        last = read_checkpoint(ckpt)[1].get("iteration")
        kept = f"{ckpt} keeps the last good checkpoint (iteration {last})"
    elif initial is not None and all(bool(torch.isfinite(t).all()) for t in
                                     initial[0].values() if t.is_floating_point()):
        write_checkpoint(ckpt, *initial, {**(extra or {}), "train_seconds": 0.0})
        kept = (f"no checkpoint had been written yet: the state training started from "
                f"(iteration {initial[1].get('iteration')}) is saved in {ckpt}")
    else:
        kept = "no checkpoint was written"
    run = ckpt.parent
    return TrainingDiverged(f"{e}. Nothing poisoned was saved: {kept}. Start over with the "
                            f"change (`sync4d fit ... --out {run} --force`), or retry as it "
                            f"was (`sync4d fit --out {run} --resume`).")  # fmt: skip


def _train_loop(
    trainer: Phase1Trainer,
    total: int,
    cfg: RunConfig,
    ckpt: Path,
    extra: dict,
    log,
    periodic: list,
    target,
    n_threads: int,
    desc: str,
    log_every: int,
    train_seconds: float,
    stop: StopSignals,
) -> tuple[float, bool]:
    """Step `trainer` up to `total` iterations with progress events (task `desc`), periodic
    evaluation and checkpoints; returns (training seconds, whether a stop signal ended it). A
    signal ends the loop after the iteration under way; the last state is always
    checkpointed."""
    emit(Started(desc, total, start=trainer.iteration, log_every=log_every))
    watchdog.forget()  # the stop's advice reads only this loop's evidence
    ema: dict[str, float] = {}

    def save() -> None:
        save_checkpoint(trainer, ckpt, {**extra, "train_seconds": train_seconds})

    initial = None if ckpt.exists() else _snapshot(trainer)

    with stop.deferred():
        try:
            while trainer.iteration < total and stop.requested is None:
                t0 = time.perf_counter()
                stats = trainer.step()
                train_seconds += time.perf_counter() - t0
                for k in ("loss", "psnr", "rho"):
                    v = stats.get(k)
                    if v is not None and math.isfinite(v):
                        ema[k] = v if k not in ema else 0.9 * ema[k] + 0.1 * v
                it = trainer.iteration
                emit(Advanced(desc, it, Stats(loss=ema.get("loss", math.nan),
                                              psnr=ema.get("psnr", math.nan),
                                              gaussians=trainer.model.num_gaussians,
                                              rho=ema.get("rho"))))  # fmt: skip
                if it % log_every == 0:
                    log({"phase": desc, "iteration": it, "train_seconds": train_seconds,
                         **stats})  # fmt: skip
                if cfg.eval_every and it % cfg.eval_every == 0 and it < total:
                    res = summarize(
                        evaluate_frames(
                            trainer.model, periodic, cfg.phase1.background, n_threads,
                            images=target,
                        )  # fmt: skip
                    )
                    log({"phase": desc, "iteration": it, "train_seconds": train_seconds,
                         "test": res})  # fmt: skip
                    emit(Evaluated(desc, it, res["psnr"], res["ssim"], res["frames"],
                                   trainer.model.num_gaussians, train_seconds))
                if cfg.checkpoint_every and it % cfg.checkpoint_every == 0 and it < total:
                    save()
        except KeyboardInterrupt:  # raised by a step itself, not by our handler
            stop.requested = stop.requested or int(signal.SIGINT)
        except watchdog.NonFinite as e:
            raise _stopped(e, trainer, save, ckpt, initial, extra) from None
        finally:
            emit(Finished(desc))
        save()
    return train_seconds, stop.requested is not None


def resolve_data(data: str | Path | None) -> tuple[Path, Path | None]:
    """Dataset folder and its default config: `data` (no default config), or with None the
    embedded synthetic scene (generated once into the cache) and the shipped synthetic config;
    emits `DatasetChosen`."""
    if data is not None:
        emit(DatasetChosen(str(data), embedded=False))
        return Path(data), None
    from sync4d.data.synthetic import default_scene_dir, ensure_default_scene

    emit(DatasetChosen(str(default_scene_dir()), embedded=True))
    root = ensure_default_scene()
    cfg = repo_configs() / "synthetic.toml"
    return root, cfg if cfg.exists() else None


def resume_trainer(
    path: str | Path,
    scene: Scene,
    config=None,
    threads: int | None = None,
    total_iterations: int | None = None,
    phase2=None,
    near: float | None = None,
) -> Phase1Trainer:
    """Rebuild the trainer of the stage that wrote `path` exactly as it was when `path` was
    saved (Phase 2's with `phase2`'s settings; `total_iterations` extends or shortens the run,
    the learning-rate schedules follow the new length; `near` replaces the stored near
    plane)."""
    path = Path(path)
    tensors, meta = read_checkpoint(path)
    stage = stage_of_kind(CheckpointKind(meta.get("kind", CheckpointKind.PHASE1)))
    with state_errors(path):
        return stage.resume(tensors, meta, scene, config=config, phase2=phase2, near=near,
                            total_iterations=total_iterations, threads=threads)  # fmt: skip


@dataclass(frozen=True)
class FitOutcome:
    """What a fit did: the training summary (None when no selected stage trains, as
    ``--phases 3`` alone) and the language field it built (None without Phase 3)."""

    run_dir: Path
    summary: dict | None = None
    phase3: object | None = None


def run_fit(
    data: FitData,
    cfg: RunConfig,
    run_dir: Path,
    resume: bool = False,
    threads: int | None = None,
    log_every: int = 100,
    command: dict | None = None,
) -> dict:
    """Train (or resume) the stages `cfg.phases` on `data` into `run_dir` (`run_stages`);
    returns the training summary."""
    return run_stages(data, cfg, run_dir, resume, threads, log_every, command).summary


def run_stages(
    data: FitData | None,
    cfg: RunConfig,
    run_dir: Path,
    resume: bool = False,
    threads: int | None = None,
    log_every: int = 100,
    command: dict | None = None,
    data_path: Path | None = None,
) -> FitOutcome:
    """Run the stages `cfg.phases` on `data` into `run_dir`: train (or resume) those that train
    (Phase 1, then Phase 2 from its model; the Phase 1 checkpoint is kept as
    ``phase1.safetensors``) with a final evaluation, then build what the others build (Phase 3's
    language field, from the dataset in `data_path`, default `data`'s; `data` may be None when
    no selected stage trains). Holds the run folder's lock throughout; `command` (the
    command-line settings behind `cfg`, see `sync4d.pipeline.record`) goes into the run record.
    Raises `FitInterrupted` after Ctrl-C, SIGTERM or SIGHUP in training, with the last state
    saved. Reports what happens as `sync4d.events` (silent without a subscriber; the command
    line subscribes `sync4d.terminal.TerminalRenderer`)."""
    stages = stages_for(parse_phases(cfg.phases))
    p1 = cfg.phase1
    if not (math.isfinite(p1.near) and p1.near > 0):
        raise ConfigError(f"near: must be a finite distance > 0 (world units), got {p1.near}")
    with RunLock(run_dir, "fit"), StopSignals() as stop, event_log(run_dir):
        try:
            fit = FitState(cfg, run_dir, n_threads=0, threads=threads,
                           data_path=data.path if data is not None else data_path)  # fmt: skip
            training = [s for s in stages if isinstance(s, TrainingStage)]
            summary = None
            if training:
                summary = _train(fit, data, training, resume, log_every, command or {}, stop)
            for stage in stages:
                if not isinstance(stage, TrainingStage):  # it builds on the trained model
                    stage.start(fit)
                    emit(Skipped.of(stage.name, stage.counts(fit)))
            return FitOutcome(run_dir, summary, fit.built)
        except KeyboardInterrupt:  # between the loops: the last checkpoint is on disk
            if data is None:
                raise
            record = {"data": str(data.path.resolve()), "embedded": data.embedded}
            emit(Interrupted(str(run_dir / CHECKPOINT_NAME), continue_command(run_dir, record)))
            raise FitInterrupted from None


@contextlib.contextmanager
def event_log(run_dir: Path) -> Iterator[None]:
    """The events emitted while the block runs, as JSON lines in the run's ``events.jsonl``
    (appended: a resumed run, or its language field built later, continues the file)."""
    log = EventLog(run_dir / EVENTS_FILE)
    try:
        with subscribe(log):
            yield
    finally:
        log.close()


def _train(
    fit: FitState,
    data: FitData,
    training: list[TrainingStage],
    resume: bool,
    log_every: int,
    command: dict,
    stop: StopSignals,
) -> dict:
    """Train the `training` stages in turn (from scratch, from the run's checkpoint, or
    resuming it), then evaluate; the fit's summary."""
    cfg, run_dir = fit.cfg, fit.run_dir
    p1 = cfg.phase1
    fit.scene = data.scene
    fit.n_threads = n_threads = set_threads(fit.threads)
    ckpt = fit.checkpoint
    run_info = {
        "data": str(data.path.resolve()),
        "embedded": data.embedded,
        "scene": fit.scene.name,
        "dataset": dataset_fingerprint(fit.scene),
        "resolution_scale": cfg.resolution_scale,
        "test_split": cfg.test_split,
        "config": dataclasses.asdict(cfg),
        "command": command,
        "threads": n_threads,
    }
    kind = checkpoint_kind(ckpt)
    first, last = training[0], training[-1]
    if kind is not None and (resume or not first.fresh):  # continuing the stored run
        fit.train_seconds = float(read_checkpoint(ckpt)[1].get("run", {}).get("train_seconds",
                                                                             0.0))  # fmt: skip
    owner = stage_of_kind(kind) if kind is not None else None
    if owner is not None and owner.phase > last.phase:
        raise ConfigError(f"{ckpt} is a Phase {owner.phase} checkpoint; Phase {last.phase} "
                          "cannot continue it")  # fmt: skip
    if resume and owner is not None:
        fit.trainer = resume_trainer(ckpt, fit.scene, p1, n_threads, owner.iterations(cfg),
                                     cfg.phase2, near=p1.near)  # fmt: skip
        emit(Resumed(str(ckpt), fit.trainer.iteration))
    elif first.fresh:
        first.start(fit)
    elif kind is None:
        raise ConfigError(
            f"{run_dir}: Phase {first.phase} alone needs the run's Phase 1 checkpoint "
            f"({CHECKPOINT_NAME}); run with phases=1,{first.phase} or fit Phase 1 first"
        )
    write_text_atomic(run_dir / RUN_FILE, json.dumps(run_info, indent=2) + "\n")
    extra = {**run_info, "cameras": camera_records(fit.scene)}
    metrics_log = (run_dir / METRICS_FILE).open("a")
    test_frames = fit.scene.test or fit.scene.train
    periodic = test_frames
    if cfg.eval_frames and len(test_frames) > cfg.eval_frames:
        step = len(test_frames) / cfg.eval_frames
        periodic = [test_frames[int(i * step)] for i in range(cfg.eval_frames)]
    test_cache: dict[str, torch.Tensor] = {}

    def target(i: int, frame) -> torch.Tensor:
        key = str(frame.image_path)
        if key not in test_cache:
            test_cache[key] = torch.from_numpy(frame.load_image(cfg.phase1.background))
        return test_cache[key]

    def log(record: dict) -> None:
        metrics_log.write(json.dumps(record) + "\n")
        metrics_log.flush()

    wall0 = time.perf_counter()
    loop = dict(cfg=cfg, ckpt=ckpt, extra=extra, log=log, periodic=periodic, target=target,
                n_threads=n_threads, log_every=log_every, stop=stop)  # fmt: skip
    interrupted = False
    try:
        for stage in training:
            if interrupted:
                break
            if fit.trainer is not None and stage_of_kind(fit.trainer.kind).phase > stage.phase:
                continue  # the run is past this stage (a resumed later stage)
            if not stage.owns(fit.trainer):
                t0 = time.perf_counter()
                stage.start(fit)
                fit.train_seconds += time.perf_counter() - t0  # its set-up (Phase 2's fits)
            stage.before_loop(fit)
            fit.train_seconds, interrupted = _train_loop(
                fit.trainer, stage.iterations(cfg), desc=stage.task,
                train_seconds=fit.train_seconds, **loop,
            )  # fmt: skip
            emit(Skipped.of(stage.name, stage.counts(fit)))
            if not interrupted:
                emit(PhaseDone(stage.name, _phase_summary(fit.trainer, fit.train_seconds)))
        trainer = fit.trainer
        if interrupted:
            emit(Interrupted(str(ckpt), continue_command(run_dir, run_info), trainer.iteration))
            raise FitInterrupted
        summary = with_backgrounds(run_dir, trainer.model, fit.scene, cfg.phase1.background,
                                   n_threads)  # fmt: skip
        owner = stage_of_kind(trainer.kind)
        owner.finish(fit, summary)
        summary.update(
            {"iterations": trainer.iteration, "train_seconds": fit.train_seconds,
             "wall_seconds": time.perf_counter() - wall0,
             "gaussians": trainer.model.num_gaussians,
             "skipped": static_skip_counts(trainer.model), "peak_rss_mib": peak_rss_mib()}
        )  # fmt: skip
        if owner.summary_counts:
            summary[owner.summary_counts] = owner.counts(fit)
        log({"iteration": trainer.iteration, "train_seconds": fit.train_seconds,
             "final": summary})  # fmt: skip
        emit(PhaseDone("fit", _fit_summary(summary, run_dir)))
    finally:
        metrics_log.close()
    return summary


def peak_rss_mib() -> float | None:
    """The largest resident memory of this process so far, MiB (`getrusage`'s ``ru_maxrss``:
    KiB on Linux, bytes on macOS); None where the platform has no `resource` module."""
    try:
        import resource
    except ImportError:  # Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0), 1)


def _fit_summary(summary: dict, run_dir: Path) -> FitSummary:
    """The numbers of the `PhaseDone("fit")` event: test metrics, Gaussians, iterations,
    training seconds, and Phase 2's rigid share, shuffle ratio and assignment."""
    keys = ("psnr", "ssim", "lpips", "gaussians", "iterations", "train_seconds")
    scores = list((summary.get("backgrounds") or {}).items())
    background, backgrounds = None, None
    if scores:  # the run's own background first (`with_backgrounds`), then the others
        background = scores[0][0]
        backgrounds = tuple(BackgroundScore(name, Scores(**m)) for name, m in
                            dict(scores[1:]).items())  # fmt: skip
    phase2 = None
    if "phase2" in summary:
        d = summary["phase2"]
        phase2 = Phase2Brief(d["rigid_share"], d["shuffle_ratio"], len(d["objects"]),
                             d["assignment"])  # fmt: skip
    return FitSummary(*(summary.get(k) for k in keys), run_dir=str(run_dir),
                      background=background, backgrounds=backgrounds, phase2=phase2)


def _phase_summary(trainer: Phase1Trainer, train_seconds: float) -> LoopSummary:
    """The numbers of a `PhaseDone` event at the end of a phase's loop."""
    return LoopSummary(trainer.iteration, train_seconds, trainer.model.num_gaussians)
