"""Phase 2 diagnostics (Appendix C).

`diagnostics`: per-object and mean rigid share, residual mean and motion variance, the
modulated fraction and the shuffle test (residual energy under random label permutations over
that with the true labels, no retraining). It reads a `MotionStrategy` (and the trainer it is
plugged into) and changes nothing; the motion export later phases read is the strategy's
`motion_export`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from sync4d.phase2.assign import adjusted_rand_index, assign_objects
from sync4d.phase2.terms import rigid_share

if TYPE_CHECKING:
    from sync4d.phase2.strategy import MotionStrategy

__all__ = ["diagnostics", "residuals_at"]


@torch.no_grad()
def residuals_at(
    p2: MotionStrategy, t: float, labels: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(x_i(t) [N, 3], r_i(t) [N, 3]) at time `t`, optionally with other `labels`."""
    x = p2.trainer.model.at_time(float(t))[0]
    lab = p2.labels if labels is None else labels
    return x, x - p2.motion(p2.trainer.model.means, lab, float(t))

@torch.no_grad()
def diagnostics(p2: MotionStrategy, shuffles: int = 5, seed: int = 0) -> dict:
    """Appendix C diagnostics over every stored frame: per-object and mean rigid share,
    residual mean, motion variance, the fraction of Gaussians with m_i > 0.5, and the
    shuffle test (residual energy under `shuffles` random label permutations over that
    with the true labels, no retraining)."""
    k = p2.assignment.num_objects
    x0 = p2.trainer.model.means
    labels = p2.labels
    rho_k = np.zeros(k)
    res_k = np.zeros(k)
    var_k = np.zeros(k)
    energy = 0.0
    rho_all = 0.0
    for t in p2.times:
        x, r = residuals_at(p2, float(t))
        x_obj = x - r
        rho_i = rigid_share(x0, x_obj, r, p2.phase2.share_eps)
        rho_all += float(rho_i.mean())
        rn = r.norm(dim=-1)
        energy += float((rn * rn).mean())
        disp = x - x0
        for j in range(k):
            sel = labels == j
            if sel.any():
                rho_k[j] += float(rho_i[sel].mean())
                res_k[j] += float(rn[sel].mean())
                dj = disp[sel]
                var_k[j] += float(((dj - dj.mean(0)) ** 2).sum(-1).mean())
    nt = len(p2.times)
    g = torch.Generator().manual_seed(seed)
    ratios = []
    for _ in range(shuffles):
        perm = labels[torch.randperm(len(labels), generator=g)]
        e = 0.0
        for t in p2.times:
            _, r = residuals_at(p2, float(t), perm)
            e += float((r * r).sum(-1).mean())
        ratios.append(e / max(energy, 1e-30))
    ema = p2.residual_ema
    m = torch.sigmoid((ema - ema.mean()) / (ema.std(unbiased=False) + 1e-6))
    counts = p2.assignment.counts()
    names = p2.assignment.names
    return {
        "objects": [
            {
                "label": j, "name": names.get(j, f"object {j}"), "gaussians": counts[j],
                "static": bool(p2.static[j]), "held": bool(p2.motion.frozen[j]),
                "rigid_share": rho_k[j] / nt,
                "residual_mean": res_k[j] / nt, "motion_variance": var_k[j] / nt,
            }
            for j in range(k)
        ],  # fmt: skip
        "rigid_share": rho_all / nt,
        "residual_energy": energy / nt,
        "modulated_fraction": float((m > 0.5).float().mean()) if p2.ema_started else 0.0,
        "shuffle_ratio": float(np.mean(ratios)) if ratios else math.nan,
        "shuffle_ratios": ratios,
        "assignment": p2.assignment.source,
        "num_objects": k,
        **_mask_agreement(p2),
    }

def _mask_agreement(p2: MotionStrategy) -> dict:
    """For an unsupervised assignment of a scene that has masks: the adjusted Rand index of
    the trajectory clusters against mask voting over all Gaussians (empty otherwise)."""
    if p2.assignment.source != "trajectories" or not p2.trainer.scene.has_masks:
        return {}
    cfg = dataclasses.replace(p2.phase2.assign, source="masks")
    reference = assign_objects(p2.trainer.model, p2.trainer.scene, p2.trainer.extent, cfg)
    return {
        "mask_agreement_ari": adjusted_rand_index(p2.assignment.labels, reference.labels),
        "mask_objects": reference.num_objects - 1,
    }
