"""Densification bookkeeping: clone / split / prune keep parameters and Adam state aligned."""

from __future__ import annotations

import dataclasses
import math

import torch

from support.scenes import densify_case
from sync4d.phase1.densify import PER_GAUSSIAN, Densifier, DensifyConfig


def test_clone_split_prune_keep_optimizer_state_aligned() -> None:
    model, opt = densify_case()
    before = {n: opt.state[getattr(model, n)]["exp_avg"].clone() for n in PER_GAUSSIAN}
    old_means = model.means.data.clone()
    old_log_scales = model.log_scales.data.clone()
    d = Densifier(DensifyConfig(grad_threshold=1e-3, percent_dense=0.1))
    d._ensure(6)
    d.grad_accum[:] = torch.tensor([1.0, 0.0, 1.0, 1.0, 0.0, 0.0])  # hot: 0, 2 (clone), 3 (split)
    d.count[:] = 1
    out = d.densify_and_prune(model, opt, scene_extent=1.0)
    assert out == {"cloned": 2, "split": 1, "pruned": 1}
    n = model.num_gaussians
    assert n == 6 + 2 + 2 - 1 - 1  # +clones, +2 children, -split parent, -pruned
    for name in PER_GAUSSIAN:
        p = getattr(model, name)
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
        assert any(p is q for grp in opt.param_groups for q in grp["params"])
    # Originals kept (0, 1, 2, 4) keep their moments, in order, and come first.
    kept = [0, 1, 2, 4]
    for name in PER_GAUSSIAN:
        assert torch.equal(opt.state[getattr(model, name)]["exp_avg"][:4], before[name][kept])
        assert opt.state[getattr(model, name)]["exp_avg"][4:].abs().max() == 0
    assert torch.equal(model.means.data[:4], old_means[kept])
    assert torch.equal(model.means.data[4:6], old_means[[0, 2]])  # clones copy their parent
    # Split children are shrunk by 1 / (0.8 * 2) and stay near their parent.
    expected = (old_log_scales[3] - math.log(1.6)).expand(2, 3)
    assert torch.allclose(model.log_scales.data[6:], expected)
    assert ((model.means.data[6:] - old_means[3]).norm(dim=-1) < 3.0).all()
    # The optimizer keeps working on the new tensors.
    sum((getattr(model, n) ** 2).sum() for n in PER_GAUSSIAN).backward()
    opt.step()
    assert d.grad_accum.shape == (n,)


def test_cap_and_opacity_reset() -> None:
    model, opt = densify_case()
    d = Densifier(DensifyConfig(grad_threshold=1e-3, percent_dense=0.1, max_gaussians=7))
    d._ensure(6)
    d.grad_accum[:] = torch.tensor([1.0, 2.0, 3.0, 0.0, 0.0, 0.0])
    d.count[:] = 1
    out = d.densify_and_prune(model, opt, scene_extent=1.0)
    assert out["cloned"] == 1  # only one slot under the cap: the hottest (index 2)
    d.reset_opacity(model, opt)
    assert torch.sigmoid(model.opacity_logits.data).max() <= 0.01 + 1e-6
    assert opt.state[model.opacity_logits]["exp_avg"].abs().max() == 0


def test_accumulate_uses_visible_gaussians_in_ndc_units() -> None:
    d = Densifier()
    grad = torch.tensor([[1.0, 0.0], [0.0, 2.0]])
    radii = torch.tensor([[3, 3], [0, 0]], dtype=torch.int32)
    d.accumulate(grad, radii, width=100, height=50)
    assert torch.allclose(d.grad_accum, torch.tensor([50.0, 0.0]))
    assert torch.equal(d.count, torch.tensor([1.0, 0.0]))


def test_too_big_gaussians_pruned_only_after_first_reset() -> None:
    """World-space giants (> prune_world_scale x extent) and, when enabled, screen-space
    giants go once the first opacity reset has passed, as in 3DGS / gsplat."""
    cfg = DensifyConfig(
        grad_threshold=1e9, start=0, stop=10_000, interval=100, opacity_reset_interval=3000,
        prune_world_scale=0.1, prune_screen_fraction=0.15,
    )  # fmt: skip
    model, opt = densify_case()
    with torch.no_grad():
        model.log_scales[:] = math.log(0.05)
        model.log_scales[1, 2] = math.log(2.0)  # 2.0 > 0.1 x extent 10: too big in the world
    d = Densifier(cfg)
    radii = torch.full((6, 2), 5, dtype=torch.int32)
    radii[4] = 40  # 40 / 200 px = 0.2 > 0.15 of the image: too big on screen
    d.accumulate(torch.zeros(6, 2), radii, width=200, height=100)
    assert torch.allclose(d.max_radius[[0, 4]], torch.tensor([0.025, 0.2]))
    # Before the first reset only the transparent Gaussian 5 goes.
    assert d.step(model, opt, 1000, scene_extent=10.0)["pruned"] == 1
    assert model.num_gaussians == 5
    d.accumulate(torch.zeros(5, 2), radii[:5], width=200, height=100)
    out = d.step(model, opt, 3100, scene_extent=10.0)
    assert out["pruned"] == 2 and model.num_gaussians == 3
    assert torch.allclose(model.log_scales.data.exp(), torch.full((3, 3), 0.05))
    assert d.max_radius.shape == (3,) and d.max_radius.abs().max() == 0
    # Disabled thresholds prune nothing but the transparent.
    model, opt = densify_case()
    off = Densifier(dataclasses.replace(cfg, prune_world_scale=0.0, prune_screen_fraction=0.0))
    off.accumulate(torch.zeros(6, 2), radii, width=200, height=100)
    assert off.step(model, opt, 3100, scene_extent=0.01)["pruned"] == 1
