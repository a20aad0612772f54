"""Test-split evaluation of a trained model: PSNR, SSIM (the loss's 3x3 average-pool SSIM) and
LPIPS-Alex per frame and their means."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sync4d.data.scene import Frame
from sync4d.gaussians import DeformableGaussians
from sync4d.losses import psnr, ssim

__all__ = ["FrameMetrics", "evaluate_frames", "render_frame", "save_side_by_side", "summarize"]


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
