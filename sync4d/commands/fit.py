"""``python -m sync4d fit [DATA] --out runs/NAME``: Phase 1 training with a progress bar,
periodic test evaluation, atomic checkpoints every K iterations and on Ctrl-C, ``--resume``,
and a final evaluation (PSNR, SSIM, LPIPS) written to ``RUN/eval.json``.

Without DATA it trains on the embedded synthetic scene (generated once into a cache folder).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import signal
import sys
import time
from pathlib import Path

import torch

from sync4d.checkpoint import camera_records, resume_trainer, save_checkpoint
from sync4d.config import ConfigError, RunConfig, apply_overrides, load_config, with_budget
from sync4d.data import DatasetError, Scene, load_scene
from sync4d.evaluate import evaluate_frames, summarize
from sync4d.progress import Progress, format_duration
from sync4d.train import Phase1Trainer, initial_model

__all__ = [
    "CHECKPOINT_NAME",
    "FitInterrupted",
    "RUN_FILE",
    "main",
    "repo_configs",
    "resolve_data",
    "run_fit",
]

#: File names inside a run directory.
CHECKPOINT_NAME = "checkpoint.safetensors"
RUN_FILE = "run.json"
METRICS_FILE = "metrics.jsonl"


def repo_configs() -> Path:
    """The repository's `configs/` folder (next to the package in a source checkout)."""
    return Path(__file__).resolve().parents[2] / "configs"


def _set_threads(threads: int | None) -> int:
    import os

    n = threads or len(os.sched_getaffinity(0))
    torch.set_num_threads(n)
    return n


def resolve_data(args: argparse.Namespace) -> tuple[Path, Path | None]:
    """Dataset folder and default config: the user's, or the embedded synthetic scene."""
    if args.data is not None:
        return Path(args.data), None
    from sync4d.data.synthetic import ensure_default_scene

    print("fit: no dataset given; using the embedded synthetic scene", file=sys.stderr)
    root = ensure_default_scene()
    cfg = repo_configs() / "synthetic.toml"
    return root, cfg if cfg.exists() else None


def _load(args: argparse.Namespace) -> tuple[Path, RunConfig]:
    data, default_cfg = resolve_data(args)
    overrides = list(args.set or [])
    if args.resolution_scale is not None:
        overrides.append(f"resolution_scale={args.resolution_scale}")
    cfg = load_config(args.config or default_cfg)
    if args.iters is not None:  # scale the file's schedule; explicit overrides still win
        cfg = with_budget(cfg, args.iters)
    return data, apply_overrides(cfg, overrides)


class FitInterrupted(Exception):
    """Training stopped by Ctrl-C or SIGTERM after saving its checkpoint."""


def _raise_interrupt(signum, frame) -> None:  # noqa: ARG001
    raise KeyboardInterrupt


def run_fit(
    scene: Scene,
    cfg: RunConfig,
    run_dir: Path,
    data: Path,
    resume: bool = False,
    threads: int | None = None,
    log_every: int = 100,
    quiet: bool = False,
) -> dict:
    """Train (or resume) Phase 1 on `scene` into `run_dir`; returns the final summary."""
    n_threads = _set_threads(threads)
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt = run_dir / CHECKPOINT_NAME
    run_info = {
        "data": str(data.resolve()),
        "scene": scene.name,
        "resolution_scale": cfg.resolution_scale,
        "test_split": cfg.test_split,
        "config": dataclasses.asdict(cfg),
        "threads": n_threads,
    }
    if resume:
        trainer = resume_trainer(ckpt, scene, cfg.phase1, n_threads, cfg.iterations)
        print(f"fit: resumed {ckpt} at iteration {trainer.iteration}", file=sys.stderr)
    else:
        model = initial_model(
            scene, cfg.init_points, cfg.sh_degree, cfg.deform, cfg.init_box_fraction,
            cfg.phase1.seed,
        )  # fmt: skip
        trainer = Phase1Trainer(model, scene, cfg.phase1, cfg.iterations, threads=n_threads)
    (run_dir / RUN_FILE).write_text(json.dumps(run_info, indent=2) + "\n")
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

    bar = Progress(cfg.iterations, start=trainer.iteration, desc="fit", log_every=log_every)
    ema: dict[str, float] = {}
    wall0 = time.perf_counter()
    train_seconds = 0.0
    previous_sigterm = signal.signal(signal.SIGTERM, _raise_interrupt)
    interrupted = False
    try:
        while trainer.iteration < cfg.iterations:
            t0 = time.perf_counter()
            stats = trainer.step()
            train_seconds += time.perf_counter() - t0
            for k in ("loss", "psnr"):
                v = stats[k]
                if math.isfinite(v):
                    ema[k] = v if k not in ema else 0.9 * ema[k] + 0.1 * v
            it = trainer.iteration
            bar.update(
                it,
                {
                    "loss": f"{ema.get('loss', float('nan')):.4f}",
                    "PSNR": f"{ema.get('psnr', float('nan')):.2f}",
                    "#G": f"{trainer.model.num_gaussians}",
                },
            )
            if it % log_every == 0:
                log({"iteration": it, "train_seconds": train_seconds, **stats})
            if cfg.eval_every and it % cfg.eval_every == 0 and it < cfg.iterations:
                res = summarize(
                    evaluate_frames(
                        trainer.model, periodic, cfg.phase1.background, n_threads, images=target
                    )
                )
                log({"iteration": it, "train_seconds": train_seconds, "test": res})
                bar.message(
                    f"[eval @ {it}] test PSNR {res['psnr']:.2f} dB, SSIM {res['ssim']:.4f} "
                    f"({res['frames']} frames, {trainer.model.num_gaussians} Gaussians, "
                    f"{format_duration(train_seconds)} training)"
                )
            if cfg.checkpoint_every and it % cfg.checkpoint_every == 0:
                save_checkpoint(trainer, ckpt, {**extra, "train_seconds": train_seconds})
    except KeyboardInterrupt:
        interrupted = True
    finally:
        signal.signal(signal.SIGTERM, previous_sigterm)
        bar.close()
    save_checkpoint(trainer, ckpt, {**extra, "train_seconds": train_seconds})
    if interrupted:
        metrics_log.close()
        print(
            f"fit: interrupted at iteration {trainer.iteration}; checkpoint saved to {ckpt}.\n"
            f"     continue with: python -m sync4d fit {data} --out {run_dir} --resume",
            file=sys.stderr,
        )
        raise FitInterrupted
    from sync4d.commands.evaluate import evaluate_run

    summary = evaluate_run(
        run_dir, trainer.model, scene, cfg.phase1.background, n_threads, quiet=quiet
    )
    summary.update(
        {"iterations": trainer.iteration, "train_seconds": train_seconds,
         "wall_seconds": time.perf_counter() - wall0, "gaussians": trainer.model.num_gaussians}
    )  # fmt: skip
    log({"iteration": trainer.iteration, "train_seconds": train_seconds, "final": summary})
    metrics_log.close()
    return summary


def main(args: argparse.Namespace) -> int:
    try:
        data, cfg = _load(args)
        run_dir = Path(args.out) if args.out else Path("runs") / data.name
        ckpt = run_dir / CHECKPOINT_NAME
        if args.resume and not ckpt.exists():
            print(f"fit: {ckpt}: no checkpoint to resume from", file=sys.stderr)
            return 2
        if ckpt.exists() and not (args.resume or args.force):
            print(
                f"fit: {run_dir} already holds a run; pass --resume to continue it or --force "
                "to start over",
                file=sys.stderr,
            )
            return 2
        if args.force and not args.resume:
            for name in (CHECKPOINT_NAME, METRICS_FILE):
                (run_dir / name).unlink(missing_ok=True)
        scene = load_scene(data, cfg.resolution_scale, cfg.test_split)
        print(
            f"fit: {scene.name}: {len(scene.train)} train / {len(scene.test)} test frames at "
            f"{scene.train[0].camera.width}x{scene.train[0].camera.height}, "
            f"{cfg.iterations} iterations -> {run_dir}",
            file=sys.stderr,
        )
        summary = run_fit(scene, cfg, run_dir, data, args.resume, args.threads)
    except (ConfigError, DatasetError) as e:
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
    return 0
