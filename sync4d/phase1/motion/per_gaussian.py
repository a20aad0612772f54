"""The paper's motion (Sec. 3.1, Eqs. 2-4): D_theta evaluated on every moving Gaussian's
[position, embedding, gamma(t)]; the static Gaussians (`sync4d.phase1.static`) keep their
canonical state and skip D_theta."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from sync4d.phase1.deform import deform_gaussians
from sync4d.phase1.motion.base import Motion

if TYPE_CHECKING:
    from sync4d.phase1.gaussians import DeformableGaussians
    from sync4d.phase1.trainer import Phase1Trainer

__all__ = ["GaussianMotion", "per_gaussian_deformed", "static_skip_counts"]


def per_gaussian_deformed(model: DeformableGaussians, t: float, q0: Tensor
                          ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """D_theta on the moving rows of `model` at `t` (static rows keep zero offsets), applied
    by Eqs. 2-4; counts the rows evaluated and skipped and keeps the offsets
    (`DeformableGaussians.last_offsets`, the motion-sparsity loss's input)."""
    n = model.num_gaussians
    if model.static.shape != (n,):  # rows changed outside the densifier
        if bool(model.static.any()):
            raise RuntimeError(f"static mask has {model.static.shape[0]} rows for {n} "
                               "Gaussians: change rows through the densifier")  # fmt: skip
        model.static = torch.zeros(n, dtype=torch.bool)
    n_static = int(model.static.sum())
    model.deform_rows += n - n_static
    model.deform_rows_skipped += n_static
    if n_static == 0:
        dx, dw, dl = model.last_offsets = model.deform(model.means, model.embeddings, t)
    elif n_static == n:  # nothing moves: the canonical Gaussians at every time
        model.last_offsets = None
        return model.means, q0, torch.exp(model.log_scales)
    else:  # D_theta on the moving rows only; static rows keep zero offsets
        rows = (~model.static).nonzero().squeeze(1)
        part = model.last_offsets = model.deform(model.means[rows], model.embeddings[rows], t)
        dx, dw, dl = (torch.zeros(n, 3, dtype=p.dtype).index_put((rows,), p) for p in part)
    return deform_gaussians(model.means, q0, model.log_scales, dx, dw, dl)


def per_gaussian_network(model: DeformableGaussians, t: float) -> tuple[Tensor, ...]:
    """D_theta's offsets at `t` on the rows `per_gaussian_deformed` evaluates (the moving
    ones)."""
    rows = (~model.static).nonzero().squeeze(1)
    return model.deform(model.means[rows], model.embeddings[rows], t)


def static_skip_counts(model: DeformableGaussians) -> dict[str, int | float]:
    """D_theta's row counters of `model` in this process and its static set now."""
    rows, skipped = model.deform_rows, model.deform_rows_skipped
    return {"deform_rows": rows, "deform_rows_skipped": skipped,
            "share": skipped / max(1, rows + skipped), "static": int(model.static.sum())}


class GaussianMotion(Motion):
    """D_theta per Gaussian (the paper), static Gaussians skipped."""

    name = "gaussians"

    def deformed(self, model: DeformableGaussians, t: float, q0: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        return per_gaussian_deformed(model, t, q0)

    def network(self, model: DeformableGaussians, t: float) -> tuple[Tensor, ...]:
        return per_gaussian_network(model, t)

    def step_stats(self, trainer: Phase1Trainer) -> dict[str, float]:
        if trainer.config.static.enabled:
            return {"static": float(trainer.model.static.sum())}
        return {}

    def skip_counts(self, trainer: Phase1Trainer) -> dict[str, int | float]:
        return static_skip_counts(trainer.model) if trainer.config.static.enabled else {}
