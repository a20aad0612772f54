"""What `sync4d fit` asks of a run folder, and the resume policy that answers it.

A `FitRequest` is the command line's words as data (the dataset, the run folder, the config
file, the overrides, the phases, --resume / --force). `fit_request` decides what the request
means for the run folder and does it:

- a new run (or `--force`): the request's config (`fresh_config`) on its dataset, or the
  embedded scene;
- `--resume`: the run's recorded config and dataset, with only the phases' lengths and the
  cadence keys free to change (`continued_config`, `continued_data`); a dataset that is not
  the recorded one is refused (`pipeline.record.dataset_differences`);
- `--phases 2`: Phase 2 again from the run's Phase 1 checkpoint, Phase 2's settings free;
- `--phases 3` alone: the language field of a finished Phase 2 run (`fit_phase3_only`).

The dataset travels with its scene (`FitData`). The command parses and prints; everything
here reports through `sync4d.events`.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

from sync4d.config import (
    ConfigError,
    RunConfig,
    apply_overrides,
    load_config,
    parse_phases,
    phase2_budget,
    repo_configs,
    with_budget,
)
from sync4d.data.synthetic import default_scene_dir, ensure_default_scene
from sync4d.events import FitStarted, SettingChanged, emit
from sync4d.pipeline.fit import FitData, FitOutcome, resolve_data, restart_phase2, run_stages
from sync4d.pipeline.phase3 import phase3_run_config
from sync4d.pipeline.record import (
    CADENCE_KEYS,
    config_differences,
    dataset_differences,
    read_record,
    recorded_config,
)
from sync4d.pipeline.stages import TrainingStage, stages_for
from sync4d.runs import (
    CHECKPOINT_NAME,
    EVAL_FILE,
    EVENTS_FILE,
    FIELD_DIR,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    RENDERS_DIR,
    RUN_FILE,
    TRAJECTORY_PLOT,
    CheckpointKind,
    RunError,
    checkpoint_kind,
)

__all__ = ["FitData", "FitOutcome", "FitRequest", "clear_run", "continued_config",
           "continued_data", "fit_request", "fresh_config", "is_run"]  # fmt: skip


@dataclass(frozen=True)
class FitRequest:
    """`sync4d fit`'s command line as data: the dataset folder (None: the embedded scene, or
    the run's recorded one), the run folder, a config file or shipped config's name, the
    ``--set`` overrides, ``--iters``, ``--resolution-scale``, ``--phases``, ``--encoder``,
    ``--resume``, ``--force`` and the CPU threads."""

    run_dir: Path
    data: Path | None = None
    config: str | None = None
    settings: tuple[str, ...] = ()
    iters: int | None = None
    resolution_scale: float | None = None
    phases: str | None = None
    encoder: str | None = None
    resume: bool = False
    force: bool = False
    threads: int | None = None

    def overrides(self) -> list[str]:
        """The request's settings as `key=value` overrides, in the order they apply."""
        overrides = list(self.settings)
        if self.resolution_scale is not None:
            overrides.append(f"resolution_scale={self.resolution_scale}")
        if self.phases is not None:
            overrides.append(f"phases={self.phases}")
        if self.encoder is not None:
            overrides.append(f"phase3.encoder={self.encoder}")
        return overrides

    def invocation(self) -> dict:
        """The request as the run record keeps it (`command.invocations`)."""
        return {"data": None if self.data is None else str(self.data), "config": self.config,
                "set": list(self.settings), "iters": self.iters,
                "resolution_scale": self.resolution_scale, "phases": self.phases,
                "resume": self.resume, "force": self.force}  # fmt: skip


def fresh_config(req: FitRequest) -> RunConfig:
    """The config of a new run: `req.config` (default: the shipped synthetic config without a
    dataset, the paper's values with one), scaled by `req.iters`, then the overrides."""
    default = None if req.data else repo_configs() / "synthetic.toml"
    cfg = load_config(req.config or default)
    if req.iters is not None:  # scale the file's schedule; explicit overrides still win
        cfg = with_budget(cfg, req.iters)
    return apply_overrides(cfg, req.overrides())


def continued_config(req: FitRequest, stored: RunConfig, kind: str | None, restart: bool,
                     source: Path) -> RunConfig:  # fmt: skip
    """The run's stored config with the request's settings applied. On --resume only the
    phases' lengths (`iters` continues the checkpoint's phase to N) and the cadence keys may
    change; `--phases 2` (`restart`) may also change Phase 2's settings. Anything else the
    request changes is refused, naming each difference."""
    cfg = load_config(req.config) if req.config else stored
    length = None  # the continued phase's new length alone: set once the settings are checked
    if req.iters is not None:
        if restart:
            cfg = dataclasses.replace(cfg, phase2=phase2_budget(cfg.phase2, req.iters))
        elif req.config:
            cfg = with_budget(cfg, req.iters)
        else:
            length = "phase2" if kind == CheckpointKind.PHASE2 else "phase1"
    overrides = req.overrides()
    cfg = apply_overrides(cfg, overrides)
    if length is not None and not any(o.startswith(f"{length}.iterations=") for o in overrides):
        # After the checks: the run's windows (densification, warm-ups, starts) were set for
        # the length it started with, and a continued run that ends before one of them only
        # stops earlier; the rules that compare them with the length guard a new run's plan.
        section = dataclasses.replace(getattr(cfg, length), iterations=req.iters)
        cfg = dataclasses.replace(cfg, **{length: section})
    free = {*CADENCE_KEYS, "phase1.iterations", "phase2.iterations"}

    def allowed(key: str) -> bool:  # Phase 3 rebuilds its field: its settings are free
        return (key in free or key.startswith("phase3.")
                or (restart and (key == "phases" or key.startswith("phase2."))))  # fmt: skip

    diffs = config_differences(stored, cfg)
    bad = {k: v for k, v in diffs.items() if not allowed(k)}
    if bad:
        listed = "; ".join(f"{k}: the run has {a!r}, this command gives {b!r}"
                           for k, (a, b) in list(bad.items())[:6])  # fmt: skip
        more = f" and {len(bad) - 6} more" if len(bad) > 6 else ""
        what = "--phases 2 keeps" if restart else "--resume continues"
        raise ConfigError(
            f"{source}: {what} the run with its recorded settings, and this command contradicts "
            f"them: {listed}{more}. Drop those settings, or start a new run (--force, or "
            "another --out)"
        )
    for k, (a, b) in diffs.items():
        if k in free:
            emit(SettingChanged(k, a, b))
    return cfg


def continued_data(req: FitRequest, record: dict, run_dir: Path) -> tuple[Path, bool]:
    """The dataset of a continued run (the request's if given, else the recorded one) and
    whether it is the embedded synthetic scene."""
    recorded = record.get("data")
    embedded = bool(record.get("embedded", recorded == str(default_scene_dir().resolve())))
    if req.data is not None:
        return req.data, embedded and req.data.resolve() == Path(recorded).resolve()
    if embedded:
        return ensure_default_scene(), True
    if recorded is None or not Path(recorded).exists():
        raise RunError(
            f"{run_dir}: the run's dataset ({recorded}) is not there any more; pass its new "
            "path as DATA"
        )
    return Path(recorded), False


def clear_run(run_dir: Path) -> None:
    """Remove a run's results (--force)."""
    for name in (CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, METRICS_FILE, EVENTS_FILE,
                 PHASE2_FILE, TRAJECTORY_PLOT, EVAL_FILE, RUN_FILE):  # fmt: skip
        (run_dir / name).unlink(missing_ok=True)
    for extra in run_dir.glob("eval-*.json"):
        extra.unlink()
    shutil.rmtree(run_dir / RENDERS_DIR, ignore_errors=True)
    shutil.rmtree(run_dir / FIELD_DIR, ignore_errors=True)


def is_run(path: Path) -> bool:
    """Whether `path` is a run folder (it holds a run record or a checkpoint)."""
    return (path / RUN_FILE).is_file() or (path / CHECKPOINT_NAME).is_file()


def _continued(req: FitRequest, kind: str, restart: bool) -> tuple[RunConfig, FitData, list]:
    """The config, dataset and earlier invocations of the recorded run `req` continues."""
    run_dir = req.run_dir
    record = read_record(run_dir)
    path, embedded = continued_data(req, record, run_dir)
    cfg = continued_config(req, recorded_config(record, run_dir), kind, restart,
                           run_dir / RUN_FILE)  # fmt: skip
    data = FitData.load(path, cfg, embedded)
    differs = dataset_differences(record.get("dataset", {}), data.scene)
    if differs:
        raise RunError(
            f"{path} is not the dataset of the run in {run_dir} "
            f"({record.get('data')}): {'; '.join(differs)}. Pass the run's dataset, or "
            "start a new run (--force, or another --out)"
        )
    return cfg, data, list(record.get("command", {}).get("invocations", []))


def _builds_only(phases: str) -> bool:
    """Whether ``--phases`` selects no stage that trains (``3``: the language field alone)."""
    try:
        return not any(isinstance(s, TrainingStage) for s in stages_for(parse_phases(phases)))
    except ConfigError:
        return False  # the config's own check names the bad value


def fit_request(req: FitRequest, fresh: RunConfig | None = None) -> FitOutcome:
    """Do what `req` asks of its run folder (see the module's note): train or continue the
    phases, then build the language field when Phase 3 is among them. `fresh`: the config of
    a new run, when the caller already resolved it (`fresh_config(req)`)."""
    run_dir = req.run_dir
    ckpt = run_dir / CHECKPOINT_NAME
    kind = checkpoint_kind(ckpt)
    if req.resume and kind is None:
        raise RunError(f"{ckpt}: no checkpoint to resume from")
    if req.phases is not None and _builds_only(req.phases):  # the run's config, not a new one
        return fit_phase3_only(req, kind)
    fresh = fresh_config(req) if fresh is None else fresh
    first = stages_for(parse_phases(fresh.phases))[0]
    if not isinstance(first, TrainingStage):  # no stage trains: build on the run's model
        return fit_phase3_only(req, kind)
    restart = not first.fresh and not req.resume  # redo a later stage from the checkpoint
    if kind is not None and not (req.resume or req.force or restart):
        raise RunError(
            f"{run_dir} already holds a run; pass --resume to continue it, --force to start "
            "over or --phases 2 to redo Phase 2 from its Phase 1 checkpoint"
        )
    if kind is not None and not req.force:  # continue the recorded run
        cfg, data, history = _continued(req, kind, restart)
        if restart:
            restart_phase2(run_dir)
    else:
        if req.force:
            clear_run(run_dir)
        cfg = fresh
        path, _ = resolve_data(req.data)  # the config was chosen already (fresh_config)
        data = FitData.load(path, cfg, embedded=req.data is None)
        history = []
    command = {"invocations": [*history, req.invocation()]}
    scene, camera = data.scene, data.scene.train[0].camera
    emit(FitStarted(scene.name, len(scene.train), len(scene.test), camera.width, camera.height,
                    cfg.phase1.iterations, str(run_dir)))  # fmt: skip
    return run_stages(data, cfg, run_dir, req.resume, req.threads, command=command)


def fit_phase3_only(req: FitRequest, kind: str | None) -> FitOutcome:
    """`fit --out RUN --phases 3`: the language field of RUN's Phase 2 checkpoint, with the
    run's recorded Phase 3 settings, then the config file's, then ``phase3.*`` overrides and
    the encoder."""
    run_dir = req.run_dir
    if kind != CheckpointKind.PHASE2:
        raise RunError(
            f"{run_dir / CHECKPOINT_NAME}: --phases 3 needs a Phase 2 checkpoint (found "
            f"{kind or 'none'}); run fit with --phases 2 (or 1,2) first"
        )
    if req.resume or req.force or req.iters is not None:
        raise ConfigError("--phases 3 builds the language field of a finished Phase 2 run; "
                          "--resume, --force and --iters do not apply to it")  # fmt: skip
    others = [s for s in req.settings if not s.startswith("phase3.")]
    if others or req.resolution_scale is not None:
        raise ConfigError(
            f"--phases 3 only builds the language field: settings other than phase3.* do not "
            f"apply ({', '.join(others) or '--resolution-scale'}); drop them"
        )
    overrides = [s for s in req.overrides() if not s.startswith("phases=")]
    cfg = dataclasses.replace(phase3_run_config(run_dir, req.config, overrides), phases="3")
    return run_stages(None, cfg, run_dir, threads=req.threads, data_path=req.data)
