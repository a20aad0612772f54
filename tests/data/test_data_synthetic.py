"""The embedded synthetic scene: layout, camera convention, ground-truth motion, caching."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from support.scenes import small_synthetic
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.data.scene import DatasetError

SMALL = small_synthetic(train_cameras=3, test_every=2)


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    return syn.write_synthetic_scene(tmp_path_factory.mktemp("synthetic"), SMALL)


def test_loads_as_dnerf_with_masks_and_labels(small_scene):
    scene = load_scene(small_scene)
    assert len(scene.train) == SMALL.frames * SMALL.train_cameras
    assert len(scene.test) == math.ceil(SMALL.frames / SMALL.test_every) * SMALL.test_cameras
    assert scene.has_masks
    assert scene.labels == {0: "background", 1: "red ball", 2: "blue box", 3: "green pillar"}
    times = sorted({f.time for f in scene.train})
    assert times[0] == 0.0 and times[-1] == 1.0 and len(times) == SMALL.frames
    img = scene.train[0].load_image()
    assert img.shape == (48, 48, 3) and img.dtype == np.float32


def test_mask_label_at_projected_object_centre(small_scene):
    """The loader's cameras (OpenCV, world-to-camera) put the ball's centre on a pixel the
    ray caster labelled as the ball: the two camera conventions agree."""
    scene = load_scene(small_scene)
    gt = syn.load_ground_truth(small_scene)
    ball = gt.ids.index(1)
    # In mid-hop the ball is in the air, above the box and beside the pillar, so nothing
    # occludes its centre.
    apex = min({f.time for f in scene.train}, key=lambda t: abs(t - syn.HOP[1]))
    assert syn.HOP[0] < apex < syn.HOP[2]
    j = int(np.argmin(np.abs(gt.times - apex)))
    views = [f for f in scene.train + scene.test if f.time == apex]
    assert len(views) >= SMALL.train_cameras
    for f in views:
        uv, z = f.camera.project(gt.translations[ball, j][None])
        assert z[0] > 0
        u, v = (int(c) for c in np.floor(uv[0]))
        assert f.load_mask()[v, u] == 1, (f.image_path, u, v)
    # Every object shows up in some view at every time step.
    for t in range(SMALL.frames):
        seen = set()
        for f in scene.train[t * SMALL.train_cameras : (t + 1) * SMALL.train_cameras]:
            seen |= set(np.unique(f.load_mask()).tolist())
        assert {0, 1, 2, 3} <= seen, (t, seen)


def test_ground_truth_motion(small_scene):
    gt = syn.load_ground_truth(small_scene)
    k, t = len(gt.ids), len(gt.times)
    assert gt.rotations.shape == (k, t, 3, 3) and gt.translations.shape == (k, t, 3)
    eye = np.broadcast_to(np.eye(3), gt.rotations.shape)
    assert np.allclose(gt.rotations @ np.swapaxes(gt.rotations, -1, -2), eye, atol=1e-12)
    assert np.allclose(np.linalg.det(gt.rotations), 1.0)
    ball, box, pillar = (gt.ids.index(i) for i in (1, 2, 3))
    # The ball rolls without slipping about y: rotation angle = distance travelled / radius.
    r = syn.OBJECTS[0].size[0]
    angle = np.arctan2(gt.rotations[ball, :, 0, 2], gt.rotations[ball, :, 0, 0])
    travel = gt.translations[ball, :, 0] - gt.translations[ball, 0, 0]
    assert np.allclose(np.unwrap(angle), travel / r, atol=1e-9)
    assert np.allclose(gt.rotations[ball, :, 1], [0, 1, 0])  # y axis fixed
    # It rests on the ground (z = r) except during the hop, where it leaves the ground.
    z = gt.translations[ball, :, 2]
    hop = (gt.times > syn.HOP[0]) & (gt.times < syn.HOP[2])
    assert np.allclose(z[~hop], r) and (z[hop] > r).all()
    # The box moves and turns; the pillar never does and is flagged static.
    assert np.linalg.norm(gt.translations[box, -1] - gt.translations[box, 0]) > 0.3
    assert not np.allclose(gt.rotations[box, -1], gt.rotations[box, 0])
    assert gt.static == [False, False, True]
    assert np.allclose(gt.rotations[pillar], np.eye(3))
    assert np.allclose(gt.translations[pillar], gt.translations[pillar, 0])
    # Named states cover [0, 1] for every object, without gaps.
    for obj in gt.ids:
        spans = sorted((a, b) for o, _, a, b in gt.states if o == obj)
        assert spans[0][0] == 0.0 and spans[-1][1] == 1.0
        assert all(b0 == a1 for (_, b0), (a1, _) in zip(spans, spans[1:], strict=False))
    assert gt.extent > 1.0


def test_object_poses_match_ground_truth_file(small_scene):
    gt = syn.load_ground_truth(small_scene)
    for j, t in enumerate(gt.times):
        poses = syn.object_poses(float(t))
        for i, obj in enumerate(gt.ids):
            assert np.allclose(poses[obj][0], gt.rotations[i, j])
            assert np.allclose(poses[obj][1], gt.translations[i, j])


def test_motion_errors(small_scene):
    gt = syn.load_ground_truth(small_scene)
    gi = gt.ids.index(2)
    rot, tr = gt.rotations[gi], gt.translations[gi]
    # The truth itself, and the truth seen from another canonical frame (a fixed rigid change
    # of coordinates that the relative motion cancels), have no error.
    for a, b in [(rot, tr), (rot @ syn._rot_z(0.3).T, tr + rot @ np.array([0.1, 0.0, 0.0]))]:
        e_rot, e_cen = gt.motion_errors(a, b, gt.times, 2)
        assert e_rot.shape == e_cen.shape == (len(gt.times),)
        assert e_rot.max() < 1e-4 and e_cen.max() < 1e-9
    # A motion that never turns: the error is the true turn.
    e_rot, _ = gt.motion_errors(np.repeat(rot[:1], len(gt.times), 0), tr, gt.times, 2)
    true_turn = np.degrees(np.arccos(np.clip((np.trace(rot @ rot[0].T, axis1=1, axis2=2) - 1) / 2,
                                             -1, 1)))  # fmt: skip
    np.testing.assert_allclose(e_rot, true_turn, atol=1e-6)
    assert e_rot.max() > 10.0
    with pytest.raises(ValueError, match="no object 9"):
        gt.motion_errors(rot, tr, gt.times, 9)
    with pytest.raises(ValueError, match="expected rotations"):
        gt.motion_errors(rot[:2], tr, gt.times, 2)
    with pytest.raises(ValueError, match="frame times"):
        gt.motion_errors(rot, tr, gt.times + 0.001, 2)


def test_generation_is_deterministic_and_cached(small_scene, tmp_path):
    other = syn.write_synthetic_scene(tmp_path / "again", SMALL)
    name = "train/t003_c1.png"
    assert (other / name).read_bytes() == (small_scene / name).read_bytes()
    # A second call with the same config rewrites nothing.
    before = {p: p.stat().st_mtime_ns for p in other.rglob("*") if p.is_file()}
    syn.write_synthetic_scene(other, SMALL)
    assert before == {p: p.stat().st_mtime_ns for p in other.rglob("*") if p.is_file()}
    # A different config, or a missing ground-truth file (interrupted run), regenerates.
    bigger = syn.SyntheticConfig(size=40, frames=4, train_cameras=2, test_cameras=1, supersample=1)
    syn.write_synthetic_scene(other, bigger)
    assert json.loads((other / "ground_truth.json").read_text())["config"]["size"] == 40
    (other / "ground_truth.json").unlink()
    syn.write_synthetic_scene(other, bigger)
    assert (other / "ground_truth.json").exists()


def test_default_scene_dir_follows_env(monkeypatch, tmp_path):
    monkeypatch.setenv("SYNC4D_CACHE", str(tmp_path))
    assert syn.default_scene_dir().parent == tmp_path


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda gt: gt.pop("objects"), "malformed ground truth"),
        (lambda gt: [o["rotations"].pop() for o in gt["objects"]], "expected rotations"),
        (lambda gt: gt["objects"][1]["translations"][0].__setitem__(0, float("nan")), "NaN"),
        (lambda gt: gt["times"].__setitem__(1, "0.5"), r"'times'\[1\] must be a number"),
    ],
)
def test_malformed_ground_truth(small_scene, tmp_path, mutate, message):
    gt = json.loads((small_scene / "ground_truth.json").read_text())
    mutate(gt)
    (tmp_path / "ground_truth.json").write_text(json.dumps(gt))
    with pytest.raises(DatasetError, match=message) as e:
        syn.load_ground_truth(tmp_path)
    assert "ground_truth.json" in str(e.value)


def test_missing_or_invalid_ground_truth(tmp_path):
    with pytest.raises(DatasetError, match="missing"):
        syn.load_ground_truth(tmp_path)
    (tmp_path / "ground_truth.json").write_text("{not json")
    with pytest.raises(DatasetError, match="invalid JSON"):
        syn.load_ground_truth(tmp_path)
