"""Object assignment (sync4d.phase2.assign): vote rule, mask voting, clustering."""

from __future__ import annotations

import numpy as np
import pytest

from support.scenes import small_synthetic
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.phase2.assign import (
    AssignConfig,
    assign_from_masks,
    cluster_trajectories,
    labels_from_votes,
)

SMALL = small_synthetic(size=64)


def test_vote_rule_thresholds():
    votes = np.array(
        [
            [0, 5, 0, 0],  # clear object 1
            [0, 2, 0, 0],  # too few object votes
            [0, 3, 2, 0],  # 3 / 5 = 0.6 consistency: object 1
            [0, 2, 2, 1],  # tie-ish, 0.4 consistency: background
            [50, 3, 0, 0],  # mostly seen on background
        ]
    )
    paper = AssignConfig(min_gaussians=1, background_votes=False)  # Appendix C's formula
    assert labels_from_votes(votes, paper).tolist() == [1, 0, 1, 0, 1]
    majority = AssignConfig(min_gaussians=1)  # background hits count (the default)
    assert labels_from_votes(votes, majority).tolist() == [1, 0, 1, 0, 0]
    # Objects with too few Gaussians merge into background.
    few = AssignConfig(min_gaussians=4, background_votes=False)
    assert labels_from_votes(votes, few).tolist() == [0, 0, 0, 0, 0]


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return syn.write_synthetic_scene(tmp_path_factory.mktemp("synthetic"), SMALL)


def _object_points(obj: syn._Object) -> np.ndarray:
    """Points inside an object, in its local frame: the centre and 6 points half-way out."""
    half = np.asarray(obj.size) * 0.5
    offs = np.concatenate([np.zeros((1, 3)), np.diag(half), -np.diag(half)])
    return offs


def test_mask_votes_recover_the_true_objects(small_scene):
    scene = load_scene(small_scene)
    local = {o.label: _object_points(o) for o in syn.OBJECTS}
    ground = np.array([[x, y, 0.0] for x in (-1.1, 1.1) for y in (-1.1, 1.1)])

    def positions_at(t: float) -> np.ndarray:
        poses = syn.object_poses(t)
        pts = [ground] + [local[k] @ poses[k][0].T + poses[k][1] for k in sorted(local)]
        return np.concatenate(pts)

    truth = np.concatenate([np.zeros(len(ground))] + [np.full(7, k) for k in sorted(local)])
    a = assign_from_masks(positions_at, scene.train, scene.labels, AssignConfig(min_gaussians=1))
    assert a.num_objects == 4 and a.source == "masks"
    assert a.names[1] == "red ball"
    assert a.labels.tolist() == truth.astype(int).tolist()
    assert a.votes.shape == (len(truth), 4)
    assert a.votes.sum(1).max() <= len(scene.train)
    assert a.counts() == {0: 4, 1: 7, 2: 7, 3: 7}
    # Appendix C's object-votes-only rule hands ground points that the pillar hides in a few
    # views to the pillar: why background hits count by default.
    paper = AssignConfig(min_gaussians=1, background_votes=False)
    b = assign_from_masks(positions_at, scene.train, scene.labels, paper)
    assert (b.labels[: len(ground)] == 3).any()


def test_mask_votes_need_masks(small_scene):
    scene = load_scene(small_scene)
    frames = [f.__class__(**{**f.__dict__, "mask_path": None}) for f in scene.train[:3]]
    with pytest.raises(ValueError, match="instance masks"):
        assign_from_masks(lambda t: np.zeros((2, 3)), frames, None)


def test_trajectory_clusters_match_the_motion_groups():
    rng = np.random.default_rng(0)
    times = np.linspace(0, 1, 12)
    static = rng.normal(scale=1e-4, size=(200, 12, 3))
    slide = np.zeros((150, 12, 3))
    slide[..., 0] = 0.5 * times
    # Rotation about z by up to 60 degrees of points at radius ~0.3 around (1, 0, 0).
    p = rng.normal(scale=0.1, size=(120, 3)) + [0.3, 0.0, 0.0]
    ang = np.radians(60) * times
    c, s = np.cos(ang), np.sin(ang)
    rot = np.stack([c[:, None] * p[None, :, 0] - s[:, None] * p[None, :, 1],
                    s[:, None] * p[None, :, 0] + c[:, None] * p[None, :, 1],
                    np.broadcast_to(p[None, :, 2], (12, 120))], -1)  # fmt: skip
    spin = np.transpose(rot - rot[:1], (1, 0, 2))
    disp = np.concatenate([static, slide + rng.normal(scale=1e-3, size=slide.shape), spin])
    truth = np.r_[np.zeros(200), np.ones(150), np.full(120, 2)]
    a = cluster_trajectories(disp, extent=2.0)
    assert a.source == "trajectories" and a.num_objects == 3
    assert (a.labels[:200] == 0).all()
    # Same partition up to label names.
    pairs = {(int(t), int(lab)) for t, lab in zip(truth, a.labels, strict=True)}
    assert len(pairs) == 3


def test_trajectory_clustering_of_a_static_scene_is_all_background():
    disp = np.random.default_rng(1).normal(scale=1e-4, size=(300, 8, 3))
    a = cluster_trajectories(disp, extent=2.0)
    assert a.num_objects == 1 and (a.labels == 0).all()


def test_adjusted_rand_index():
    from sync4d.phase2.assign import adjusted_rand_index

    a = np.array([0, 0, 1, 1, 2, 2])
    assert adjusted_rand_index(a, a) == pytest.approx(1.0)
    assert adjusted_rand_index(a, np.array([5, 5, 3, 3, 9, 9])) == pytest.approx(1.0)  # renamed
    # Worked example: 1 agreeing pair of 6, expectation 1/3, bound 3/2 -> (2/3) / (7/6) = 4/7.
    assert adjusted_rand_index([0, 0, 1, 1], [0, 0, 1, 2]) == pytest.approx(4 / 7)
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 4, 20000), rng.integers(0, 4, 20000)
    assert abs(adjusted_rand_index(x, y)) < 0.01  # independent labelings: chance level
    assert adjusted_rand_index(np.zeros(5), np.zeros(5)) == 1.0
    assert adjusted_rand_index(a, np.array([0, 1, 0, 1, 0, 1])) < 0.0  # worse than chance
    with pytest.raises(ValueError, match="differ in length"):
        adjusted_rand_index(a, a[:3])
