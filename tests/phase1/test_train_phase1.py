"""Phase 1 loop: on a small scene rendered from known Gaussians, training lowers the loss."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from support.scenes import orbit_scene, orbit_student
from support.training import train
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.trainer import Phase1Trainer


def test_training_reduces_the_photometric_loss(tmp_path: Path) -> None:
    scene, gt = orbit_scene(tmp_path)
    model = orbit_student(gt, 1, jitter=0.05)
    cfg = Phase1Config(densify=DensifyConfig(start=10_000))
    trainer = Phase1Trainer(model, scene, cfg, total_iterations=150, threads=1)
    first = [trainer.step()["loss"] for _ in range(5)]
    train(trainer, 140)
    last = [trainer.step()["loss"] for _ in range(5)]
    assert np.mean(last) < 0.5 * np.mean(first), (first, last)
    assert trainer.iteration == 150


def test_densification_runs_inside_the_loop(tmp_path: Path) -> None:
    scene, gt = orbit_scene(tmp_path)
    model = DeformableGaussians(gt.means.data.clone(), None, sh_degree=0)
    cfg = Phase1Config(densify=DensifyConfig(start=5, interval=5, stop=40, grad_threshold=1e-6))
    trainer = Phase1Trainer(model, scene, cfg, total_iterations=20, threads=1)
    stats = train(trainer, 20)
    assert stats["gaussians"] > 40  # low threshold: clones/splits happened
    # Parameters and optimizer state still line up after densification.
    for group in trainer.optimizer.param_groups:
        for p in group["params"]:
            st = trainer.optimizer.state.get(p)
            if st:
                assert st["exp_avg"].shape == p.shape


def test_opacity_reset_applies_at_the_start_of_the_next_iteration(tmp_path: Path) -> None:
    """An evaluation or checkpoint at a reset iteration sees the trained opacities; the reset
    lands when the next iteration starts."""
    scene, gt = orbit_scene(tmp_path)
    model = DeformableGaussians(gt.means.data.clone(), None, sh_degree=0)
    with torch.no_grad():
        model.opacity_logits.fill_(2.0)
    dcfg = DensifyConfig(start=10_000, stop=100, opacity_reset_interval=3)
    trainer = Phase1Trainer(model, scene, Phase1Config(densify=dcfg), 10, threads=1)
    train(trainer, 3)
    assert float(torch.sigmoid(model.opacity_logits.detach()).min()) > 0.5
    trainer.step()
    assert float(torch.sigmoid(model.opacity_logits.detach()).max()) < 0.05


def test_static_and_learning_rate_warmups_hold_d_theta_back(tmp_path: Path) -> None:
    """During the static warm-up D_theta is off (its weights do not move); then its and the
    embeddings' rates ramp linearly to the schedule over `lr_deform_warmup` iterations."""
    scene, gt = orbit_scene(tmp_path)
    model = DeformableGaussians(gt.means.data.clone(), None, sh_degree=0,
                                generator=torch.Generator().manual_seed(2))  # fmt: skip
    cfg = Phase1Config(static_warmup=4, lr_deform_warmup=10,
                       densify=DensifyConfig(start=10_000))  # fmt: skip
    trainer = Phase1Trainer(model, scene, cfg, total_iterations=40, threads=1)
    lr = {g["name"]: g for g in trainer.optimizer.param_groups}
    head = model.deform.head.weight.detach().clone()
    train(trainer, 4)
    assert not trainer.deform_active()
    assert torch.equal(model.deform.head.weight.detach(), head)
    train(trainer, 1)  # iteration 5: the first with D_theta, at a tenth of its rate
    assert trainer.deform_active()
    full = trainer.decayed(cfg.lr_deform, cfg.lr_deform_final)
    assert math.isclose(lr["deform"]["lr"], 0.1 * full, rel_tol=1e-9)
    assert not torch.equal(model.deform.head.weight.detach(), head)
    train(trainer, 9)  # iteration 14: the ramp is over
    full = trainer.decayed(cfg.lr_deform, cfg.lr_deform_final)
    assert math.isclose(lr["deform"]["lr"], full, rel_tol=1e-9)
    embed = trainer.decayed(cfg.lr_embed, cfg.lr_embed_final)
    assert math.isclose(lr["embeddings"]["lr"], embed, rel_tol=1e-9)
