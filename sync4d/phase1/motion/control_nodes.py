"""Motion on control nodes (SC-GS; the maths in `sync4d.phase1.nodes`) as a Phase 1 motion:
the per-Gaussian model (`per_gaussian`) for `nodes.init_after` iterations (the coarse stage),
then `NodeMotion` sampled among the Gaussians carries the motion: D_theta on M nodes, each
Gaussian blending its K nearest; ARAP between two training times; adaptive nodes on
densification steps; the nearest-node tables refreshed on a schedule."""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch import Tensor, nn

from sync4d.phase1.motion.base import ControlPoints, Motion
from sync4d.phase1.motion.per_gaussian import (
    per_gaussian_deformed,
    per_gaussian_network,
    static_skip_counts,
)
from sync4d.phase1.nodes import (
    NodeConfig,
    NodeMotion,
    arap_loss,
    blend_weights,
    densify_nodes,
    strain_loss,
)

if TYPE_CHECKING:
    from sync4d.phase1.config import Phase1Config
    from sync4d.phase1.gaussians import DeformableGaussians
    from sync4d.phase1.trainer import Phase1Trainer

__all__ = ["NodesMotion"]


class NodesMotion(Motion):
    """Control nodes after a coarse per-Gaussian stage (`Phase1Config.nodes`). `nodes` is
    None during the coarse stage; once sampled, the model holds them as its submodule
    ``nodes`` (parameters ``nodes.positions``, ``nodes.log_radii``, ``nodes.embeddings``)."""

    name = "nodes"

    def __init__(self, config: Phase1Config | None = None) -> None:
        super().__init__(config)
        self.nodes: NodeMotion | None = None
        self._last_arap: float | None = None

    @property
    def current(self) -> str:
        return "gaussians" if self.nodes is None else "nodes"

    def modules(self) -> dict[str, nn.Module]:
        return {} if self.nodes is None else {"nodes": self.nodes}

    # -- the model ---------------------------------------------------------------------------
    def deformed(self, model: DeformableGaussians, t: float, q0: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        if self.nodes is None:
            return per_gaussian_deformed(model, t, q0)
        model.deform_rows += self.nodes.count
        return self.nodes.deformed(model.deform, model.means, q0, model.log_scales, t)

    def network(self, model: DeformableGaussians, t: float) -> tuple[Tensor, ...]:
        if self.nodes is None:
            return per_gaussian_network(model, t)
        return self.nodes.motion(model.deform, t)

    def render_inputs(self) -> dict[str, Tensor]:
        motion = None if self.nodes is None else self.nodes.last_motion
        if motion is None:
            return {}
        return dict(zip(("node_rotations", "node_shifts", "node_log_scales"), motion,
                        strict=True))  # fmt: skip

    def state(self) -> tuple[dict[str, Tensor], dict]:
        if self.nodes is None:  # the coarse stage: a per-Gaussian checkpoint
            return {}, {}
        return self.nodes.state(), {"motion": "nodes", "node_config": self.nodes.settings()}

    def load(self, model: DeformableGaussians, tensors: dict[str, Tensor], meta: dict) -> None:
        self.nodes = NodeMotion.from_state(tensors, meta["node_config"], model.num_gaussians,
                                           model.config.embed_dim)  # fmt: skip

    def rows_changed(self, fn: Callable[[str, Tensor, bool], Tensor]) -> None:
        if self.nodes is not None:  # children blend their parent's nodes until the next refresh
            self.nodes.index = fn("node_index", self.nodes.index, False)

    def control_points(self, model: DeformableGaussians) -> ControlPoints | None:
        nodes = self.nodes
        if nodes is None:
            return None
        weights = blend_weights(model.means.detach(), nodes.positions.detach(),
                                nodes.log_radii.detach(), nodes.index)  # fmt: skip
        return ControlPoints(
            positions=nodes.positions.detach(), index=nodes.index, weights=weights,
            offset=lambda t: nodes.motion(model.deform, t)[1].detach(),
        )  # fmt: skip

    def counts(self) -> dict[str, int]:
        return {} if self.nodes is None else {"nodes": self.nodes.count}

    def sample(self, model: DeformableGaussians, config: NodeConfig,
               generator: torch.Generator | None = None) -> NodeMotion:  # fmt: skip
        """Hand the motion to nodes sampled among `model`'s Gaussians (`NodeMotion.sample`:
        each node copies its Gaussian's position and embedding, so D_theta gives it that
        Gaussian's motion); the static set is cleared (the nodes make D_theta's cost
        independent of N). Returns the nodes."""
        opacities = torch.sigmoid(model.opacity_logits.detach())
        self.nodes = NodeMotion.sample(model.means.detach(), model.embeddings.detach(),
                                       opacities, config, generator)  # fmt: skip
        model.static = torch.zeros(model.num_gaussians, dtype=torch.bool)
        model.last_offsets = None
        model.attach_motion_modules()
        return self.nodes

    # -- the trainer -------------------------------------------------------------------------
    def for_config(self, config: Phase1Config) -> Motion:
        if self.nodes is not None:  # learnt nodes keep the motion, whatever the config says
            self.config = config
            return self
        return super().for_config(config)

    def _groups(self, trainer: Phase1Trainer) -> list[tuple[str, Tensor, float]]:
        nodes, c = self.nodes, trainer.config
        assert nodes is not None
        return [
            ("node_positions", nodes.positions, c.nodes.lr_position * trainer.extent),
            ("node_radii", nodes.log_radii, c.nodes.lr_radius),
            ("node_embeddings", nodes.embeddings, c.lr_embed),
        ]

    def param_groups(self, trainer: Phase1Trainer) -> list[tuple[str, Tensor, float]]:
        return [] if self.nodes is None else self._groups(trainer)

    def begin_step(self, trainer: Phase1Trainer) -> None:
        """The coarse stage over (`nodes.init_after`): sample the nodes (seeded from the
        run's seed) and give them Adam groups, after D_theta's."""
        if self.nodes is None and trainer.iteration > trainer.config.nodes.init_after:
            self.to_final_stage(trainer)

    def to_final_stage(self, trainer: Phase1Trainer) -> None:
        if self.nodes is not None:
            return
        generator = torch.Generator().manual_seed(trainer.config.seed + 1)
        self.sample(trainer.model, trainer.config.nodes, generator)
        for name, p, lr in self._groups(trainer):
            trainer.optimizer.add_param_group({"params": [p], "name": name, "lr": lr})

    def update_learning_rates(self, trainer: Phase1Trainer, ramp: float) -> None:
        c = trainer.config
        for g in trainer.optimizer.param_groups:
            if g["name"] == "node_embeddings":
                g["lr"] = ramp * trainer.decayed(c.lr_embed, c.lr_embed_final)
            elif g["name"] == "node_positions":
                final = c.nodes.lr_position * c.lr_means_final / c.lr_means
                g["lr"] = trainer.decayed(c.nodes.lr_position, final) * trainer.extent

    def arap_weight(self, trainer: Phase1Trainer) -> float:
        """`nodes.arap_weight`, falling linearly to zero from the coarse stage's end to
        `nodes.arap_until` when that is set."""
        c = trainer.config.nodes
        if c.arap_until <= 0:
            return c.arap_weight
        start = c.init_after
        left = (c.arap_until - trainer.iteration) / max(1, c.arap_until - start)
        return c.arap_weight * min(1.0, max(0.0, left))

    def regulariser(self, trainer: Phase1Trainer, t: float) -> Tensor | None:
        """The node graph's priors: the ARAP loss (`arap_weight`) between the node motion at
        the frame's time `t` (the render's) and at a second training time drawn from a
        generator seeded by the iteration (so a resumed run draws the same), plus
        `nodes.strain_weight` times the strain prior at `t`."""
        nodes, c = self.nodes, trainer.config
        if nodes is None or nodes.last_motion is None:
            return None
        terms: list[Tensor] = []
        weight = self.arap_weight(trainer)
        if weight > 0:
            times = trainer.train_times
            t2 = times[random.Random(c.seed * 1_000_003 + trainer.iteration)
                       .randrange(len(times))]  # fmt: skip
            if len(times) > 1 and t2 == t:
                t2 = times[(times.index(t2) + 1) % len(times)]
            arap = arap_loss(nodes.positions, nodes.edges, nodes.last_motion,
                             nodes.motion(trainer.model.deform, t2))  # fmt: skip
            self._last_arap = float(arap.detach())
            terms.append(weight * arap)
        if c.nodes.strain_weight > 0:
            strain = strain_loss(nodes.positions, nodes.edges, nodes.last_motion)
            terms.append(c.nodes.strain_weight * strain)
        return sum(terms[1:], terms[0]) if terms else None

    def last_regulariser(self) -> float | None:
        return self._last_arap

    def after_optimizer_step(self, trainer: Phase1Trainer) -> None:
        """Adaptive nodes on Gaussian densification steps (before the densifier resets its
        statistics) until `nodes.densify_until`, and the nearest-node tables' refresh every
        `nodes.refresh_every` iterations."""
        nodes, c = self.nodes, trainer.config.nodes
        if nodes is None:
            return
        it, densifier, model = trainer.iteration, trainer.densifier, trainer.model
        if densifier.densify_due(it) and it <= c.densify_until and \
                densifier.count.shape[0] == model.num_gaussians:  # fmt: skip
            grad = densifier.grad_accum / densifier.count.clamp_min(1)
            densify_nodes(nodes, model.means.detach(), grad, trainer.optimizer)
        elif it % c.refresh_every == 0:
            nodes.refresh(model.means.detach())

    def step_stats(self, trainer: Phase1Trainer) -> dict[str, float]:
        if self.nodes is not None:
            return {"nodes": float(self.nodes.count)}
        if trainer.config.static.enabled:
            return {"static": float(trainer.model.static.sum())}
        return {}

    def skip_counts(self, trainer: Phase1Trainer) -> dict[str, int | float]:
        nodes = self.nodes
        if nodes is not None:
            return {"nodes": nodes.count, "nodes_from": trainer.config.nodes.init_after + 1,
                    "nodes_added": nodes.added, "nodes_removed": nodes.removed}  # fmt: skip
        return static_skip_counts(trainer.model) if trainer.config.static.enabled else {}

    def static_set_applies(self) -> bool:
        return self.nodes is None  # the nodes' cost does not depend on N

    def watched_units(self) -> dict[str, str]:
        return {f"nodes.{n}": "nodes" for n in NodeMotion.PER_NODE}
