"""Initial points triangulated from one instant of a multi-view capture (pycolmap, fixed poses):
the points lie on the true surfaces of the synthetic scene, results are cached, monocular
scenes are refused with a clear error. Which source `init_from` picks is Phase 1's:
tests/phase1/test_initial_points.py."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from support.datasets import write_blender
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.data.scene import DatasetError
from sync4d.data.triangulate import (
    TriangulationConfig,
    is_multiview,
    triangulate_scene,
    views_at_one_instant,
)

SCENE = syn.SyntheticConfig(size=256, frames=2, train_cameras=24, test_cameras=1, test_every=2,
                            supersample=1)  # fmt: skip
ONE_THREAD = TriangulationConfig(threads=1)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory) -> Path:
    return syn.write_synthetic_scene(tmp_path_factory.mktemp("multiview"), SCENE)


def _surface_distance(p: np.ndarray, t: float) -> np.ndarray:
    """Distance [N] from world points to the nearest surface of the synthetic scene at `t`."""
    d = np.abs(p[:, 2])  # the ground plane z = 0
    poses = syn.object_poses(t)
    for obj in syn.OBJECTS:
        rot, centre = poses[obj.label]
        local = (p - centre) @ rot  # R^T (p - c)
        if obj.kind == "sphere":
            d = np.minimum(d, np.abs(np.linalg.norm(local, axis=1) - obj.size[0]))
        else:
            q = np.abs(local) - np.asarray(obj.size)
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
            inside = np.minimum(q.max(axis=1), 0.0)
            d = np.minimum(d, np.abs(outside + inside))
    return d


def test_points_lie_on_the_true_surfaces(synthetic, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SYNC4D_CACHE", str(tmp_path / "cache"))
    scene = load_scene(synthetic)
    assert is_multiview(scene)
    tri = triangulate_scene(scene, ONE_THREAD)
    assert tri.views == SCENE.train_cameras and tri.time == 0.0 and not tri.cached
    assert len(tri.points) >= 100
    assert tri.points.shape == (len(tri.points), 3) and tri.colors.shape == tri.points.shape
    assert 0.0 <= tri.colors.min() and tri.colors.max() <= 1.0
    dist = _surface_distance(tri.points, tri.time)
    # Scene extent about 2.5 m, a pixel about 1 cm at the scene centre. Some features sit on
    # occlusion boundaries or repeat along the objects' stripes, so not every point is exact;
    # points uniform in the scene box would have a median distance of about 0.3 m.
    assert np.median(dist) < 0.03, np.median(dist)
    assert np.mean(dist < 0.05) > 0.6, np.mean(dist < 0.05)
    # A second call reads the cache and returns the same cloud.
    again = triangulate_scene(scene, ONE_THREAD)
    assert again.cached
    np.testing.assert_array_equal(again.points, tri.points)


def test_views_at_one_instant_prefers_most_cameras_then_earliest(synthetic) -> None:
    scene = load_scene(synthetic)
    t, frames = views_at_one_instant(scene.train[1:])  # drop one view of t = 0
    assert t == 1.0 and len(frames) == SCENE.train_cameras
    t, frames = views_at_one_instant(scene.train)
    assert t == 0.0 and len(frames) == SCENE.train_cameras


def test_monocular_scene_is_refused(tmp_path) -> None:
    root = tmp_path / "mono"
    write_blender(root, n=4, size=24)
    scene = load_scene(root)
    assert not is_multiview(scene)
    with pytest.raises(DatasetError, match="at least two training cameras"):
        triangulate_scene(scene, ONE_THREAD, use_cache=False)
