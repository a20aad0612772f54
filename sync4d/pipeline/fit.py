"""The fit loop: Phase 1, then Phase 2 from its model (``phases``), into a run folder, with
periodic test evaluation, atomic checkpoints every K iterations and on Ctrl-C or SIGTERM,
resume from the last checkpoint, and a final evaluation and Phase 2 diagnostics. It prints
nothing: it reports progress and results as `sync4d.events`, which the command line renders.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import shutil
import signal
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from sync4d import watchdog
from sync4d.config import ConfigError, RunConfig, parse_phases, repo_configs
from sync4d.data import Scene, load_scene
from sync4d.events import (
    Advanced,
    Assigned,
    DatasetChosen,
    Evaluated,
    EventLog,
    Finished,
    Interrupted,
    MotionDiagnosed,
    NothingMoves,
    Phase2Starting,
    PhaseDone,
    Resumed,
    ScaleAdvice,
    Skipped,
    Started,
    Wrote,
    emit,
    subscribe,
)
from sync4d.files import RunLock, write_atomic, write_text_atomic
from sync4d.phase1.init import initial_model, scene_extent, with_initial_points
from sync4d.phase1.motion.per_gaussian import static_skip_counts
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.phase2.diagnostics import diagnostics
from sync4d.phase2.strategy import MotionStrategy
from sync4d.phase2.trainer import phase2_from_state, phase2_trainer
from sync4d.pipeline.evaluate import evaluate_frames, summarize, with_backgrounds
from sync4d.pipeline.record import continue_command, dataset_fingerprint
from sync4d.pipeline.stop import StopSignals
from sync4d.report import plot_object_trajectories
from sync4d.runs.checkpoint import (
    camera_records,
    checkpoint_kind,
    load_model,
    read_checkpoint,
    save_checkpoint,
    state_errors,
    write_checkpoint,
)
from sync4d.runs.names import (
    CHECKPOINT_NAME,
    EVENTS_FILE,
    FIELD_DIR,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    RUN_FILE,
    TRAJECTORY_PLOT,
)

__all__ = [
    "FitData",
    "FitInterrupted",
    "TrainingDiverged",
    "event_log",
    "length_advice",
    "resolve_data",
    "restart_phase2",
    "resume_trainer",
    "run_fit",
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


@dataclass(frozen=True)
class FitData:
    """A run's dataset: its folder `path`, the `scene` loaded from it, and whether it is the
    embedded synthetic scene (`embedded`, kept in the run record)."""

    path: Path
    scene: Scene
    embedded: bool = False

    @classmethod
    def load(cls, path: str | Path, cfg: RunConfig, embedded: bool = False) -> FitData:
        """The dataset in `path`, loaded at `cfg`'s resolution scale and test split."""
        path = Path(path)
        return cls(path, load_scene(path, cfg.resolution_scale, cfg.test_split), embedded)


class FitInterrupted(Exception):
    """Training stopped by Ctrl-C, SIGTERM or SIGHUP after saving its checkpoint."""


#: The scene extent (3DGS: 1.1 times the cameras' radius) the absolute lengths' defaults are
#: for: D-NeRF's scenes (cameras 4.03 units from the objects) and the embedded one.
REFERENCE_EXTENT = 4.4
#: Scenes whose extent is off the reference by more than this factor get `length_advice`.
LENGTH_TOLERANCE = 10.0


def length_advice(extent: float, p1) -> ScaleAdvice | None:
    """The advice for a scene whose size is far from the one the absolute lengths (`near`,
    `init_scale`, `deform.scale_position`, `deform.position_unit`) are for: the settings that
    scale them to it, or None
    when the scene is within `LENGTH_TOLERANCE` of `REFERENCE_EXTENT` or they were set already.
    Measured (docs/results/stability.md): the embedded scene scaled by 1e-3 loses 6.3 dB with
    the defaults, and matches the unscaled one with the lengths scaled alike."""
    ratio = extent / REFERENCE_EXTENT
    d = p1.deform
    lengths = (p1.near, p1.init_scale, d.scale_position, d.position_unit)
    defaults = lengths == (0.01, 0.02, 0.1, 1.0)
    if not defaults or 1.0 / LENGTH_TOLERANCE <= ratio <= LENGTH_TOLERANCE:
        return None
    return ScaleAdvice(ratio, extent, REFERENCE_EXTENT, {
        "phase1.near": 0.01 * ratio, "phase1.init_scale": 0.02 * ratio,
        "phase1.deform.scale_position": 0.1 * ratio, "phase1.deform.position_unit": ratio,
    })  # fmt: skip


class TrainingDiverged(RuntimeError):
    """A NaN or inf stopped training (`sync4d.watchdog`); the message says where, what the run
    folder keeps and what to try."""


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
                emit(Advanced(desc, it, {"loss": ema.get("loss", math.nan),
                                         "psnr": ema.get("psnr", math.nan),
                                         "gaussians": trainer.model.num_gaussians,
                                         **({"rho": ema["rho"]} if "rho" in ema else {})}))
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
    """Rebuild the trainer (`Phase1Trainer`; for a Phase 2 checkpoint with the motion strategy
    plugged in, with `phase2`'s settings) exactly as it was when `path` was saved
    (`total_iterations` extends or shortens the run; the learning-rate schedules follow the
    new length; `near` replaces the stored near plane)."""
    path = Path(path)
    tensors, meta = read_checkpoint(path)
    kw = dict(config=config, total_iterations=total_iterations, threads=threads, near=near)
    with state_errors(path):
        if meta.get("kind") == "sync4d.phase2":
            return phase2_from_state(tensors, meta, scene, phase2=phase2, **kw).trainer
        return Phase1Trainer.from_state(tensors, meta, scene, **kw)


def run_fit(
    data: FitData,
    cfg: RunConfig,
    run_dir: Path,
    resume: bool = False,
    threads: int | None = None,
    log_every: int = 100,
    command: dict | None = None,
) -> dict:
    """Train (or resume) the phases `cfg.phases` on `data` into `run_dir`: Phase 1, then Phase 2
    from its model (the Phase 1 checkpoint is kept as ``phase1.safetensors``); returns the final
    summary (test metrics, and Phase 2's diagnostics when it ran). Holds the run folder's lock
    throughout; `command` (the command-line settings behind `cfg`, see `sync4d.pipeline.record`)
    goes into the run record. Raises `FitInterrupted` after Ctrl-C, SIGTERM or SIGHUP, with
    the last state saved. Reports what happens as `sync4d.events` (silent without a
    subscriber; the command line subscribes `sync4d.terminal.TerminalRenderer`)."""
    phases = parse_phases(cfg.phases)
    p1 = cfg.phase1
    if not (math.isfinite(p1.near) and p1.near > 0):
        raise ConfigError(f"near: must be a finite distance > 0 (world units), got {p1.near}")
    with RunLock(run_dir, "fit"), StopSignals() as stop, event_log(run_dir):
        try:
            return _run_fit(data, cfg, phases, run_dir, resume, threads, log_every,
                            command or {}, stop)  # fmt: skip
        except KeyboardInterrupt:  # between the loops: the last checkpoint is on disk
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


def _run_fit(
    data: FitData,
    cfg: RunConfig,
    phases: tuple[int, ...],
    run_dir: Path,
    resume: bool,
    threads: int | None,
    log_every: int,
    command: dict,
    stop: StopSignals,
) -> dict:
    p1 = cfg.phase1
    scene = data.scene
    n_threads = set_threads(threads)
    ckpt = run_dir / CHECKPOINT_NAME
    run_info = {
        "data": str(data.path.resolve()),
        "embedded": data.embedded,
        "scene": scene.name,
        "dataset": dataset_fingerprint(scene),
        "resolution_scale": cfg.resolution_scale,
        "test_split": cfg.test_split,
        "config": dataclasses.asdict(cfg),
        "command": command,
        "threads": n_threads,
    }
    kind = checkpoint_kind(ckpt)
    trainer: Phase1Trainer | None = None
    train_seconds = 0.0
    if kind is not None and (resume or 1 not in phases):  # continuing the stored run
        train_seconds = float(read_checkpoint(ckpt)[1].get("run", {}).get("train_seconds", 0.0))
    if kind == "sync4d.phase2" and 2 not in phases:
        raise ConfigError(f"{ckpt} is a Phase 2 checkpoint; Phase 1 cannot continue it")
    if resume and kind is not None:
        total = cfg.phase2.iterations if kind == "sync4d.phase2" else p1.iterations
        trainer = resume_trainer(ckpt, scene, p1, n_threads, total, cfg.phase2, near=p1.near)
        emit(Resumed(str(ckpt), trainer.iteration))
    elif 1 in phases:
        scene = with_initial_points(scene, p1, threads=torch.get_num_threads())
        model = initial_model(
            scene, p1.init_points, p1.sh_degree, p1.deform, p1.init_box_fraction, p1.seed,
            near=p1.near, init_scale=p1.init_scale,
        )  # fmt: skip
        advice = length_advice(scene_extent(scene), p1)
        if advice:
            emit(advice)
        trainer = Phase1Trainer(model, scene, p1, p1.iterations, threads=n_threads)
    elif kind is None:
        raise ConfigError(
            f"{run_dir}: Phase 2 alone needs the run's Phase 1 checkpoint ({CHECKPOINT_NAME}); "
            "run with phases=1,2 or fit Phase 1 first"
        )
    write_text_atomic(run_dir / RUN_FILE, json.dumps(run_info, indent=2) + "\n")
    extra = {**run_info, "cameras": camera_records(scene)}
    metrics_log = (run_dir / METRICS_FILE).open("a")
    test_frames = scene.test or scene.train
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
        if trainer is not None and _motion(trainer) is None and 1 in phases:
            train_seconds, interrupted = _train_loop(
                trainer, p1.iterations, desc="fit", train_seconds=train_seconds, **loop
            )
            emit(Skipped("phase1", phase1_skips(trainer)))
            if not interrupted:
                emit(PhaseDone("phase1", _phase_summary(trainer, train_seconds)))
        if not interrupted and 2 in phases:
            p2 = _motion(trainer)
            if p2 is None:
                t0 = time.perf_counter()
                p2 = _start_phase2(trainer, scene, cfg, run_dir, n_threads)
                trainer = p2.trainer
                train_seconds += time.perf_counter() - t0  # the assignment and refinement
            if p2.skip_loop(cfg.phase2.iterations):
                emit(NothingMoves(p2.assignment.num_objects))
            train_seconds, interrupted = _train_loop(
                trainer, cfg.phase2.iterations, desc="phase2", train_seconds=train_seconds,
                **loop,
            )  # fmt: skip
            emit(Skipped("phase2", p2.skip_counts()))
            if not interrupted:
                emit(PhaseDone("phase2", _phase_summary(trainer, train_seconds)))
        if interrupted:
            emit(Interrupted(str(ckpt), continue_command(run_dir, run_info), trainer.iteration))
            raise FitInterrupted
        summary = _finish(trainer, scene, cfg, run_dir, n_threads)
        summary.update(
            {"iterations": trainer.iteration, "train_seconds": train_seconds,
             "wall_seconds": time.perf_counter() - wall0,
             "gaussians": trainer.model.num_gaussians,
             "skipped": static_skip_counts(trainer.model), "peak_rss_mib": peak_rss_mib()}
        )  # fmt: skip
        if (p2 := _motion(trainer)) is not None:
            summary["phase2_skipped"] = p2.skip_counts()
        log({"iteration": trainer.iteration, "train_seconds": train_seconds, "final": summary})
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


def _fit_summary(summary: dict, run_dir: Path) -> dict:
    """The numbers of the `PhaseDone("fit")` event: test metrics, Gaussians, iterations,
    training seconds, and Phase 2's rigid share, shuffle ratio and assignment."""
    out = {k: summary.get(k) for k in ("psnr", "ssim", "lpips", "gaussians", "iterations",
                                       "train_seconds")}  # fmt: skip
    out["run_dir"] = str(run_dir)
    scores = list((summary.get("backgrounds") or {}).items())
    if scores:  # the run's own background first (`with_backgrounds`), then the others
        out["background"] = scores[0][0]
        out["backgrounds"] = dict(scores[1:])
    if "phase2" in summary:
        d = summary["phase2"]
        out["phase2"] = {"rigid_share": d["rigid_share"], "shuffle_ratio": d["shuffle_ratio"],
                         "objects": len(d["objects"]), "assignment": d["assignment"]}
    return out


def _phase_summary(trainer: Phase1Trainer, train_seconds: float) -> dict:
    """The numbers of a `PhaseDone` event at the end of a phase's loop."""
    return {"iteration": trainer.iteration, "train_seconds": train_seconds,
            "gaussians": trainer.model.num_gaussians}  # fmt: skip


def _motion(trainer: Phase1Trainer | None) -> MotionStrategy | None:
    """The Phase 2 motion strategy plugged into `trainer` (None: a Phase 1 trainer)."""
    plugins = [] if trainer is None else trainer.plugins
    return next((p for p in plugins if isinstance(p, MotionStrategy)), None)


def phase1_skips(trainer: Phase1Trainer) -> dict[str, int | float]:
    """What Phase 1 skipped in this process, for each switch that is on (the `Skipped` event's
    counts): D_theta on the Gaussians (control nodes carry the motion: ``nodes``,
    ``nodes_from``, ``nodes_added``, ``nodes_removed``) or on static Gaussians
    (`static_skip_counts`), pixels of the coarse iterations (``coarse_iterations``,
    ``coarse_scale``, ``pixels_saved``: a fraction), transparent Gaussians pruned after
    densification (``pruned``, ``prune_opacity``); ``gaussians`` the count now."""
    c = trainer.config
    out: dict[str, int | float] = {"gaussians": trainer.model.num_gaussians}
    out.update(trainer.model.motion_model.skip_counts(trainer))
    if c.coarse_iterations > 0 and c.coarse_scale < 1.0 and trainer.pixels:
        out.update(coarse_iterations=c.coarse_iterations, coarse_scale=c.coarse_scale,
                   pixels_saved=(trainer.coarse_full_pixels - trainer.coarse_pixels)
                   / trainer.pixels)  # fmt: skip
    if c.densify.prune_after_stop:
        out.update(pruned=trainer.densifier.pruned_transparent,
                   prune_opacity=c.densify.prune_opacity)  # fmt: skip
    return out


def _start_phase2(
    trainer: Phase1Trainer | None, scene: Scene, cfg: RunConfig, run_dir: Path, n_threads: int
) -> MotionStrategy:
    """Keep the Phase 1 checkpoint as ``phase1.safetensors`` and build Phase 2's trainer from
    its model (the assignment, M_phi's start and the photometric refinement run here);
    returns its motion strategy."""
    p1 = cfg.phase1
    ckpt = run_dir / CHECKPOINT_NAME
    kept = run_dir / PHASE1_CHECKPOINT_NAME
    write_atomic(kept, lambda tmp: shutil.copyfile(ckpt, tmp))
    model = trainer.model if trainer is not None else load_model(ckpt, p1.near)[0]
    emit(Phase2Starting(cfg.phase2.iterations, str(kept)))
    try:
        p2 = phase2_trainer(model, scene, p1, cfg.phase2, cfg.phase2.iterations, n_threads)
    except ValueError as e:  # bad assignment input
        raise ConfigError(str(e)) from None
    names = p2.assignment.names
    emit(Assigned(p2.assignment.source, p2.assignment.num_objects,
                  {str(names.get(k, k)): int(n) for k, n in p2.assignment.counts().items()}))
    return p2


def _finish(
    trainer: Phase1Trainer, scene: Scene, cfg: RunConfig, run_dir: Path, n_threads: int
) -> dict:
    """The final evaluation, and after Phase 2 its diagnostics and trajectory plot."""
    summary = with_backgrounds(run_dir, trainer.model, scene, cfg.phase1.background, n_threads)
    if (p2 := _motion(trainer)) is not None:
        diag = diagnostics(p2)
        export = p2.motion_export()
        cent = export["centroids"]
        diag["trajectories"] = {
            "times": export["times"].tolist(),
            "centroids": {str(k): cent[k].tolist() for k in range(len(cent))},
        }
        write_text_atomic(run_dir / PHASE2_FILE, json.dumps(diag, indent=2) + "\n")
        plot = plot_object_trajectories(
            export, p2.assignment.names, run_dir / TRAJECTORY_PLOT,
            f"{scene.name}: object centroids after Phase 2 ({diag['assignment']} assignment)",
        )  # fmt: skip
        summary["phase2"] = diag
        emit(MotionDiagnosed({k: v for k, v in diag.items() if k != "trajectories"}))
        emit(Wrote("fit", (str(run_dir / PHASE2_FILE), str(plot))))
    return summary


def restart_phase2(run_dir: Path) -> None:
    """Put the run's Phase 1 checkpoint back in place so Phase 2 starts over from it; the
    language field of the old Phase 2 goes (it describes a model that will not exist)."""
    ckpt = run_dir / CHECKPOINT_NAME
    kept = run_dir / PHASE1_CHECKPOINT_NAME
    if kept.exists():
        write_atomic(ckpt, lambda tmp: shutil.copyfile(kept, tmp))
    elif checkpoint_kind(ckpt) != "sync4d.phase1":
        raise ConfigError(
            f"{run_dir}: --phases 2 needs a Phase 1 checkpoint ({CHECKPOINT_NAME} or "
            f"{PHASE1_CHECKPOINT_NAME}); fit Phase 1 first"
        )
    shutil.rmtree(run_dir / FIELD_DIR, ignore_errors=True)
