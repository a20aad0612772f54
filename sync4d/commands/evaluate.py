"""``python -m sync4d eval RUN``: PSNR, SSIM and LPIPS-Alex of a run's checkpoint on the test
split, per frame and mean, written to ``RUN/eval.json`` and printed as a table."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

import torch

from sync4d.checkpoint import CheckpointError, load_model
from sync4d.data import DatasetError, Scene, load_scene
from sync4d.evaluate import FrameMetrics, evaluate_frames, summarize
from sync4d.gaussians import DeformableGaussians
from sync4d.lpips import MIN_SIZE, LPIPSAlex, load_lpips
from sync4d.progress import Progress
from sync4d.report import align_table

__all__ = ["main", "evaluate_run", "load_run", "EVAL_FILE", "RENDERS_DIR", "RunError"]

EVAL_FILE = "eval.json"
#: Folder (inside a run) of the evaluation's side-by-side renders, one subfolder per split.
RENDERS_DIR = "renders"


class RunError(ValueError):
    """A run directory that cannot be used; the message names the file."""


def _lpips_metric() -> LPIPSAlex | None:
    """The LPIPS-Alex callable, or None (with a note on stderr) when its weights are missing."""
    try:
        return load_lpips()
    except RuntimeError as e:
        print(f"eval: LPIPS skipped: {e}", file=sys.stderr)
        return None


def format_metrics(metrics: list[FrameMetrics], summary: dict) -> str:
    """Per-frame table plus the mean row."""

    def f(v: float | None, spec: str) -> str:
        return "-" if v is None else format(v, spec)

    rows = [[m.name, f"{m.time:.3f}", f(m.psnr, ".2f"), f(m.ssim, ".4f"), f(m.lpips, ".4f")]
            for m in metrics]  # fmt: skip
    rows.append(
        ["mean", "", f(summary["psnr"], ".2f"), f(summary["ssim"], ".4f"),
         f(summary["lpips"], ".4f")]
    )  # fmt: skip
    return align_table(["frame", "time", "PSNR dB", "SSIM", "LPIPS"], rows)


def evaluate_run(
    run_dir: Path,
    model: DeformableGaussians,
    scene: Scene,
    background: tuple[float, ...] | list[float],
    threads: int | None = None,
    split: str = "test",
    quiet: bool = False,
    renders: bool = True,
) -> dict:
    """Evaluate `model` on `scene`'s split, write ``run_dir/eval.json`` (and, with `renders`,
    ``run_dir/renders/<split>/<frame>.png``: render beside ground truth), print the table;
    returns the summary (mean PSNR, SSIM, LPIPS)."""
    frames = scene.test if split == "test" else scene.train
    if not frames:
        raise RunError(f"{run_dir}: the dataset has no {split} frames to evaluate")
    lpips = _lpips_metric()
    h, w = frames[0].camera.height, frames[0].camera.width
    if lpips is not None and min(h, w) < MIN_SIZE:
        print(f"eval: LPIPS skipped: {w}x{h} images are smaller than the {MIN_SIZE} pixels "
              "AlexNet needs", file=sys.stderr)  # fmt: skip
        lpips = None
    bar = Progress(len(frames), desc=f"eval {split}", log_every=max(1, len(frames)))
    metrics = evaluate_frames(
        model, frames, tuple(background), threads, lpips=lpips,
        on_frame=lambda i, m: bar.update(i + 1, {"PSNR": f"{m.psnr:.2f}"}),
        save_dir=run_dir / RENDERS_DIR / split if renders else None,
    )  # fmt: skip
    bar.close()
    summary = summarize(metrics)
    out = {
        "split": split,
        "mean": summary,
        "frames": [asdict(m) for m in metrics],
        "gaussians": model.num_gaussians,
    }
    path = run_dir / EVAL_FILE
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(out, indent=2) + "\n")
    tmp.replace(path)
    if not quiet:
        print(format_metrics(metrics, summary))
        where = f" and {run_dir / RENDERS_DIR / split}/" if renders else ""
        print(f"eval: wrote {path}{where}")
    return dict(summary)


def load_run(
    run_dir: Path, data: str | None = None
) -> tuple[DeformableGaussians, dict, Scene | None, list[float]]:
    """Model, checkpoint metadata, dataset (None when it cannot be found and `data` was not
    given) and background of the run in `run_dir`."""
    from sync4d.commands.fit import CHECKPOINT_NAME

    ckpt = run_dir / CHECKPOINT_NAME
    if not run_dir.is_dir():
        raise RunError(f"{run_dir}: run directory does not exist")
    model, meta = load_model(ckpt)
    run = meta.get("run", {})
    background = meta.get("background", [1.0, 1.0, 1.0])
    root = data or run.get("data")
    scene = None
    if root is not None and (data is not None or Path(root).exists()):
        scene = load_scene(
            root, float(run.get("resolution_scale", 1.0)), run.get("test_split", "test")
        )
    return model, meta, scene, background


def main(args: argparse.Namespace) -> int:
    run_dir = Path(args.run)
    try:
        model, meta, scene, background = load_run(run_dir, args.data)
        if scene is None:
            raise RunError(
                f"{run_dir}: the run's dataset ({meta.get('run', {}).get('data')}) is not "
                "there any more; pass --data PATH"
            )
        threads = args.threads or None
        if threads:
            torch.set_num_threads(threads)
        evaluate_run(run_dir, model, scene, background, threads, args.split)
    except (RunError, CheckpointError, DatasetError) as e:
        print(f"eval: {e}", file=sys.stderr)
        return 2
    return 0
