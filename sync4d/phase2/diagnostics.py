"""Phase 2 diagnostics (Appendix C) and the motion export later phases read.

`diagnostics`: per-object and mean rigid share, residual mean and motion variance, the
modulated fraction and the shuffle test (residual energy under random label permutations over
that with the true labels, no retraining). `motion_export`: every object's transform, centroid
and velocity at each stored frame. Both read a `Phase2Trainer` and change nothing.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from sync4d.phase2.assign import adjusted_rand_index, assign_objects
from sync4d.report import align_table

if TYPE_CHECKING:
    from sync4d.phase2.trainer import Phase2Trainer

__all__ = ["diagnostics", "format_diagnostics", "motion_export", "residuals_at", "rigid_share"]


def rigid_share(x0: Tensor, x_obj: Tensor, residual: Tensor, eps: float = 1e-6) -> Tensor:
    """Per-Gaussian rigid share ||x~ - x0|| / (||x~ - x0|| + ||r|| + eps) [N] (Eq. 9's terms)."""
    shared = (x_obj - x0).norm(dim=-1)
    return shared / (shared + residual.norm(dim=-1) + eps)


@torch.no_grad()
def residuals_at(
    trainer: Phase2Trainer, t: float, labels: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """(x_i(t) [N, 3], r_i(t) [N, 3]) at time `t`, optionally with other `labels`."""
    x = trainer.model.at_time(float(t))[0]
    lab = trainer.labels if labels is None else labels
    return x, x - trainer.motion(trainer.model.means, lab, float(t))

@torch.no_grad()
def diagnostics(trainer: Phase2Trainer, shuffles: int = 5, seed: int = 0) -> dict:
    """Appendix C diagnostics over every stored frame: per-object and mean rigid share,
    residual mean, motion variance, the fraction of Gaussians with m_i > 0.5, and the
    shuffle test (residual energy under `shuffles` random label permutations over that
    with the true labels, no retraining)."""
    k = trainer.assignment.num_objects
    x0 = trainer.model.means
    labels = trainer.labels
    rho_k = np.zeros(k)
    res_k = np.zeros(k)
    var_k = np.zeros(k)
    energy = 0.0
    rho_all = 0.0
    for t in trainer.times:
        x, r = residuals_at(trainer, float(t))
        x_obj = x - r
        rho_i = rigid_share(x0, x_obj, r, trainer.phase2.share_eps)
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
    nt = len(trainer.times)
    g = torch.Generator().manual_seed(seed)
    ratios = []
    for _ in range(shuffles):
        perm = labels[torch.randperm(len(labels), generator=g)]
        e = 0.0
        for t in trainer.times:
            _, r = residuals_at(trainer, float(t), perm)
            e += float((r * r).sum(-1).mean())
        ratios.append(e / max(energy, 1e-30))
    ema = trainer.residual_ema
    m = torch.sigmoid((ema - ema.mean()) / (ema.std(unbiased=False) + 1e-6))
    counts = trainer.assignment.counts()
    names = trainer.assignment.names
    return {
        "objects": [
            {
                "label": j, "name": names.get(j, f"object {j}"), "gaussians": counts[j],
                "static": bool(trainer.static[j]), "held": bool(trainer.motion.frozen[j]),
                "rigid_share": rho_k[j] / nt,
                "residual_mean": res_k[j] / nt, "motion_variance": var_k[j] / nt,
            }
            for j in range(k)
        ],  # fmt: skip
        "rigid_share": rho_all / nt,
        "residual_energy": energy / nt,
        "modulated_fraction": float((m > 0.5).float().mean()) if trainer.ema_started else 0.0,
        "shuffle_ratio": float(np.mean(ratios)) if ratios else math.nan,
        "shuffle_ratios": ratios,
        "assignment": trainer.assignment.source,
        "num_objects": k,
        **_mask_agreement(trainer),
    }

def _mask_agreement(trainer: Phase2Trainer) -> dict:
    """For an unsupervised assignment of a scene that has masks: the adjusted Rand index of
    the trajectory clusters against mask voting over all Gaussians (empty otherwise)."""
    if trainer.assignment.source != "trajectories" or not trainer.scene.has_masks:
        return {}
    cfg = dataclasses.replace(trainer.phase2.assign, source="masks")
    reference = assign_objects(trainer.model, trainer.scene, trainer.extent, cfg)
    return {
        "mask_agreement_ari": adjusted_rand_index(trainer.assignment.labels, reference.labels),
        "mask_objects": reference.num_objects - 1,
    }

@torch.no_grad()
def motion_export(trainer: Phase2Trainer) -> dict[str, np.ndarray]:
    """Per-object per-frame motion for later phases: rotations (linear part) [K, T, 3, 3],
    translations [K, T, 3], centroids of each object's Gaussians [K, T, 3] and their
    velocities [K, T, 3] (central differences in world units per unit time), frame times
    [T] and labels [N]."""
    a, b = trainer.motion.trajectory()
    k, nt = a.shape[0], a.shape[1]
    cent = np.zeros((k, nt, 3))
    labels = trainer.labels.numpy()
    for i, t in enumerate(trainer.times):
        x = trainer.model.at_time(float(t))[0].double().numpy()
        for j in range(k):
            sel = labels == j
            if sel.any():
                cent[j, i] = x[sel].mean(0)
    vel = np.gradient(cent, trainer.times, axis=1) if nt > 1 else np.zeros_like(cent)
    return {
        "rotations": a, "translations": b, "centroids": cent, "velocities": vel,
        "times": trainer.times.copy(), "labels": labels.astype(np.int64),
    }  # fmt: skip


def format_diagnostics(diag: dict) -> str:
    """Phase 2 diagnostics (Appendix C) as a table plus a summary line."""
    rows = [
        [str(o["label"]), o["name"], f"{o['gaussians']:,}",
         "held" if o.get("held") else "yes" if o["static"] else "",
         f"{o['rigid_share']:.3f}", f"{o['residual_mean']:.4f}", f"{o['motion_variance']:.2e}"]
        for o in diag["objects"]
    ]  # fmt: skip
    table = align_table(
        ["k", "object", "Gaussians", "static", "rigid share", "residual", "motion var"], rows,
        left=(1,),
    )  # fmt: skip
    return (
        f"{table}\nmean rigid share {diag['rigid_share']:.3f}, residual energy "
        f"{diag['residual_energy']:.2e}, modulated fraction {diag['modulated_fraction']:.3f}, "
        f"shuffle ratio {diag['shuffle_ratio']:.2f} ({diag['assignment']} assignment)"
        + (
            f"\nagreement with mask voting: adjusted Rand index {diag['mask_agreement_ari']:.3f} "
            f"({diag['num_objects'] - 1} clusters vs {diag['mask_objects']} mask objects)"
            if "mask_agreement_ari" in diag
            else ""
        )
    )
