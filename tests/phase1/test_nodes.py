"""Control nodes (sync4d.phase1.nodes): the blend and ARAP against finite differences and
closed forms, sampling, adaptive nodes (counters, Adam rows), checkpoints, and training."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
import torch

from support.scenes import orbit_scene, orbit_student, random_gaussians
from support.training import train
from sync4d.geometry import axis_angle_to_quat, quat_multiply, rotvec_to_matrix
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.nodes import (
    BLENDS,
    NodeConfig,
    NodeMotion,
    arap_loss,
    blend,
    blend_weights,
    densify_nodes,
    farthest_point_sample,
    knn,
    strain_loss,
)
from sync4d.phase1.trainer import Phase1Trainer

F64 = torch.float64


def _case(n: int = 7, m: int = 5, k: int = 3, seed: int = 0, angle: float = 0.6):
    """Random Gaussians, nodes and node motions in float64, with requires_grad."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randn(n, 3, generator=g, dtype=F64)
    q0 = torch.randn(n, 4, generator=g, dtype=F64)
    q0 = q0 / q0.norm(dim=-1, keepdim=True)
    ls0 = torch.randn(n, 3, generator=g, dtype=F64) * 0.1
    pos = torch.randn(m, 3, generator=g, dtype=F64)
    lr = torch.randn(m, generator=g, dtype=F64) * 0.2
    w = torch.randn(m, 3, generator=g, dtype=F64) * angle
    q = axis_angle_to_quat(w)
    dx = torch.randn(m, 3, generator=g, dtype=F64) * 0.3
    dl = torch.randn(m, 3, generator=g, dtype=F64) * 0.05
    index = knn(x0, pos, k)
    return [t.requires_grad_() for t in (x0, q0, ls0, pos, lr, q, dx, dl)], index


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("kind", BLENDS)
def test_blend_gradients_match_finite_differences(kind: str, fused: bool) -> None:
    """Both blends, with the weights given or computed from the same gathered node rows
    (the training path), against finite differences in float64; the two paths agree."""
    (x0, q0, ls0, pos, lr, q, dx, dl), index = _case()

    def f(x0, q0, ls0, pos, lr, q, dx, dl):
        if fused:
            return blend(x0, q0, ls0, pos, (q, dx, dl), index, None, kind, lr)
        w = blend_weights(x0, pos, lr, index)
        return blend(x0, q0, ls0, pos, (q, dx, dl), index, w, kind)

    args = (x0, q0, ls0, pos, lr, q, dx, dl)
    assert torch.autograd.gradcheck(f, args, atol=1e-6)
    w = blend_weights(x0, pos, lr, index)
    for a, b in zip(blend(x0, q0, ls0, pos, (q, dx, dl), index, None, kind, lr),
                    blend(x0, q0, ls0, pos, (q, dx, dl), index, w, kind), strict=True):  # fmt: skip
        torch.testing.assert_close(a, b, atol=1e-12, rtol=0)


def test_arap_gradient_matches_finite_differences() -> None:
    (_, _, _, pos, _, q, dx, dl), _ = _case(m=6)
    g = torch.Generator().manual_seed(3)
    q2 = axis_angle_to_quat(torch.randn(6, 3, generator=g, dtype=F64)).requires_grad_()
    dx2 = (torch.randn(6, 3, generator=g, dtype=F64) * 0.3).requires_grad_()
    edges = knn(pos.detach(), pos.detach(), 3, exclude_self=True)

    scale = float(((pos[edges] - pos.unsqueeze(1)) ** 2).sum(-1).mean().detach())
    torch.testing.assert_close(arap_loss(pos, edges, (q, dx, dl), (q2, dx2, dl)),
                               arap_loss(pos, edges, (q, dx, dl), (q2, dx2, dl), scale))

    def f(pos, q, dx, q2, dx2):  # the normalising scale is a constant of the loss
        return arap_loss(pos, edges, (q, dx, dl), (q2, dx2, dl), scale)

    assert torch.autograd.gradcheck(f, (pos, q, dx, q2, dx2), atol=1e-6)


@pytest.mark.parametrize("kind", BLENDS)
def test_one_rigid_motion_for_every_node_moves_the_gaussians_rigidly(kind: str) -> None:
    """All nodes turning by R about their own positions and moving by dx_j = (R - I)(p_j - c)
    + d is one rigid motion x -> R (x - c) + c + d; both blends give it exactly."""
    (x0, q0, ls0, pos, lr, _, _, dl), index = _case(angle=0.0)
    x0, q0, ls0, pos, lr = (t.detach() for t in (x0, q0, ls0, pos, lr))
    rv = torch.tensor([0.3, -1.1, 0.7], dtype=F64)
    rot, c, d = rotvec_to_matrix(rv), torch.tensor([0.2, 0.1, -0.4], dtype=F64), \
        torch.tensor([0.5, -0.2, 0.3], dtype=F64)  # fmt: skip
    m = pos.shape[0]
    q = axis_angle_to_quat(rv).expand(m, 4)
    dx = ((rot - torch.eye(3, dtype=F64)) @ (pos - c).unsqueeze(-1)).squeeze(-1) + d
    dl = torch.full((m, 3), 0.1, dtype=F64)
    w = blend_weights(x0, pos, lr, index)
    x, qt, s = blend(x0, q0, ls0, pos, (q, dx, dl), index, w, kind)
    want = ((rot @ (x0 - c).unsqueeze(-1)).squeeze(-1) + c + d)
    torch.testing.assert_close(x, want, atol=1e-12, rtol=0)
    qw = quat_multiply(axis_angle_to_quat(rv).expand_as(q0), q0)
    torch.testing.assert_close(qt * qt[:, :1].sign(), qw * qw[:, :1].sign(), atol=1e-12, rtol=0)
    torch.testing.assert_close(s, torch.exp(ls0 + 0.1))


def test_identity_motion_leaves_the_gaussians_canonical_and_weights_sum_to_one() -> None:
    (x0, q0, ls0, pos, lr, _, _, _), index = _case()
    x0, q0, ls0, pos, lr = (t.detach() for t in (x0, q0, ls0, pos, lr))
    m = pos.shape[0]
    ident = (torch.tensor([1.0, 0, 0, 0], dtype=F64).expand(m, 4),
             torch.zeros(m, 3, dtype=F64), torch.zeros(m, 3, dtype=F64))  # fmt: skip
    far = x0 * 1e4  # far from every node: the weights still form a partition of unity
    for pts in (x0, far):
        w = blend_weights(pts, pos, lr - 5.0, index)
        assert torch.isfinite(w).all()
        torch.testing.assert_close(w.sum(-1), torch.ones(len(pts), dtype=F64))
        for kind in BLENDS:
            x, qt, s = blend(pts, q0, ls0, pos, ident, index, w, kind)
            torch.testing.assert_close(x, pts, atol=1e-9 * float(pts.abs().max()), rtol=0)
            torch.testing.assert_close(qt, q0)
            torch.testing.assert_close(s, ls0.exp())


def test_the_two_blends_differ_on_opposed_rotations() -> None:
    """Two nodes at the origin turned +-90 degrees about z: a point at (1, 0, 0) is averaged
    onto the axis by the linear blend (the candy-wrapper collapse) and kept by dual
    quaternions, whose blend of the two turns is no turn."""
    pos = torch.zeros(2, 3, dtype=F64)
    q = axis_angle_to_quat(torch.tensor([[0, 0, math.pi / 2], [0, 0, -math.pi / 2]], dtype=F64))
    motion = (q, torch.zeros(2, 3, dtype=F64), torch.zeros(2, 3, dtype=F64))
    x0 = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64)
    index = torch.tensor([[0, 1]])
    w = torch.tensor([[0.5, 0.5]], dtype=F64)
    q0 = torch.tensor([[1.0, 0, 0, 0]], dtype=F64)
    ls0 = torch.zeros(1, 3, dtype=F64)
    lin = blend(x0, q0, ls0, pos, motion, index, w, "linear")[0]
    dq = blend(x0, q0, ls0, pos, motion, index, w, "dual_quaternion")[0]
    assert float(lin.norm()) < 1e-12
    torch.testing.assert_close(dq, x0)


def test_arap_is_zero_for_rigid_motion_and_positive_otherwise() -> None:
    g = torch.Generator().manual_seed(1)
    pos = torch.randn(20, 3, generator=g, dtype=F64)
    edges = knn(pos, pos, 4, exclude_self=True)

    def rigid(rv, d):
        rot = rotvec_to_matrix(torch.tensor(rv, dtype=F64))
        dx = ((rot - torch.eye(3, dtype=F64)) @ pos.unsqueeze(-1)).squeeze(-1)
        dx = dx + torch.tensor(d, dtype=F64)
        return axis_angle_to_quat(torch.tensor(rv, dtype=F64)).expand(20, 4), dx, dx * 0

    a, b = rigid([0.1, 0.2, 0.3], [1.0, 0, 0]), rigid([-0.5, 0.0, 0.9], [0, 2.0, 0])
    assert float(arap_loss(pos, edges, a, b)) < 1e-20
    bent = (b[0], b[1] + torch.randn(20, 3, generator=g, dtype=F64) * 0.1, b[2])
    assert float(arap_loss(pos, edges, a, bent)) > 1e-4
    # Scale-free: the same motion on a scene 1000x larger gives the same loss.
    big = (bent[0], bent[1] * 1e3, bent[2])
    aa = (a[0], a[1] * 1e3, a[2])
    torch.testing.assert_close(arap_loss(pos * 1e3, edges, aa, big), arap_loss(pos, edges, a, bent))


def test_strain_is_zero_for_rigid_motion_scale_free_and_matches_finite_differences() -> None:
    g = torch.Generator().manual_seed(2)
    pos = torch.randn(12, 3, generator=g, dtype=F64)
    edges = knn(pos, pos, 3, exclude_self=True)
    rv = torch.tensor([0.4, -0.2, 0.9], dtype=F64)
    dx = ((rotvec_to_matrix(rv) - torch.eye(3, dtype=F64)) @ pos.unsqueeze(-1)).squeeze(-1) + 1.5
    q = axis_angle_to_quat(torch.zeros(12, 3, dtype=F64))  # rotations do not enter the strain
    assert float(strain_loss(pos, edges, (q, dx, dx * 0))) < 1e-20
    # Every edge stretched by 10 %: strain 0.01 whatever the edge's length or the scene's size.
    for scale in (1.0, 1e-3, 1e3):
        p = pos * scale
        torch.testing.assert_close(strain_loss(p, edges, (q, 0.1 * p, dx * 0)),
                                   torch.tensor(0.01, dtype=F64))  # fmt: skip
    dxr = (torch.randn(12, 3, generator=g, dtype=F64) * 0.2).requires_grad_()
    assert torch.autograd.gradcheck(lambda d: strain_loss(pos, edges, (q, d, d * 0)), (dxr,))


def test_arap_weight_decays_to_zero_at_arap_until() -> None:
    from types import SimpleNamespace

    from sync4d.phase1.motion.control_nodes import NodesMotion

    def weight(it: int, until: int) -> float:
        config = SimpleNamespace(nodes=NodeConfig(arap_weight=1e-3, init_after=1000,
                                                  arap_until=until))  # fmt: skip
        return NodesMotion().arap_weight(SimpleNamespace(config=config, iteration=it))

    assert weight(5000, 0) == 1e-3
    assert weight(1000, 3000) == 1e-3 and weight(3000, 3000) == 0.0 and weight(9000, 3000) == 0.0
    assert abs(weight(2000, 3000) - 5e-4) < 1e-15


def test_farthest_point_sampling_spreads_and_knn_orders() -> None:
    g = torch.Generator().manual_seed(0)
    # Two clusters of 500 and 5 points: sampling 2 takes one from each.
    pts = torch.cat([torch.randn(500, 3, generator=g) * 0.01, torch.randn(5, 3, generator=g)
                     * 0.01 + 10])  # fmt: skip
    idx = farthest_point_sample(pts, 2, torch.Generator().manual_seed(0))
    assert sorted(int(i) >= 500 for i in idx) == [False, True]
    assert len(set(farthest_point_sample(pts, 600).tolist())) == 505
    near = knn(pts[:3], pts, 4)
    d = (pts[near] - pts[:3].unsqueeze(1)).norm(dim=-1)
    assert (d[:, 1:] >= d[:, :-1]).all() and (near[:, 0] == torch.arange(3)).all()
    assert not (knn(pts[:50], pts[:50], 3, exclude_self=True) == torch.arange(50)[:, None]).any()


def _node_model(n: int = 300, count: int = 16, **node) -> DeformableGaussians:
    model = random_gaussians(n, 0, spread=0.5, opacity_logit=1.0)
    with torch.no_grad():  # a D_theta that moves things
        model.deform.head.weight.normal_(0.0, 0.2, generator=torch.Generator().manual_seed(1))
    model.use_nodes(NodeConfig(count=count, neighbours=4, **node),
                    torch.Generator().manual_seed(2))  # fmt: skip
    return model


def test_nodes_start_with_the_motion_of_the_gaussians_they_were_sampled_at() -> None:
    model = random_gaussians(200, 0, spread=0.5, opacity_logit=1.0)
    with torch.no_grad():
        model.deform.head.weight.normal_(0.0, 0.2, generator=torch.Generator().manual_seed(1))
    per_gaussian = model.deform(model.means, model.embeddings, 0.3)
    nodes = model.use_nodes(NodeConfig(count=12), torch.Generator().manual_seed(2))
    assert nodes.count == 12 and model.motion == "nodes"
    # Each node is one of the Gaussians: same position, same embedding, same D_theta output.
    d = torch.cdist(nodes.positions.detach(), model.means.detach(),
                    compute_mode="donot_use_mm_for_euclid_dist")
    rows = d.argmin(1)
    assert float(d.min(1).values.max()) == 0.0
    node_dx = model.deform(nodes.positions, nodes.embeddings, 0.3)[0]
    torch.testing.assert_close(node_dx, per_gaussian[0][rows])
    assert (nodes.log_radii.exp() > 0).all()
    x, q, s = model.at_time(0.3)
    assert x.shape == (200, 3) and torch.isfinite(x).all() and model.deform_rows == 12


def test_node_checkpoint_round_trip_renders_the_same() -> None:
    model = _node_model(blend="dual_quaternion")
    tensors, meta = model.state()
    assert meta["motion"] == "nodes" and tensors["gaussians.node_index"].dtype == torch.int32
    back = DeformableGaussians.from_state(tensors, meta)
    for a, b in zip(model.at_time(0.7), back.at_time(0.7), strict=True):
        torch.testing.assert_close(a, b, atol=0, rtol=0)
    bad = dict(tensors)
    bad["gaussians.node_index"] = tensors["gaussians.node_index"] + 100
    with pytest.raises(ValueError, match="outside"):
        DeformableGaussians.from_state(bad, meta)
    with pytest.raises(ValueError, match="motion model"):
        DeformableGaussians.from_state(tensors, {**meta, "motion": "grid"})


def test_adaptive_nodes_add_where_the_gradient_is_and_remove_idle_ones() -> None:
    model = _node_model(add_per_step=3, prune_weight=0.5, grad_threshold=1e-3)
    nodes = model.nodes
    assert nodes is not None
    opt = torch.optim.Adam([{"params": [getattr(nodes, n)]} for n in NodeMotion.PER_NODE])
    sum(getattr(nodes, n).square().sum() for n in NodeMotion.PER_NODE).backward()
    opt.step()
    with torch.no_grad():  # an idle node, far from every Gaussian
        nodes.positions[0] = 100.0
    nodes.refresh(model.means)
    m = nodes.count
    grad = torch.zeros(model.num_gaussians)
    hot = (model.means.detach()[:, 0] > 0.3).nonzero().squeeze(1)
    grad[hot] = 1e-2
    added, removed = densify_nodes(nodes, model.means.detach(), grad, opt)
    assert added == 3 and removed == 1 and nodes.count == m + 2
    assert (nodes.added, nodes.removed) == (3, 1)
    assert float(nodes.positions.detach()[:, 0].max()) < 100  # the idle node went
    # New nodes sit among the hot Gaussians; every parameter's Adam moments follow its rows.
    assert (nodes.positions.detach()[-3:, 0] > 0.2).all()
    for p in (nodes.positions, nodes.log_radii, nodes.embeddings):
        st = opt.state[p]
        assert st["exp_avg"].shape == p.shape and (st["exp_avg"][-3:] == 0).all()
    assert nodes.index.shape == (model.num_gaussians, 4) and int(nodes.index.max()) < nodes.count
    # Nothing hot, nothing idle: nothing changes.
    assert densify_nodes(nodes, model.means.detach(), grad * 0, opt) == (0, 0)


def test_densification_carries_each_gaussians_nodes(tmp_path: Path) -> None:
    scene, gt = orbit_scene(tmp_path)
    model = DeformableGaussians(gt.means.data.clone(), None, sh_degree=0)
    cfg = Phase1Config(densify=DensifyConfig(start=5, interval=5, stop=40, grad_threshold=1e-6),
                       motion="nodes", nodes=NodeConfig(count=8, init_after=2, neighbours=3,
                                                        densify_until=0))  # fmt: skip
    trainer = Phase1Trainer(model, scene, cfg, total_iterations=20, threads=1)
    stats = train(trainer, 20)
    assert stats["gaussians"] > 40 and stats["nodes"] == 8
    assert model.nodes is not None and model.nodes.index.shape == (model.num_gaussians, 3)


def test_training_on_nodes_switches_after_the_coarse_stage_and_resumes_exactly(
    tmp_path: Path,
) -> None:
    scene, gt = orbit_scene(tmp_path)
    nodes = NodeConfig(count=10, init_after=5, neighbours=4, arap_weight=0.1)
    cfg = Phase1Config(densify=DensifyConfig(start=10_000), motion="nodes", nodes=nodes)

    def trainer_for(model):
        return Phase1Trainer(model, scene, cfg, total_iterations=30, threads=1)

    t1 = trainer_for(orbit_student(gt, 1, jitter=0.05))
    train(t1, 5)
    assert t1.model.motion == "gaussians"  # the coarse stage
    train(t1, 5)
    assert t1.model.motion == "nodes" and t1.model.motion_model.last_regulariser() is not None
    names = [g["name"] for g in t1.optimizer.param_groups]
    assert names[-3:] == ["node_positions", "node_radii", "node_embeddings"]
    before = t1.model.nodes.positions.detach().clone()
    tensors, meta = t1.state()
    t2 = Phase1Trainer.from_state(tensors, meta, scene, config=cfg, threads=1)
    train(t1, 10)
    train(t2, 10)
    assert not torch.equal(before, t1.model.nodes.positions.detach())  # nodes are trained
    for a, b in zip(t1.model.at_time(0.5), t2.model.at_time(0.5), strict=True):
        torch.testing.assert_close(a, b, atol=0, rtol=0)


def test_node_settings_scale_with_the_budget() -> None:
    from sync4d.config import RunConfig, with_budget

    cfg = RunConfig()
    cfg = dataclasses.replace(cfg, phase1=dataclasses.replace(cfg.phase1, iterations=9000))
    small = with_budget(cfg, 3000).phase1.nodes
    assert small.init_after == round(NodeConfig().init_after / 3)
    assert small.count == NodeConfig().count


def test_one_node_left_has_no_graph_loss_and_configs_that_cannot_work_are_refused() -> None:
    """A single node (pruning can leave one) has no graph edge: ARAP and strain are 0, not the
    NaN of a mean over nothing; settings whose counts cannot go together are refused when the
    config is read, each naming the setting to change."""
    from sync4d.config import ConfigError, RunConfig, apply_overrides

    pos = torch.zeros(1, 3, dtype=F64, requires_grad=True)
    edges = knn(pos, pos, 4, exclude_self=True)
    motion = (torch.tensor([[1.0, 0, 0, 0]], dtype=F64), pos * 2.0, pos[:, 0] * 0)
    assert edges.shape == (1, 0)
    loss = arap_loss(pos, edges, motion, motion) + strain_loss(pos, edges, motion)
    assert float(loss.detach()) == 0.0
    loss.backward()
    assert torch.isfinite(pos.grad).all()
    cases = {
        "phase1.nodes.count=1": "neighbours = 8 exceeds count = 1",
        "phase1.nodes.count=4": "neighbours = 8 exceeds count = 4",
        "phase1.nodes.max_count=100": "max_count = 100 is below count = 512",
    }
    for override, message in cases.items():
        with pytest.raises(ConfigError, match=message):
            apply_overrides(RunConfig(), [override])
    with pytest.raises(ConfigError, match="count = 1 needs at least 2 nodes for the ARAP"):
        apply_overrides(RunConfig(), ["phase1.nodes.count=1", "phase1.nodes.neighbours=1"])
    # without the graph losses one node works; 8 nodes take 8 neighbours (ARAP's 7 others)
    apply_overrides(RunConfig(), ["phase1.nodes.count=1", "phase1.nodes.neighbours=1",
                                  "phase1.nodes.arap_weight=0"])
    apply_overrides(RunConfig(), ["phase1.nodes.count=8"])
