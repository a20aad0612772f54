"""A run's image at a time from a camera, for the front ends that render on request (`view`'s
"Render view", `serve`'s `render` tool): one place that renders, checks and says why a render
failed.

Design: the model's render is watched (the watchdog stops a NaN or a diverged value of what the
rasterizer would receive), the rasterizer may refuse its input, and the image itself may hold
NaN or inf pixels; each becomes a `RenderFailed` of one sentence (no line break, no sentence
break inside) that says what happened and what to do, and nothing is written.
"""

from __future__ import annotations

import numpy as np
import torch

from sync4d.data.scene import Camera
from sync4d.errors import Sync4dError
from sync4d.phase1.gaussians import DeformableGaussians

__all__ = ["RenderFailed", "render_rgb"]

#: What a render that stopped on a non-finite value asks the user to do.
RETRAIN = ("train the run again with lower learning rates (fit --out RUN --force), or render "
           "another time")
#: What a render the rasterizer refused asks by default.
ELSEWHERE = "move the camera or the time and render again"


class RenderFailed(Sync4dError, ValueError):
    """A render of a run that failed, in one sentence saying what to do: the watchdog's stop on
    what the rasterizer would receive (a NaN or a diverged value of the checkpoint at that
    time), the rasterizer's refusal, or NaN or inf pixels."""

    @classmethod
    def of(cls, e: BaseException | None, t: float, camera: str | None = None,
           instead: str = ELSEWHERE) -> RenderFailed:  # fmt: skip
        """The failure `e` (None: NaN or inf pixels) of a render at time `t` (from `camera`,
        when named); `instead`: what to try after a refusal of the rasterizer."""
        where = f"the render at t = {t:.3f}" + (f" from camera {camera}" if camera else "")
        if e is None:
            text = f"{where} has NaN or inf pixels (the checkpoint is not finite there); {RETRAIN}"
        elif isinstance(e, FloatingPointError):  # the watchdog's NonFinite
            what = str(e).partition(". Try:")[0].split("stopped: ", 1)[-1]
            text = f"{where} stopped: {what}; {RETRAIN}"
        else:
            text = f"{where} failed ({e}); {instead}"
        return cls(" ".join(text.split()).replace(". ", "; ").rstrip("."))


def render_rgb(model: DeformableGaussians, camera: Camera, t: float, background: torch.Tensor,
               threads: int | None = None, *, name: str | None = None,
               instead: str = ELSEWHERE) -> np.ndarray:  # fmt: skip
    """`model` at time `t` seen by `camera` on `background` [3], as 8-bit RGB [H, W, 3];
    `RenderFailed` (`name`: the camera's, in the message; `instead`: see `RenderFailed.of`)
    when the watchdog stops it, the rasterizer refuses it or its image is not finite."""
    try:
        with torch.no_grad():
            img = model.render(camera, float(t), background=background, threads=threads)
        finite = bool(torch.isfinite(img.features).all())
    except (FloatingPointError, ValueError, RuntimeError) as e:  # the watchdog, the raster
        raise RenderFailed.of(e, t, name, instead) from None
    if not finite:
        raise RenderFailed.of(None, t, name, instead)
    return (img.features.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
