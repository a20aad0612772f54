"""Phase 1's motion is a plug-in (`sync4d.phase1.motion`): a toy motion model defined here, in
one file with one registry row, is chosen by `phase1.motion`, trains (its parameters get Adam
groups and move), round-trips through a checkpoint, and the trainer never asks which motion
it runs."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

from support.scenes import orbit_scene, orbit_student
from sync4d.config import ConfigError, config_from_dict
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.motion import MOTIONS, Motion, register_motion
from sync4d.phase1.trainer import Phase1Trainer


class Drift(Motion):
    """Every Gaussian drifts with one learnt velocity: x(t) = x0 + v t."""

    name = "drift"

    def __init__(self, config=None) -> None:
        super().__init__(config)
        self.velocity = nn.ParameterDict({"v": nn.Parameter(torch.zeros(3))})

    def modules(self) -> dict[str, nn.Module]:
        return {"drift": self.velocity}

    def deformed(self, model, t, q0) -> tuple[Tensor, Tensor, Tensor]:
        return model.means + self.velocity["v"] * t, q0, torch.exp(model.log_scales)

    def param_groups(self, trainer) -> list[tuple[str, Tensor, float]]:
        return [("drift", self.velocity["v"], 1e-2)]

    def state(self) -> tuple[dict[str, Tensor], dict]:
        return {"drift.v": self.velocity["v"].detach()}, {"motion": "drift"}

    def load(self, model, tensors, meta) -> None:
        with torch.no_grad():
            self.velocity["v"].copy_(tensors["drift.v"])

    def watched_units(self) -> dict[str, str]:
        return {"drift.v": "axes"}


@pytest.fixture
def drift():
    register_motion(Drift)  # the one row
    yield Drift
    MOTIONS.pop("drift")


def test_a_registered_motion_is_configured_trained_and_checkpointed(tmp_path: Path,
                                                                    drift) -> None:
    cfg = config_from_dict({"phase1": {"motion": "drift"}}, "test").phase1
    assert cfg.motion == "drift"
    scene, gt = orbit_scene(tmp_path)
    cfg = Phase1Config(densify=DensifyConfig(start=10_000), motion="drift")
    trainer = Phase1Trainer(orbit_student(gt, 1), scene, cfg, total_iterations=10, threads=1)
    model = trainer.model
    assert isinstance(model.motion_model, drift) and model.motion == "drift"
    assert [g["name"] for g in trainer.optimizer.param_groups][-1] == "drift"
    assert "drift.v" in dict(model.named_parameters())  # the watchdog sees it
    for _ in range(4):
        trainer.step()
    v = model.motion_model.velocity["v"].detach().clone()
    assert float(v.abs().sum()) > 0  # trained: Adam moved it from zero
    torch.testing.assert_close(model.at_time(1.0)[0] - model.at_time(0.0)[0],
                               v.expand(model.num_gaussians, 3))  # fmt: skip
    tensors, meta = trainer.state()
    assert meta["motion"] == "drift" and torch.equal(tensors["drift.v"], v)
    again = DeformableGaussians.from_state(tensors, meta)
    assert isinstance(again.motion_model, drift)
    torch.testing.assert_close(again.at_time(0.7)[0], model.at_time(0.7)[0])
    resumed = Phase1Trainer.from_state(tensors, meta, scene, config=cfg, threads=1)
    trainer.step()
    resumed.step()
    torch.testing.assert_close(resumed.model.motion_model.velocity["v"],
                               model.motion_model.velocity["v"], atol=0, rtol=0)  # fmt: skip


def test_an_unregistered_motion_is_refused_by_name() -> None:
    with pytest.raises(ConfigError, match="phase1.motion.*gaussians, nodes"):
        config_from_dict({"phase1": {"motion": "drift"}}, "test")
    with pytest.raises(ValueError, match="unknown motion model 'drift'"):
        DeformableGaussians.from_state(*_with_motion("drift"))


def _with_motion(name: str) -> tuple[dict, dict]:
    model = DeformableGaussians(torch.zeros(2, 3), sh_degree=0)
    tensors, meta = model.state()
    return tensors, {**meta, "motion": name}
