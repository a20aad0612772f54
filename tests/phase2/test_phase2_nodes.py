"""Phase 2 on a node model: nodes take their objects from their Gaussians' votes, and M_phi's
closed-form start is fitted on the node trajectories (hundreds of rows, not every Gaussian),
recovering the synthetic scene's true motion as the per-Gaussian fit does."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from support.oracle import PHASE2_SCENE as SMALL
from support.oracle import oracle_points
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.geometry import matrix_to_rotvec
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.nodes import NodeConfig
from sync4d.phase2 import Phase2Config, phase2_trainer
from sync4d.phase2.assign import node_votes
from sync4d.phase2.motion import MotionConfig


class TrueNodeMotion(nn.Module):
    """Stands in for D_theta on the nodes: each node moves rigidly with the object of the
    oracle point nearest to it (the scene's true poses), so node trajectories are exact."""

    def __init__(self, points: np.ndarray, truth: np.ndarray) -> None:
        super().__init__()
        self.points = torch.as_tensor(points, dtype=torch.float32)
        self.truth = truth
        self.pose0 = syn.object_poses(0.0)

    def forward(self, x0: Tensor, z: Tensor, t: float) -> tuple[Tensor, Tensor, Tensor]:
        label = self.truth[torch.cdist(x0.detach(), self.points).argmin(1).numpy()]
        poses = syn.object_poses(float(t))
        x = x0.detach().double().numpy()
        dx, dw = np.zeros_like(x), np.zeros_like(x)
        for k in np.unique(label):
            if int(k) not in poses:  # the plate (0): it does not move
                continue
            sel = label == k
            k = int(k)
            r0, t0 = self.pose0[k]
            rt, tt = poses[k]
            rel = rt @ r0.T
            dx[sel] = (x[sel] - t0) @ rel.T + tt - x[sel]
            dw[sel] = matrix_to_rotvec(rel)
        f = torch.float32
        return (torch.as_tensor(dx, dtype=f), torch.as_tensor(dw, dtype=f),
                torch.zeros(len(x), 3))  # fmt: skip


@pytest.fixture(scope="module")
def node_oracle(tmp_path_factory):
    root = syn.write_synthetic_scene(tmp_path_factory.mktemp("synthetic"), SMALL)
    points, truth = oracle_points()
    model = DeformableGaussians(torch.as_tensor(points, dtype=torch.float32), None, sh_degree=0)
    with torch.no_grad():
        model.opacity_logits.fill_(3.0)
    model.use_nodes(NodeConfig(count=96, neighbours=4), torch.Generator().manual_seed(0))
    model.deform = TrueNodeMotion(points, truth)
    return load_scene(root), model, truth, syn.load_ground_truth(root)


def test_nodes_vote_for_their_gaussians_objects(node_oracle):
    _, model, truth, _ = node_oracle
    labels = node_votes(model.motion_model.control_points(model), model.means.detach(), truth, 4)
    near = torch.cdist(model.nodes.positions.detach(), model.means.detach()).argmin(1).numpy()
    assert (labels == truth[near]).mean() > 0.9
    assert set(np.unique(labels)) == {0, 1, 2, 3}


def test_phase2_fits_its_start_on_node_trajectories(node_oracle):
    scene, model, _, gt = node_oracle
    tr = phase2_trainer(model, scene, Phase1Config(),
                        Phase2Config(motion=MotionConfig(init="fit")), 100, threads=1)  # fmt: skip
    assert tr.node_fitted_objects >= 3  # objects with 3 or more nodes use them
    ex = tr.motion_export()
    for label in (1, 2):  # the ball rolls and hops, the box slides and turns
        rot, cen = gt.motion_errors(ex["rotations"][label], ex["translations"][label],
                                    ex["times"], label)  # fmt: skip
        assert float(rot.mean()) < 2.0, (label, rot)
        assert float(cen.mean()) < 0.02 * gt.extent, (label, cen)
