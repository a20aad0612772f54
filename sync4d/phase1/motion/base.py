"""The interface of Phase 1's motion (`Motion`), its registry and the checkpoint round trip
(the package docstring says how they fit)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

from torch import Tensor, nn

if TYPE_CHECKING:
    from sync4d.phase1.config import Phase1Config
    from sync4d.phase1.gaussians import DeformableGaussians
    from sync4d.phase1.trainer import Phase1Trainer

__all__ = [
    "MOTIONS",
    "ControlPoints",
    "Motion",
    "motion_for",
    "motion_from_state",
    "register_motion",
]


@dataclass(frozen=True)
class ControlPoints:
    """Points that carry a motion model's motion, for Phase 2's fit of M_phi on a few hundred
    trajectories instead of every Gaussian's: canonical `positions` [M, 3], each Gaussian's
    points `index` [N, K] (int64) and its weights on them `weights` [N, K] (rows sum to 1),
    and `offset(t)`: the points' displacements [M, 3] from `positions` at time t."""

    positions: Tensor
    index: Tensor
    weights: Tensor
    offset: Callable[[float], Tensor]


class Motion(ABC):
    """What moves Phase 1's Gaussians: every hook does what the per-Gaussian model needs
    (nothing) unless overridden. Model hooks get the model; trainer hooks get the trainer,
    whose public names (`iteration`, `config`, `optimizer`, `model`, `extent`, `densifier`)
    they read."""

    #: The registry name, the value of `Phase1Config.motion`.
    name: ClassVar[str] = ""

    def __init__(self, config: Phase1Config | None = None) -> None:
        self.config = config

    # -- the model ---------------------------------------------------------------------------
    @property
    def current(self) -> str:
        """What moves the Gaussians now (a stage may differ from `name`): the checkpoint's
        ``"motion"`` and `DeformableGaussians.motion`."""
        return self.name

    @abstractmethod
    def deformed(self, model: DeformableGaussians, t: float, q0: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        """The Gaussians' means [N, 3], unit quaternions [N, 4] (`q0`: the canonical ones,
        normalised) and scales [N, 3] at time `t`. Every motion defines it."""

    def network(self, model: DeformableGaussians, t: float) -> tuple[Tensor, ...]:
        """The motion's learnt function alone at `t` (`bench step`'s D_theta column): D_theta
        on the rows the motion evaluates it on; by default the whole deformed state."""
        quats = model.quats / model.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return self.deformed(model, t, quats)

    def modules(self) -> dict[str, nn.Module]:
        """The modules holding this motion's parameters, by the attribute name the model
        registers them under (`DeformableGaussians.attach_motion_modules`): their parameters
        are the model's (`named_parameters`, the watchdog's names)."""
        return {}

    def render_inputs(self) -> dict[str, Tensor]:
        """Tensors of the last `deformed` call the watchdog checks before a render, by name."""
        return {}

    def state(self) -> tuple[dict[str, Tensor], dict]:
        """Tensors and JSON-ready settings a checkpoint holds for this motion (besides the
        Gaussians and D_theta); the settings name it under ``"motion"`` unless it is the
        per-Gaussian model."""
        return {}, {}

    def load(self, model: DeformableGaussians, tensors: dict[str, Tensor], meta: dict) -> None:
        """Load what `state` wrote, for `model` (its Gaussians loaded). KeyError for a missing
        tensor or setting, ValueError for one that does not fit."""
        return None  # a hook: nothing unless a motion overrides it

    def rows_changed(self, fn: Callable[[str, Tensor, bool], Tensor]) -> None:
        """Densification replaced the Gaussian rows by `fn(name, tensor, is_state)`: carry
        per-Gaussian tensors of the motion through it."""
        return None  # a hook: nothing unless a motion overrides it

    def control_points(self, model: DeformableGaussians) -> ControlPoints | None:
        """The points that carry the motion (None: every Gaussian carries its own)."""
        return None

    def counts(self) -> dict[str, int]:
        """Sizes to report (``"nodes"``: M), {} when nothing but the Gaussians."""
        return {}

    # -- the trainer -------------------------------------------------------------------------
    def for_config(self, config: Phase1Config) -> Motion:
        """The motion a trainer with `config` uses for this model: this one, configured, if
        it is the configured kind or holds learnt state; else a new one of the configured
        kind (`motion_for`)."""
        if self.name == config.motion:
            self.config = config
            return self
        return motion_for(config)

    def param_groups(self, trainer: Phase1Trainer) -> list[tuple[str, Tensor, float]]:
        """Adam groups (name, parameter, rate) beyond the Gaussians' and D_theta's."""
        return []

    def begin_step(self, trainer: Phase1Trainer) -> None:
        """At the start of an iteration (`trainer.iteration` already counts it): a stage
        change (nodes sampled, their groups added to `trainer.optimizer`)."""
        return None  # a hook: nothing unless a motion overrides it

    def update_learning_rates(self, trainer: Phase1Trainer, ramp: float) -> None:
        """Set this iteration's rates of the groups `param_groups` added (`ramp`: D_theta's
        warm-up factor)."""
        return None  # a hook: nothing unless a motion overrides it

    def regulariser(self, trainer: Phase1Trainer, t: float) -> Tensor | None:
        """A term added to the loss for a frame at time `t` (weight included), while D_theta
        is on."""
        return None

    def after_optimizer_step(self, trainer: Phase1Trainer) -> None:
        """After Adam's step, before densification."""
        return None  # a hook: nothing unless a motion overrides it

    def step_stats(self, trainer: Phase1Trainer) -> dict[str, float]:
        """Scalars of the step's report."""
        return {}

    def skip_counts(self, trainer: Phase1Trainer) -> dict[str, int | float]:
        """What this motion skipped in this process (the `Skipped` event's counts)."""
        return {}

    def static_set_applies(self) -> bool:
        """Whether Phase 1's static Gaussians (skipping D_theta) apply to this motion now."""
        return True

    def watched_units(self) -> dict[str, str]:
        """The unit of the rows of this motion's parameters in the model's
        `named_parameters` (the watchdog's messages)."""
        return {}

    def last_regulariser(self) -> float | None:
        """The last `regulariser` value (None before one)."""
        return None

    def to_final_stage(self, trainer: Phase1Trainer) -> None:
        """Move to the motion's trained stage now (a benchmark of its step)."""
        return None  # a hook: nothing unless a motion overrides it


#: Registered motions by name (`register_motion`).
MOTIONS: dict[str, type[Motion]] = {}


def register_motion(cls: type[Motion]) -> type[Motion]:
    """Register `cls` under `cls.name` (usable as a decorator); a name is registered once."""
    if not cls.name:
        raise ValueError(f"{cls.__name__}: a motion needs a name")
    if MOTIONS.get(cls.name, cls) is not cls:
        raise ValueError(f"a motion named {cls.name!r} is registered already")
    MOTIONS[cls.name] = cls
    return cls


def motion_for(config: Phase1Config) -> Motion:
    """A new motion of the kind `config.motion` names."""
    try:
        return MOTIONS[config.motion](config)
    except KeyError:
        raise ValueError(f"unknown motion model {config.motion!r} (registered: "
                         f"{', '.join(MOTIONS)})") from None  # fmt: skip


def motion_from_state(model: DeformableGaussians, tensors: dict[str, Tensor], meta: dict
                      ) -> Motion:  # fmt: skip
    """The motion a checkpoint recorded (``"motion"``, absent: the per-Gaussian model),
    loaded for `model`."""
    name = meta.get("motion", "gaussians")
    if name not in MOTIONS:
        raise ValueError(f"unknown motion model {name!r} (expected one of "
                         f"{', '.join(repr(m) for m in MOTIONS)})")  # fmt: skip
    motion = MOTIONS[name]()
    motion.load(model, tensors, meta)
    return motion
