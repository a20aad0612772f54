"""Phase 2's loss terms (paper Eqs. 8-12): each regulariser is one object with its weight and
start iteration, both read from `Phase2Config` (`from_config`), so the config keys stay as
they are. The motion strategy's `loss` builds one `TermContext` per iteration (the deformed
and M_phi-carried positions, the residuals, M_phi itself) and sums the terms' weighted losses.

The protocol (`LossTerm`): `name` (reported as ``L_<name>``), `weight`, `start`;
`observe(ctx)`, called on every iteration the auxiliary losses run (from M_phi's start, before
the term's own start: the residual modulation's EMA updates there); `applies(ctx)`, from
`start` on (every iteration with `simultaneous`) and whatever else the term needs;
`value(ctx)`, the unweighted loss. The trainer visits the terms in order (observe, then
applies and value) and sums ``weight * value`` in that order: the order of the sum, and of
the autograd graph the terms build, is part of the result's bits.

A new term is one class here with `weight_key` and `start_key` naming its `Phase2Config`
fields, added to `TERMS` (or passed to `phase2_trainer(terms=...)`). Its start field, declared
`ranged(..., scales=0)` as every ``*_start`` field is (a test checks), scales with
`fit --iters` (`sync4d.config.phase2_budget`) with no list to update.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, ClassVar

import numpy as np
import torch
from torch import Tensor

from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase2.motion import ObjectMotion

if TYPE_CHECKING:
    from collections.abc import Callable

    from sync4d.phase2.config import Phase2Config

__all__ = [
    "IdentityPrior",
    "LossTerm",
    "ResidualEnergy",
    "RigidShareHinge",
    "Smoothness",
    "TERMS",
    "TermContext",
    "VelocityCoherence",
    "default_terms",
    "scale_grad",
]


def rigid_share(x0: Tensor, x_obj: Tensor, residual: Tensor, eps: float = 1e-6) -> Tensor:
    """Per-Gaussian rigid share ||x~ - x0|| / (||x~ - x0|| + ||r|| + eps) [N] (Eq. 9's terms)."""
    shared = (x_obj - x0).norm(dim=-1)
    return shared / (shared + residual.norm(dim=-1) + eps)


@dataclass
class TermContext:
    """What the terms of one iteration read: its `iteration` (and `simultaneous`, every term
    on from 0), M_phi (`motion`), the `model`, the object `labels` [N], `static` objects [K],
    the stored frame `times` [T] and this frame's index `j` among them, the warm-up factor `w`
    on the scene's gradient, D_theta's positions `x` [N, 3] and the canonical ones `x0`
    [N, 3] (both with that factor on their gradient), M_phi's `x_obj` [N, 3] (Eq. 5), the
    residuals `r` = x - x_obj (Eq. 6), the rigid share's `share_eps` and `modulate`, which
    updates the residual EMA and returns m_i (`MotionStrategy.modulation_weights`).
    `rho` and `residual_norm` are computed on first use; `modulation` is m_i [N] once the
    residual term has observed this iteration."""

    iteration: int
    simultaneous: bool
    motion: ObjectMotion
    model: DeformableGaussians
    labels: Tensor
    static: Tensor
    times: np.ndarray
    j: int
    w: float
    x: Tensor
    x0: Tensor
    x_obj: Tensor
    r: Tensor
    share_eps: float
    modulate: Callable[[Tensor], Tensor]
    modulation: Tensor | None = None

    def active(self, start: int) -> bool:
        """Whether a term starting at iteration `start` acts now."""
        return self.simultaneous or self.iteration >= start

    @cached_property
    def rho(self) -> Tensor:
        """The mean rigid share (Eq. 9's rho, over every Gaussian)."""
        return rigid_share(self.x0, self.x_obj, self.r, self.share_eps).mean()

    @cached_property
    def residual_norm(self) -> Tensor:
        """||r_i|| [N]."""
        return self.r.norm(dim=-1)


def scale_grad(x: Tensor, scale: float) -> Tensor:
    """`x` in the forward pass, with its gradient multiplied by `scale`."""
    if scale >= 1.0:
        return x
    return x.detach() + scale * (x - x.detach())


@dataclass(frozen=True)
class LossTerm(abc.ABC):
    """One Phase 2 regulariser: `weight` times its `value` from iteration `start` on.
    Subclasses name themselves (`name`) and their `Phase2Config` fields (`weight_key`,
    `start_key`) and give `value`."""

    name: ClassVar[str] = ""
    weight_key: ClassVar[str] = ""
    start_key: ClassVar[str] = ""
    weight: float
    start: int

    @classmethod
    def from_config(cls, p: Phase2Config) -> LossTerm | None:
        """This term with `p`'s weight and start; None when `p` switches it off."""
        return cls(getattr(p, cls.weight_key), getattr(p, cls.start_key))

    def observe(self, ctx: TermContext) -> None:
        """Called on every iteration the auxiliary losses run, before `applies`; a term
        that keeps state between iterations overrides it (nothing to do by default)."""
        return None

    def applies(self, ctx: TermContext) -> bool:
        """Whether the term acts at this iteration: from `start` on."""
        return ctx.active(self.start)

    @abc.abstractmethod
    def value(self, ctx: TermContext) -> Tensor:
        """The unweighted loss (a scalar)."""

    def loss(self, ctx: TermContext) -> Tensor:
        """`weight` times `value`."""
        return self.weight * self.value(ctx)


@dataclass(frozen=True)
class Smoothness(LossTerm):
    """M_phi's temporal smoothness at frame j (Eq. 11), from M_phi's start."""

    name: ClassVar[str] = "smooth"
    weight_key: ClassVar[str] = "lambda_smooth"
    start_key: ClassVar[str] = "motion_start"

    def value(self, ctx: TermContext) -> Tensor:
        return ctx.motion.smoothness(ctx.j)


@dataclass(frozen=True)
class IdentityPrior(LossTerm):
    """The identity prior on static objects' transforms at frame j (Eq. 12)."""

    name: ClassVar[str] = "id"
    weight_key: ClassVar[str] = "lambda_id"
    start_key: ClassVar[str] = "motion_start"

    def value(self, ctx: TermContext) -> Tensor:
        return ctx.motion.identity_prior(ctx.j, ctx.static)


@dataclass(frozen=True)
class RigidShareHinge(LossTerm):
    """The rigid-share hinge max(0, tau - rho)^2 (Eq. 9); off without `hinge`."""

    name: ClassVar[str] = "share"
    weight_key: ClassVar[str] = "lambda_share"
    start_key: ClassVar[str] = "motion_start"
    tau: float = 0.35

    @classmethod
    def from_config(cls, p: Phase2Config) -> LossTerm | None:
        return cls(p.lambda_share, p.motion_start, p.tau) if p.hinge else None

    def value(self, ctx: TermContext) -> Tensor:
        return torch.clamp(self.tau - ctx.rho, min=0.0) ** 2


@dataclass(frozen=True)
class VelocityCoherence(LossTerm):
    """Velocity coherence between frames j-1 and j (Eq. 10): D_theta's displacement minus
    M_phi's, squared; from frame 1 on."""

    name: ClassVar[str] = "vel"
    weight_key: ClassVar[str] = "lambda_vel"
    start_key: ClassVar[str] = "velocity_start"

    def applies(self, ctx: TermContext) -> bool:
        return ctx.j > 0 and ctx.active(self.start)

    def value(self, ctx: TermContext) -> Tensor:
        t_prev = float(ctx.times[ctx.j - 1])
        x_prev = scale_grad(ctx.model.at_time(t_prev)[0], ctx.w)
        x_obj_prev = ctx.motion(ctx.x0, ctx.labels, t_prev)
        d = (ctx.x - x_prev) - (ctx.x_obj - x_obj_prev)
        return (d * d).sum(-1).mean()


@dataclass(frozen=True)
class ResidualEnergy(LossTerm):
    """The modulated residual energy mean((1 - m_i) ||r_i||^2) (Eq. 8). Its modulation m_i
    (a sigmoid of the z-scored EMA of ||r_i||) updates on every iteration from M_phi's start,
    before the term's own; without `modulated` m_i = 0 (every residual penalised)."""

    name: ClassVar[str] = "res"
    weight_key: ClassVar[str] = "lambda_res"
    start_key: ClassVar[str] = "residual_start"
    modulated: bool = True

    @classmethod
    def from_config(cls, p: Phase2Config) -> LossTerm | None:
        return cls(p.lambda_res, p.residual_start, p.modulation)

    def observe(self, ctx: TermContext) -> None:
        rn = ctx.residual_norm
        ctx.modulation = ctx.modulate(rn) if self.modulated else torch.zeros_like(rn)

    def value(self, ctx: TermContext) -> Tensor:
        rn, m = ctx.residual_norm, ctx.modulation
        assert m is not None  # set by `observe`
        return ((1.0 - m) * rn * rn).mean()


#: The paper's terms, in the order their losses are summed.
TERMS: tuple[type[LossTerm], ...] = (
    Smoothness,
    IdentityPrior,
    RigidShareHinge,
    VelocityCoherence,
    ResidualEnergy,
)


def default_terms(p: Phase2Config) -> list[LossTerm]:
    """The `TERMS` `p` switches on, with its weights and starts."""
    return [t for cls in TERMS if (t := cls.from_config(p)) is not None]
