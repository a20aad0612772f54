"""Evaluation of a trained model on a split: PSNR, SSIM (the loss's 3x3 average-pool SSIM) and
LPIPS-Alex per frame and their means; `evaluate_run` writes them to the run's ``eval.json``
with side-by-side renders."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from sync4d.data.scene import Frame, Scene
from sync4d.metrics import psnr, ssim
from sync4d.metrics.lpips import MIN_SIZE, LPIPSAlex, load_lpips
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.progress import Progress
from sync4d.report import align_table
from sync4d.runs.files import write_text_atomic
from sync4d.runs.folder import EVAL_FILE, RENDERS_DIR, RunError

__all__ = [
    "FrameMetrics",
    "evaluate_frames",
    "evaluate_run",
    "format_metrics",
    "render_frame",
    "save_side_by_side",
    "summarize",
]


@dataclass
class FrameMetrics:
    """Metrics of one test frame (`lpips` is None when the LPIPS weights are not installed)."""

    index: int
    name: str
    time: float
    psnr: float
    ssim: float
    lpips: float | None = None


@torch.no_grad()
def render_frame(
    model: DeformableGaussians,
    frame: Frame,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    threads: int | None = None,
) -> torch.Tensor:
    """The model's RGB render [H, W, 3] in [0, 1] of `frame`'s camera at its time."""
    bg = torch.tensor(list(background), dtype=torch.float32)
    out = model.render(frame.camera, frame.time, background=bg, threads=threads)
    return out.features.clamp(0.0, 1.0)


@torch.no_grad()
def evaluate_frames(
    model: DeformableGaussians,
    frames: Sequence[Frame],
    background: Sequence[float] = (1.0, 1.0, 1.0),
    threads: int | None = None,
    lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
    images: Callable[[int, Frame], torch.Tensor] | None = None,
    on_frame: Callable[[int, FrameMetrics], None] | None = None,
    save_dir: Path | None = None,
) -> list[FrameMetrics]:
    """Render every frame and compare with its ground-truth image. `images(i, frame)` supplies
    cached targets (default: load from disk); `lpips(pred, target)` adds LPIPS; `save_dir`
    receives one PNG per frame, the render beside the ground truth."""
    out: list[FrameMetrics] = []
    for i, frame in enumerate(frames):
        if images is not None:
            target = images(i, frame)
        else:
            target = torch.from_numpy(frame.load_image(tuple(background)))
        pred = render_frame(model, frame, background, threads)
        m = FrameMetrics(
            index=i,
            name=frame.name,
            time=float(frame.time),
            psnr=psnr(pred, target),
            ssim=float(ssim(pred, target)),
        )
        if lpips is not None:
            m.lpips = float(lpips(pred, target))
        if save_dir is not None:
            save_side_by_side(pred, target, save_dir / f"{Path(frame.name).stem}.png")
        out.append(m)
        if on_frame is not None:
            on_frame(i, m)
    return out


def save_side_by_side(pred: torch.Tensor, target: torch.Tensor, path: Path) -> Path:
    """Write the render [H, W, 3] and the ground truth [H, W, 3] (values in [0, 1]) side by side
    as an 8-bit PNG."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    pair = torch.cat([pred.detach().clamp(0, 1), target.clamp(0, 1)], dim=1)
    Image.fromarray((pair.numpy() * 255 + 0.5).astype(np.uint8)).save(path)
    return path


def summarize(metrics: Sequence[FrameMetrics]) -> dict[str, float | None]:
    """Means of PSNR, SSIM and LPIPS over frames (LPIPS None if any frame lacks it)."""
    if not metrics:
        return {"psnr": None, "ssim": None, "lpips": None, "frames": 0}
    lp = [m.lpips for m in metrics]
    return {
        "psnr": float(np.mean([m.psnr for m in metrics])),
        "ssim": float(np.mean([m.ssim for m in metrics])),
        "lpips": None if any(v is None for v in lp) else float(np.mean(lp)),
        "frames": len(metrics),
    }


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
    tag: str | None = None,
) -> dict:
    """Evaluate `model` on `scene`'s split, write ``run_dir/eval.json`` (and, with `renders`,
    ``run_dir/renders/<split>/<frame>.png``: render beside ground truth), print the table;
    returns the summary (mean PSNR, SSIM, LPIPS). With `tag` (another split or dataset than
    the run's test split) the files are ``eval-<tag>.json`` and ``renders/<tag>/`` instead, so
    the run's own results are never overwritten."""
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
        save_dir=run_dir / RENDERS_DIR / (tag or split) if renders else None,
    )  # fmt: skip
    bar.close()
    summary = summarize(metrics)
    out = {
        "split": split,
        "mean": summary,
        "frames": [asdict(m) for m in metrics],
        "gaussians": model.num_gaussians,
    }
    path = run_dir / (EVAL_FILE if tag is None else f"eval-{tag}.json")
    write_text_atomic(path, json.dumps(out, indent=2) + "\n")
    if not quiet:
        print(format_metrics(metrics, summary))
        where = f" and {run_dir / RENDERS_DIR / (tag or split)}/" if renders else ""
        print(f"eval: wrote {path}{where}")
    return dict(summary)
