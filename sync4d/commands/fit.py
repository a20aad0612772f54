"""``python -m sync4d fit [DATA] --out runs/NAME``: Phase 1 then Phase 2 training (``phases``)
into a run folder (`sync4d.runs.run_fit`), then the test metrics and Phase 2's diagnostics.

Without DATA it trains on the embedded synthetic scene (generated once into a cache folder).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sync4d.config import (
    ConfigError,
    RunConfig,
    apply_overrides,
    load_config,
    parse_phases,
    with_budget,
)
from sync4d.data import DatasetError, load_scene
from sync4d.progress import format_duration
from sync4d.runs import (
    CHECKPOINT_NAME,
    METRICS_FILE,
    PHASE1_CHECKPOINT_NAME,
    PHASE2_FILE,
    TRAJECTORY_PLOT,
    CheckpointError,
    FitInterrupted,
    resolve_data,
    restart_phase2,
    run_fit,
)

__all__ = ["main"]


def _load(args: argparse.Namespace) -> tuple[Path, RunConfig]:
    data, default_cfg = resolve_data(args.data)
    overrides = list(args.set or [])
    if args.resolution_scale is not None:
        overrides.append(f"resolution_scale={args.resolution_scale}")
    if getattr(args, "phases", None) is not None:
        overrides.append(f"phases={args.phases}")
    cfg = load_config(args.config or default_cfg)
    if args.iters is not None:  # scale the file's schedule; explicit overrides still win
        cfg = with_budget(cfg, args.iters)
    return data, apply_overrides(cfg, overrides)


def main(args: argparse.Namespace) -> int:
    """Run `fit` with parsed `args`; the exit status."""
    try:
        data, cfg = _load(args)
        run_dir = Path(args.out) if args.out else Path("runs") / data.name
        ckpt = run_dir / CHECKPOINT_NAME
        if args.resume and not ckpt.exists():
            print(f"fit: {ckpt}: no checkpoint to resume from", file=sys.stderr)
            return 2
        phase2_only = parse_phases(cfg.phases) == (2,)
        if ckpt.exists() and not (args.resume or args.force or phase2_only):
            print(
                f"fit: {run_dir} already holds a run; pass --resume to continue it, --force "
                "to start over or --phases 2 to redo Phase 2 from its Phase 1 checkpoint",
                file=sys.stderr,
            )
            return 2
        if phase2_only and not args.resume:
            restart_phase2(run_dir)
        elif args.force and not args.resume:
            for name in (CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, METRICS_FILE, PHASE2_FILE,
                         TRAJECTORY_PLOT):  # fmt: skip
                (run_dir / name).unlink(missing_ok=True)
        scene = load_scene(data, cfg.resolution_scale, cfg.test_split)
        print(
            f"fit: {scene.name}: {len(scene.train)} train / {len(scene.test)} test frames at "
            f"{scene.train[0].camera.width}x{scene.train[0].camera.height}, "
            f"{cfg.phase1.iterations} iterations -> {run_dir}",
            file=sys.stderr,
        )
        summary = run_fit(scene, cfg, run_dir, data, args.resume, args.threads)
    except (ConfigError, DatasetError, CheckpointError) as e:
        print(f"fit: {e}", file=sys.stderr)
        return 2
    except FitInterrupted:
        return 130
    print(
        f"fit: done in {format_duration(summary['train_seconds'])} of training: test PSNR "
        f"{summary['psnr']:.2f} dB, SSIM {summary['ssim']:.4f}, LPIPS "
        f"{'n/a' if summary['lpips'] is None else format(summary['lpips'], '.4f')}, "
        f"{summary['gaussians']} Gaussians; run in {run_dir}"
    )
    if "phase2" in summary:
        d = summary["phase2"]
        print(
            f"fit: Phase 2: mean rigid share {d['rigid_share']:.3f}, shuffle ratio "
            f"{d['shuffle_ratio']:.2f}, {len(d['objects'])} labels ({d['assignment']})"
        )
    return 0
