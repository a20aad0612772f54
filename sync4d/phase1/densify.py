"""Adaptive density control of 3DGS (clone / split / prune, opacity reset) as a strategy object
that owns its statistics, so the trainer never changes when the strategy does.

Every operation keeps the Adam state aligned with the parameters: rows of kept Gaussians keep
their moments, new rows start at zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from sync4d.geometry import quat_to_matrix
from sync4d.phase1.gaussians import PER_GAUSSIAN, DeformableGaussians
from sync4d.phase1.rows import replace_param_rows
from sync4d.settings import ranged

__all__ = ["DensifyConfig", "Densifier", "PER_GAUSSIAN"]


@dataclass(frozen=True)
class DensifyConfig:
    """3DGS densification settings (paper Appendix A values where given)."""

    #: Mean screen-space gradient norm of a Gaussian's centre above which it is cloned or split.
    grad_threshold: float = ranged(2e-4, 0.0, lo_open=True)
    #: First iteration of densification (below `stop` and `phase1.iterations` while `stop` >
    #: 0, else no iteration densifies: refused when the config is read).
    start: int = ranged(500, 0, scales=0)
    #: Last iteration of densification (0: none).
    stop: int = ranged(15_000, 0, scales=0)
    #: Iterations between densification steps.
    interval: int = ranged(100, 1, scales=10)
    #: Iterations between opacity resets (every opacity set to at most 0.01).
    opacity_reset_interval: int = ranged(3_000, 1, scales=1)
    #: Gaussians with opacity below this are pruned at each densification step.
    prune_opacity: float = ranged(0.005, 0.0, 1.0)
    #: Gaussians larger than this fraction of the scene extent are split, smaller ones cloned.
    percent_dense: float = ranged(0.01, 0.0)
    #: Keep pruning Gaussians with opacity below `prune_opacity` every `interval` iterations
    #: after `stop`, to the end of training (3DGS prunes only while densifying). They draw
    #: next to nothing (below 1/255 nothing at all, and then get no gradient to come back),
    #: yet still pay D_theta, projection and binning at every step.
    prune_after_stop: bool = False
    #: Gaussians a split Gaussian becomes.
    split_count: int = ranged(2, 2)
    #: Densification stops adding Gaussians at this count.
    max_gaussians: int = ranged(1_000_000, 1)
    #: After the first opacity reset, also prune Gaussians whose largest world-space scale
    #: exceeds this fraction of the scene extent (3DGS / gsplat use 0.1; 0 disables, the
    #: default here: on the embedded scene and bouncingballs it cost 0.6-1 dB in our short
    #: CPU schedules). Wide captures need it: metre-sized blobs otherwise fill empty space as
    #: fog and cover novel views (the panoptic config sets 0.1).
    prune_world_scale: float = ranged(0.0, 0.0)
    #: ...and, when > 0, those whose projected radius exceeded this fraction of the image's
    #: larger side in some view since the last densification (gsplat's optional 0.15; off by
    #: default as in gsplat and, effectively, 3DGS).
    prune_screen_fraction: float = ranged(0.0, 0.0)


def _replace_rows(optimizer: torch.optim.Optimizer, model: DeformableGaussians, fn) -> None:
    """Replace every per-Gaussian parameter `p` by `fn(name, p, is_state)`, carrying the Adam
    moments through the same row operation."""
    replace_param_rows(optimizer, model, PER_GAUSSIAN, fn)
    # Per-Gaussian flags follow the same rows (split and cloned children inherit them).
    model.static = fn("static", model.static, False)
    model.motion_model.rows_changed(fn)


class Densifier:
    """Accumulates screen-space gradient statistics and densifies / prunes on schedule."""

    def __init__(self, config: DensifyConfig | None = None, seed: int = 0) -> None:
        self.config = config or DensifyConfig()
        #: Draws the split children's offsets; its state is checkpointed, so a resumed run
        #: densifies as an uninterrupted one would.
        self.generator = torch.Generator().manual_seed(seed)
        self.grad_accum = torch.zeros(0)
        self.count = torch.zeros(0)
        #: Largest projected radius of each Gaussian since the last densification, as a
        #: fraction of the image's larger side.
        self.max_radius = torch.zeros(0)
        #: Gaussians `prune_transparent` removed after densification (in this process).
        self.pruned_transparent = 0

    def _ensure(self, n: int) -> None:
        if self.grad_accum.shape[0] != n:
            self.grad_accum = torch.zeros(n)
            self.count = torch.zeros(n)
        if self.max_radius.shape[0] != n:
            self.max_radius = torch.zeros(n)

    def accumulate(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:
        """Add one view's screen-space gradient norms (pixels -> NDC units) for visible
        Gaussians. `means2d_grad` [N, 2], `radii` [N, 2]."""
        n = means2d_grad.shape[0]
        self._ensure(n)
        visible = (radii > 0).all(dim=-1)
        g = means2d_grad.detach() * torch.tensor([0.5 * width, 0.5 * height])
        self.grad_accum[visible] += g[visible].norm(dim=-1)
        self.count[visible] += 1
        r = radii.detach().to(self.max_radius.dtype).amax(dim=-1) / max(width, height)
        self.max_radius = torch.maximum(self.max_radius, torch.where(visible, r, 0.0))

    def step(
        self,
        model: DeformableGaussians,
        optimizer: torch.optim.Optimizer,
        iteration: int,
        scene_extent: float,
    ) -> dict[str, int]:
        """Densify and prune after `iteration` when the schedule says so; returns counts of
        what happened (cloned, split, pruned). Opacity resets are `reset_due`'s business."""
        c = self.config
        out = {"cloned": 0, "split": 0, "pruned": 0}
        if self.densify_due(iteration):
            prune_big = iteration > c.opacity_reset_interval
            out = self.densify_and_prune(model, optimizer, scene_extent, prune_big)
        elif c.prune_after_stop and iteration >= c.stop and iteration % c.interval == 0:
            out["pruned"] = self.prune_transparent(model, optimizer)
        return out

    def densify_due(self, iteration: int) -> bool:
        """Whether `step` densifies after `iteration` (every `interval` in [start, stop))."""
        c = self.config
        return c.start <= iteration < c.stop and iteration % c.interval == 0 and iteration > 0

    @torch.no_grad()
    def prune_transparent(
        self, model: DeformableGaussians, optimizer: torch.optim.Optimizer
    ) -> int:
        """Remove the Gaussians with opacity below `prune_opacity` (never all of them);
        returns how many went. The densification statistics follow the rows."""
        keep = torch.sigmoid(model.opacity_logits.data) >= self.config.prune_opacity
        n_prune = int((~keep).sum())
        if n_prune == 0 or n_prune == model.num_gaussians:
            return 0
        self.pruned_transparent += n_prune
        self._ensure(model.num_gaussians)
        self.grad_accum, self.count = self.grad_accum[keep], self.count[keep]
        self.max_radius = self.max_radius[keep]
        self._keep(model, optimizer, keep)
        return n_prune

    def reset_due(self, iteration: int) -> bool:
        """Whether the opacity reset scheduled after `iteration` is due. The trainer applies it
        at the start of the next iteration, so evaluations and checkpoints taken at the end
        of `iteration` see the model before the reset rather than washed-out opacities."""
        c = self.config
        return iteration > 0 and iteration % c.opacity_reset_interval == 0 and iteration < c.stop

    @torch.no_grad()
    def densify_and_prune(
        self,
        model: DeformableGaussians,
        optimizer: torch.optim.Optimizer,
        scene_extent: float,
        prune_big: bool = False,
    ) -> dict[str, int]:
        """Clone small high-gradient Gaussians, split large ones, prune transparent ones and,
        when `prune_big`, those too large on screen or in the world (see `DensifyConfig`)."""
        c = self.config
        n = model.num_gaussians
        self._ensure(n)
        # Screen sizes are per row before the rows move; clones inherit them, children not.
        big_on_screen = torch.zeros(n, dtype=torch.bool)
        if prune_big and c.prune_screen_fraction > 0:
            big_on_screen = self.max_radius > c.prune_screen_fraction
        avg = self.grad_accum / self.count.clamp_min(1)
        big = model.log_scales.exp().max(dim=-1).values > c.percent_dense * scene_extent
        hot = avg >= c.grad_threshold
        room = max(0, c.max_gaussians - n)
        clone = hot & ~big
        split = hot & big
        # Respect the cap: clones add 1 row each, splits add split_count - 1.
        if int(clone.sum()) + int(split.sum()) * (c.split_count - 1) > room:
            order = torch.argsort(avg, descending=True)
            budget, keep = room, torch.zeros(n, dtype=torch.bool)
            for i in order.tolist():
                cost = 1 if clone[i] else c.split_count - 1
                if not hot[i] or cost > budget:
                    continue
                keep[i] = True
                budget -= cost
            clone &= keep
            split &= keep
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone or n_split:
            # New rows: clones copy; split children are sampled inside the parent and shrunk.
            stds = model.log_scales.data[split].exp().repeat(c.split_count, 1)
            rot = quat_to_matrix(model.quats.data[split]).repeat(c.split_count, 1, 1)
            noise = torch.randn(stds.shape, generator=self.generator, dtype=stds.dtype)
            offsets = (rot @ (noise * stds).unsqueeze(-1)).squeeze(-1)
            shrink = math.log(0.8 * c.split_count)

            def grow(name: str, t: Tensor, is_state: bool) -> Tensor:
                cloned = t[clone]
                kids = t[split].repeat(c.split_count, *([1] * (t.dim() - 1)))
                if not is_state:
                    if name == "means":
                        kids = kids + offsets
                    elif name == "log_scales":
                        kids = kids - shrink
                else:
                    cloned, kids = torch.zeros_like(cloned), torch.zeros_like(kids)
                # Parents of splits are removed below; append clones and children.
                return torch.cat([t, cloned, kids], dim=0)

            _replace_rows(optimizer, model, grow)
            keep = torch.ones(model.num_gaussians, dtype=torch.bool)
            keep[:n][split] = False
            kids = torch.zeros(n_split * c.split_count, dtype=torch.bool)
            big_on_screen = torch.cat([big_on_screen, big_on_screen[clone], kids])[keep]
            self._keep(model, optimizer, keep)
        opacity = torch.sigmoid(model.opacity_logits.data)
        prune = (opacity < c.prune_opacity) | big_on_screen
        if prune_big and c.prune_world_scale > 0:
            world = model.log_scales.data.exp().max(dim=-1).values
            prune |= world > c.prune_world_scale * scene_extent
        n_prune = int(prune.sum())
        if n_prune and n_prune < model.num_gaussians:
            self._keep(model, optimizer, ~prune)
        self.grad_accum = torch.zeros(model.num_gaussians)
        self.count = torch.zeros(model.num_gaussians)
        self.max_radius = torch.zeros(model.num_gaussians)
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}

    def _keep(
        self, model: DeformableGaussians, optimizer: torch.optim.Optimizer, keep: Tensor
    ) -> None:
        _replace_rows(optimizer, model, lambda name, t, is_state: t[keep])

    @torch.no_grad()
    def reset_opacity(self, model: DeformableGaussians, optimizer: torch.optim.Optimizer) -> None:
        """Clamp opacities to at most 0.01 and zero their Adam moments (3DGS opacity reset)."""
        cap = math.log(0.01 / 0.99)

        def reset(name: str, t: Tensor, is_state: bool) -> Tensor:
            if name != "opacity_logits":
                return t
            return torch.zeros_like(t) if is_state else t.clamp_max(cap)

        _replace_rows(optimizer, model, reset)
