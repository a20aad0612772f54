"""``python -m sync4d fit [DATA] --out runs/NAME``: Phase 1 then Phase 2 training (``phases``)
into a run folder (`sync4d.pipeline.run_fit`), then the test metrics and Phase 2's diagnostics.
What the pipeline reports (`sync4d.events`) is printed by `sync4d.progress.TerminalRenderer`.

Without DATA it trains on the embedded synthetic scene (generated once into a cache folder).
The run is always ``--out RUN``, also when fit continues it (``--resume``), redoes Phase 2
(``--phases 2``) or builds its language field (``--phases 3``). ``fit RUN --phases 3`` (or
``--phases 2``, ``--resume``), the spelling before, still works for one release, with a note.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import sys
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
from sync4d.data import DatasetError, load_scene
from sync4d.data.synthetic import default_scene_dir, ensure_default_scene
from sync4d.files import LOCK_FILE, RunBusy, RunLock, WriteFailed
from sync4d.phase3.encoders.encoder import EncoderError
from sync4d.phase3.store import FieldError
from sync4d.pipeline import FitInterrupted, TrainingDiverged, restart_phase2, run_fit
from sync4d.pipeline.phase3 import build_phase3, phase3_config
from sync4d.pipeline.record import (
    CADENCE_KEYS,
    config_differences,
    dataset_differences,
    read_record,
    recorded_config,
)
from sync4d.progress import TerminalRenderer, format_duration
from sync4d.runs import (
    CHECKPOINT_NAME,
    EVAL_FILE,
    FIELD_DIR,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    RENDERS_DIR,
    RUN_FILE,
    TRAJECTORY_PLOT,
    CheckpointError,
    RunError,
    checkpoint_kind,
)
from sync4d.watchdog import NonFinite

__all__ = ["main"]


def _overrides(args: argparse.Namespace) -> list[str]:
    """The command line's settings as `key=value` overrides, in the order they apply."""
    overrides = list(args.set or [])
    if args.resolution_scale is not None:
        overrides.append(f"resolution_scale={args.resolution_scale}")
    if getattr(args, "phases", None) is not None:
        overrides.append(f"phases={args.phases}")
    if getattr(args, "encoder", None) is not None:
        overrides.append(f"phase3.encoder={args.encoder}")
    return overrides


def _fresh_config(args: argparse.Namespace) -> RunConfig:
    """The config of a new run: --config (default: the shipped synthetic config without DATA,
    the paper's values with it), scaled by --iters, then --set, --resolution-scale, --phases."""
    default = None if args.data else repo_configs() / "synthetic.toml"
    cfg = load_config(args.config or default)
    if args.iters is not None:  # scale the file's schedule; explicit overrides still win
        cfg = with_budget(cfg, args.iters)
    return apply_overrides(cfg, _overrides(args))


def _continued_config(
    args: argparse.Namespace, stored: RunConfig, kind: str | None, restart: bool, source: Path
) -> RunConfig:
    """The run's stored config with the command line's settings applied. On --resume only the
    phases' lengths (`--iters N` continues the checkpoint's phase to N) and the cadence keys may
    change; `--phases 2` (`restart`) may also change Phase 2's settings. Anything else the
    command line changes is refused, naming each difference."""
    cfg = load_config(args.config) if args.config else stored
    if args.iters is not None:
        if restart:
            cfg = dataclasses.replace(cfg, phase2=phase2_budget(cfg.phase2, args.iters))
        elif args.config:
            cfg = with_budget(cfg, args.iters)
        elif kind == "sync4d.phase2":
            cfg = dataclasses.replace(
                cfg, phase2=dataclasses.replace(cfg.phase2, iterations=args.iters)
            )
        else:
            cfg = dataclasses.replace(
                cfg, phase1=dataclasses.replace(cfg.phase1, iterations=args.iters)
            )
    cfg = apply_overrides(cfg, _overrides(args))
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
            print(f"fit: {k}: {a} -> {b}", file=sys.stderr)
    return cfg


def _continued_data(args: argparse.Namespace, record: dict, run_dir: Path) -> tuple[Path, bool]:
    """The dataset of a continued run (DATA if given, else the recorded one) and whether it is
    the embedded synthetic scene."""
    recorded = record.get("data")
    embedded = bool(record.get("embedded", recorded == str(default_scene_dir().resolve())))
    if args.data is not None:
        return Path(args.data), embedded and Path(args.data).resolve() == Path(recorded).resolve()
    if embedded:
        return ensure_default_scene(), True
    if recorded is None or not Path(recorded).exists():
        raise RunError(
            f"{run_dir}: the run's dataset ({recorded}) is not there any more; pass its new "
            "path as DATA"
        )
    return Path(recorded), False


def _clear(run_dir: Path) -> None:
    """Remove a run's results (--force)."""
    for name in (CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, METRICS_FILE, PHASE2_FILE,
                 TRAJECTORY_PLOT, EVAL_FILE, RUN_FILE):  # fmt: skip
        (run_dir / name).unlink(missing_ok=True)
    for extra in run_dir.glob("eval-*.json"):
        extra.unlink()
    shutil.rmtree(run_dir / RENDERS_DIR, ignore_errors=True)
    shutil.rmtree(run_dir / FIELD_DIR, ignore_errors=True)


def _is_run(path: Path) -> bool:
    """Whether `path` is a run folder (it holds a run record or a checkpoint)."""
    return (path / RUN_FILE).is_file() or (path / CHECKPOINT_NAME).is_file()


def _extends_a_run(args: argparse.Namespace) -> bool:
    """Whether the command line continues or extends an existing run: --resume, or --phases
    without Phase 1 (2, 2,3 or 3)."""
    try:
        return args.resume or (args.phases is not None and 1 not in parse_phases(args.phases))
    except ConfigError:
        return False


def main(args: argparse.Namespace) -> int:
    """Run `fit` with parsed `args`; the exit status."""
    if args.resume and args.force:
        print("fit: --resume continues RUN and --force deletes it; pass one of them",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.out is None and args.data and _is_run(Path(args.data)) and _extends_a_run(args):
        args.out, args.data = args.data, None  # `fit RUN --phases 3`: RUN, not a dataset
        print("fit: `fit RUN --phases ...` is now `fit --out RUN --phases ...` (the old "
              "spelling goes after this release)", file=sys.stderr)  # fmt: skip
    name = Path(args.data).name if args.data else default_scene_dir().name
    run_dir = Path(args.out) if args.out else Path("runs") / name
    created = not run_dir.exists()
    try:
        fresh = _fresh_config(args)
        with RunLock(run_dir, "fit"), TerminalRenderer().installed():
            return _fit(args, run_dir, fresh)
    except (ConfigError, DatasetError, CheckpointError, RunError, RunBusy, WriteFailed,
            EncoderError, FieldError) as e:  # fmt: skip
        print(f"fit: {e}", file=sys.stderr)
        return 2
    except TrainingDiverged as e:
        print(f"fit: {e}", file=sys.stderr)
        return 3
    except NonFinite as e:  # outside a training loop: the refinement, Phase 3's solve
        print(f"fit: {e}. Nothing was saved from it: the run keeps its last good checkpoint "
              "(and no new language field).", file=sys.stderr)  # fmt: skip
        return 3
    except FitInterrupted:
        return 130
    finally:
        if created and run_dir.is_dir() and {p.name for p in run_dir.iterdir()} <= {LOCK_FILE}:
            (run_dir / LOCK_FILE).unlink(missing_ok=True)
            os.rmdir(run_dir)  # a command that failed before writing anything leaves nothing


def _fit(args: argparse.Namespace, run_dir: Path, fresh: RunConfig) -> int:
    ckpt = run_dir / CHECKPOINT_NAME
    kind = checkpoint_kind(ckpt)
    if args.resume and kind is None:
        raise RunError(f"{ckpt}: no checkpoint to resume from")
    phases = parse_phases(fresh.phases)
    if phases == (3,):
        return _phase3_only(args, run_dir, kind)
    restart = phases[0] == 2 and not args.resume
    if kind is not None and not (args.resume or args.force or restart):
        raise RunError(
            f"{run_dir} already holds a run; pass --resume to continue it, --force to start "
            "over or --phases 2 to redo Phase 2 from its Phase 1 checkpoint"
        )
    invocation = {"data": args.data, "config": args.config, "set": list(args.set or []),
                  "iters": args.iters, "resolution_scale": args.resolution_scale,
                  "phases": args.phases, "resume": args.resume, "force": args.force}  # fmt: skip
    if kind is not None and not args.force:  # continue the recorded run
        record = read_record(run_dir)
        source = run_dir / RUN_FILE
        data, embedded = _continued_data(args, record, run_dir)
        cfg = _continued_config(args, recorded_config(record, run_dir), kind, restart, source)
        scene = load_scene(data, cfg.resolution_scale, cfg.test_split)
        differs = dataset_differences(record.get("dataset", {}), scene)
        if differs:
            raise RunError(
                f"{data} is not the dataset of the run in {run_dir} "
                f"({record.get('data')}): {'; '.join(differs)}. Pass the run's dataset, or "
                "start a new run (--force, or another --out)"
            )
        history = list(record.get("command", {}).get("invocations", []))
        if restart:
            restart_phase2(run_dir)
    else:
        if args.force:
            _clear(run_dir)
        cfg = fresh
        if args.data is None:
            print("fit: no dataset given; using the embedded synthetic scene", file=sys.stderr)
        data, embedded = (Path(args.data), False) if args.data else (ensure_default_scene(), True)
        scene = load_scene(data, cfg.resolution_scale, cfg.test_split)
        history = []
    command = {"embedded": embedded, "invocations": [*history, invocation]}
    print(
        f"fit: {scene.name}: {len(scene.train)} train / {len(scene.test)} test frames at "
        f"{scene.train[0].camera.width}x{scene.train[0].camera.height}, "
        f"{cfg.phase1.iterations} iterations -> {run_dir}",
        file=sys.stderr,
    )
    summary = run_fit(scene, cfg, run_dir, data, args.resume, args.threads, command=command)
    print(
        f"fit: done in {format_duration(summary['train_seconds'])} of training: test PSNR "
        f"{summary['psnr']:.2f} dB, SSIM "
        f"{'n/a' if summary['ssim'] is None else format(summary['ssim'], '.4f')}, LPIPS "
        f"{'n/a' if summary['lpips'] is None else format(summary['lpips'], '.4f')}, "
        f"{summary['gaussians']} Gaussians; run in {run_dir}"
    )
    if "phase2" in summary:
        d = summary["phase2"]
        print(
            f"fit: Phase 2: mean rigid share {d['rigid_share']:.3f}, shuffle ratio "
            f"{d['shuffle_ratio']:.2f}, {len(d['objects'])} labels ({d['assignment']})"
        )
    if 3 in parse_phases(cfg.phases):
        _build_phase3(run_dir, cfg.phase3, args.threads, data)
    return 0


def _phase3_only(args: argparse.Namespace, run_dir: Path, kind: str | None) -> int:
    """`fit --out RUN --phases 3`: the language field of RUN's Phase 2 checkpoint, with the run's
    recorded Phase 3 settings, then --config's, then --set phase3.* and --encoder."""
    if kind != "sync4d.phase2":
        raise RunError(
            f"{run_dir / CHECKPOINT_NAME}: --phases 3 needs a Phase 2 checkpoint (found "
            f"{kind or 'none'}); run fit with --phases 2 (or 1,2) first"
        )
    if args.resume or args.force or args.iters is not None:
        raise ConfigError("--phases 3 builds the language field of a finished Phase 2 run; "
                          "--resume, --force and --iters do not apply to it")  # fmt: skip
    others = [s for s in args.set or [] if not s.startswith("phase3.")]
    if others or args.resolution_scale is not None:
        raise ConfigError(
            f"--phases 3 only builds the language field: settings other than phase3.* do not "
            f"apply ({', '.join(others) or '--resolution-scale'}); drop them"
        )
    overrides = [s for s in _overrides(args) if not s.startswith("phases=")]
    cfg3 = phase3_config(run_dir, args.config, overrides)
    data = Path(args.data) if args.data else None
    _build_phase3(run_dir, cfg3, args.threads, data)
    return 0


def _build_phase3(run_dir: Path, cfg3, threads: int | None, data: Path | None) -> None:
    """Build and save the language field of the Phase 2 run in `run_dir`; print a summary."""
    from sync4d.phase3 import load_encoder
    from sync4d.phase3.build import skip_report

    encoder = load_encoder(cfg3.encoder or None)
    print(f"fit: Phase 3 (language field) with the {encoder.kind} encoder ({encoder.dim}-d"
          f"{', closed-vocabulary' if encoder.closed_vocabulary else ''}) ...",
          file=sys.stderr)  # fmt: skip
    built = build_phase3(run_dir, cfg3, threads=threads, data=data, encoder=encoder)
    field, t = built.field, built.field.timings
    print(
        f"fit: Phase 3: {len(field.labels)} objects x {len(field.times)} frames, "
        f"{int(t['crops'])} crops ({100 * field.observed.mean():.0f} % observed), built in "
        f"{t['total_s']:.1f} s (observe {t['observe_s']:.1f}, encode {t['encode_s']:.1f}); "
        f"field in {built.folder}"
    )
    print(skip_report(field), file=sys.stderr)
