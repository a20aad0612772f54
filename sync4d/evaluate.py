"""Test-split evaluation of a trained model: PSNR, SSIM (the loss's 3x3 average-pool SSIM) and
LPIPS-Alex per frame and their means."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from sync4d.data.scene import Frame
from sync4d.gaussians import DeformableGaussians
from sync4d.losses import psnr, ssim

__all__ = ["FrameMetrics", "render_frame", "evaluate_frames", "summarize"]


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
) -> list[FrameMetrics]:
    """Render every frame and compare with its ground-truth image. `images(i, frame)` supplies
    cached targets (default: load from disk); `lpips(pred, target)` adds LPIPS."""
    out: list[FrameMetrics] = []
    for i, frame in enumerate(frames):
        if images is not None:
            target = images(i, frame)
        else:
            target = torch.from_numpy(frame.load_image(tuple(background)))
        pred = render_frame(model, frame, background, threads)
        m = FrameMetrics(
            index=i,
            name=frame.image_path.name,
            time=float(frame.time),
            psnr=psnr(pred, target),
            ssim=float(ssim(pred, target)),
        )
        if lpips is not None:
            m.lpips = float(lpips(pred, target))
        out.append(m)
        if on_frame is not None:
            on_frame(i, m)
    return out


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
