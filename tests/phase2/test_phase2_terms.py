"""Phase 2's loss terms (sync4d.phase2.terms): the paper's regularisers as objects read from
the config, and a term plugged into the trainer."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import pytest
import torch

from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase2 import Phase2Config, phase2_trainer
from sync4d.phase2.terms import (
    TERMS,
    LossTerm,
    ResidualEnergy,
    RigidShareHinge,
    TermContext,
    default_terms,
)

SMALL = syn.SyntheticConfig(size=64, frames=8, train_cameras=4, test_cameras=1, test_every=4,
                            supersample=1)  # fmt: skip


def test_default_terms_read_their_weight_and_start_from_the_config() -> None:
    p2 = Phase2Config(lambda_vel=0.5, velocity_start=7, tau=0.4, modulation=False)
    terms = default_terms(p2)
    assert [t.name for t in terms] == ["smooth", "id", "share", "vel", "res"]
    for t in terms:
        assert t.weight == getattr(p2, t.weight_key) and t.start == getattr(p2, t.start_key)
    assert terms[3].weight == 0.5 and terms[3].start == 7
    assert isinstance(terms[2], RigidShareHinge) and terms[2].tau == 0.4
    assert isinstance(terms[4], ResidualEnergy) and not terms[4].modulated
    no_hinge = default_terms(dataclasses.replace(p2, hinge=False))
    assert [t.name for t in no_hinge] == ["smooth", "id", "vel", "res"]
    # Each term's start is a start field the budget scales.
    fields = {f.name: f for f in dataclasses.fields(Phase2Config)}
    assert all(cls.start_key in fields and cls.start_key.endswith("_start") for cls in TERMS)


@dataclasses.dataclass(frozen=True)
class _Pull(LossTerm):
    """A term of the kind a new regulariser is: M_phi's translations pulled to 0."""

    name: ClassVar[str] = "pull"
    seen: list = dataclasses.field(default_factory=list, compare=False)

    def observe(self, ctx: TermContext) -> None:
        self.seen.append(ctx.iteration)

    def value(self, ctx: TermContext) -> torch.Tensor:
        return (ctx.motion.translations**2).sum()


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return load_scene(syn.write_synthetic_scene(tmp_path_factory.mktemp("synthetic"), SMALL))


def test_a_plugged_term_acts_from_its_start(scene) -> None:
    g = torch.Generator().manual_seed(0)
    model = DeformableGaussians.random_in_box(
        300, torch.tensor([-1.0, -1.0, 0.0]), torch.tensor([1.0, 1.0, 1.0]), generator=g,
        sh_degree=0,
    )  # fmt: skip
    p2 = Phase2Config(motion_start=1, velocity_start=0, residual_start=0, warmup_start=0,
                      warmup_end=2, skip_still_scene=False)  # fmt: skip
    pull = _Pull(weight=0.5, start=3)
    tr = phase2_trainer(model, scene, Phase1Config(), p2, 10, threads=1,
                        terms=[*default_terms(p2), pull]).trainer  # fmt: skip
    stats = [tr.step() for _ in range(4)]
    assert pull.seen == [1, 2, 3, 4]  # observed from M_phi's start, before its own
    assert "L_pull" not in stats[1] and "L_pull" in stats[2] and "L_pull" in stats[3]
    assert all(math.isfinite(v) for s in stats for v in s.values())
    # Only the plugged term: the others are not computed.
    alone = phase2_trainer(model, scene, Phase1Config(), p2, 10, threads=1, terms=[pull]).trainer
    s = alone.step()
    assert [k for k in s if k.startswith("L_")] == [] and "rho" in s
    s = [alone.step() for _ in range(2)][-1]
    assert [k for k in s if k.startswith("L_")] == ["L_pull"]
