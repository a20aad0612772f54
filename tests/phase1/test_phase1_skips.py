"""Phase 1 skips beyond static Gaussians (`test_static.py`): coarse iterations render
fewer pixels, the motion-sparsity loss drives unneeded offsets to zero, and a schedule that
prunes Gaussians too transparent to ever be drawn. Each switch changes what is computed
(counters), not only the time."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from support.scenes import densify_case, orbit_scene, orbit_student
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.static import StaticConfig, motion_sparsity
from sync4d.phase1.trainer import Phase1Trainer


def _trainer(tmp_path: Path, **config) -> Phase1Trainer:
    scene, gt = orbit_scene(tmp_path)
    model = orbit_student(gt, 1)
    cfg = Phase1Config(densify=DensifyConfig(start=10_000), **config)
    return Phase1Trainer(model, scene, cfg, total_iterations=20, threads=1)


def test_coarse_iterations_render_a_smaller_image_then_the_full_one(tmp_path: Path) -> None:
    trainer = _trainer(tmp_path, coarse_iterations=5, coarse_scale=0.5)
    sizes = []
    render = trainer.model.render

    def spy(camera, *a, **kw):
        sizes.append((camera.width, camera.height))
        return render(camera, *a, **kw)

    trainer.model.render = spy
    for _ in range(8):
        stats = trainer.step()
        assert math.isfinite(stats["loss"])
    assert sizes == [(20, 16)] * 5 + [(40, 32)] * 3  # 40x32 frames at scale 0.5, then full
    assert trainer.pixels == 8 * 40 * 32 and trainer.coarse_pixels == 5 * 20 * 16
    assert trainer.coarse_full_pixels == 5 * 40 * 32
    assert trainer._coarse_images == {}  # the small targets are dropped after the switch


def test_coarse_target_is_the_area_average_of_the_image(tmp_path: Path) -> None:
    trainer = _trainer(tmp_path, coarse_iterations=5, coarse_scale=0.5)
    frame = trainer.scene.train[0]
    camera, small = trainer._coarse_view(0, frame)
    full = trainer.image(0, frame)
    want = full.reshape(16, 2, 20, 2, 3).mean(dim=(1, 3))
    assert (camera.width, camera.height) == (20, 16)
    assert torch.allclose(small, want, atol=1e-6)
    assert camera.fx == frame.camera.fx / 2 and camera.cx == frame.camera.cx / 2


def test_no_coarse_iterations_by_default(tmp_path: Path) -> None:
    trainer = _trainer(tmp_path)
    for _ in range(3):
        trainer.step()
    assert trainer.coarse_pixels == 0 and trainer.pixels == 3 * 40 * 32


def test_motion_sparsity_is_a_group_lasso_of_the_offsets() -> None:
    dx = torch.tensor([[0.0, 0.0, 0.0], [3.0, 4.0, 0.0]], requires_grad=True)
    dw = torch.zeros(2, 3, requires_grad=True)
    dl = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.2]], requires_grad=True)
    loss = motion_sparsity((dx, dw, dl), extent=10.0, n=4)
    # Row 1: |dx| 5 / (1e-2 * 10) + |dl| 0.2 / 0.1 = 52; over n = 4 Gaussians.
    assert math.isclose(loss.item(), 52.0 / 4, rel_tol=1e-6)
    loss.backward()
    assert torch.isfinite(dx.grad).all() and (dx.grad[0] == 0).all()  # no NaN at zero


def test_sparsity_weight_pulls_d_thetas_offsets_down(tmp_path: Path) -> None:
    """The same run with and without the loss: with it, D_theta moves the Gaussians less."""
    offsets = {}
    for weight in (0.0, 1.0):
        static = StaticConfig(enabled=True, start=10_000, sparsity=weight)
        trainer = _trainer(tmp_path, lr_deform=1e-2, lr_embed=1e-2, static=static)
        for _ in range(15):
            trainer.step()
        with torch.no_grad():
            dx, _, _ = trainer.model.deform(trainer.model.means, trainer.model.embeddings, 0.5)
        offsets[weight] = float(dx.norm(dim=-1).mean())
    assert offsets[1.0] < 0.5 * offsets[0.0], offsets


def test_pruning_after_densification_removes_only_transparent_gaussians() -> None:
    from sync4d.phase1.densify import Densifier

    for enabled in (False, True):
        model, opt = densify_case()  # row 5 is transparent (opacity logit -10)
        d = Densifier(DensifyConfig(start=0, stop=10, interval=5, prune_after_stop=enabled))
        keep = model.means.data[:5].clone()
        assert d.step(model, opt, 12, 1.0)["pruned"] == 0  # not on the interval
        out = d.step(model, opt, 15, 1.0)
        assert out == {"cloned": 0, "split": 0, "pruned": int(enabled)}
        assert model.num_gaussians == (5 if enabled else 6)
        if enabled:
            assert torch.equal(model.means.data, keep)
            assert opt.state[model.means]["exp_avg"].shape[0] == 5
            assert d.grad_accum.shape[0] == 5


def test_motion_sparsity_below_leaves_large_motions_alone() -> None:
    dx = torch.tensor([[0.05, 0.0, 0.0], [3.0, 4.0, 0.0]], requires_grad=True)
    zero = torch.zeros(2, 3)
    loss = motion_sparsity((dx, zero, zero), extent=10.0, n=2, below=1.0)
    assert math.isclose(loss.item(), 0.05 / 0.1 / 2, rel_tol=1e-6)  # row 1 (score 50) is free
    loss.backward()
    assert (dx.grad[1] == 0).all() and dx.grad[0, 0] > 0


def test_static_checks_follow_the_schedule_and_the_last_densification(tmp_path: Path) -> None:
    """Checks from `start` every `every` iterations, and once after the last densification;
    not after the others (children inherit their parent's flag)."""
    static = StaticConfig(enabled=True, start=4, every=10)
    trainer = _trainer(tmp_path, static=static, lr_deform_warmup=1)
    trainer.densifier.config = DensifyConfig(start=2, stop=12, interval=3)
    due = []
    for it in range(1, 26):
        trainer.iteration = it
        densified = 2 <= it < 12 and it % 3 == 0
        if trainer.static_check_due(densified):
            due.append(it)
    assert due == [4, 9, 14, 24]  # 9 is the last densification (9 + 3 >= 12)
