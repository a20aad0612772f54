"""Phase 1's initial points (`sync4d.phase1.init`): the source `init_from` picks (the dataset's
points, triangulated from a multi-view instant, or none), and points on a capture dome's wall
(`init_dome_points`): the sphere through the cameras, colours from the first instant's images,
and the refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from support.cameras import look_at_w2c
from support.datasets import write_blender
from sync4d.config import ConfigError, RunConfig, load_config
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.data.scene import Camera, DatasetError, Frame, Scene
from sync4d.phase1.init import camera_sphere, dome_points, with_dome_points, with_initial_points

#: A multi-view capture: 24 cameras at each of two instants.
MULTIVIEW = syn.SyntheticConfig(size=256, frames=2, train_cameras=24, test_cameras=1,
                                test_every=2, supersample=1)  # fmt: skip
CENTRE = np.array([0.5, -1.0, 0.2])
RADIUS = 2.0
COLOUR = (51, 102, 153)


def _scene(tmp_path, eyes: np.ndarray, times: tuple[float, ...] = (0.0, 0.5)) -> Scene:
    path = tmp_path / "wall.png"
    Image.new("RGB", (16, 12), COLOUR).save(path)
    frames = [
        Frame(path, Camera(look_at_w2c(e, CENTRE), 12.0, 12.0, 8.0, 6.0, 16, 12), t,
              name=f"{i}_{t}")  # fmt: skip
        for t in times
        for i, e in enumerate(eyes)
    ]
    return Scene("dome", frames, frames[:1])


def _dome_eyes(n: int = 14, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return CENTRE + RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True)


def test_points_lie_behind_the_cameras_sphere_with_the_images_colour(tmp_path) -> None:
    scene = _scene(tmp_path, _dome_eyes())
    centre, radius = camera_sphere(scene)
    assert np.allclose(centre, CENTRE, atol=1e-9) and radius == pytest.approx(RADIUS)
    pts, cols = dome_points(scene, 500, radius_factor=1.05, seed=1)
    assert 0 < len(pts) <= 500 and pts.shape == (len(pts), 3) and cols.dtype == np.float32
    assert np.allclose(np.linalg.norm(pts - CENTRE, axis=1), 1.05 * RADIUS)
    assert np.allclose(cols, np.array(COLOUR) / 255.0, atol=1e-6)
    again, _ = dome_points(scene, 500, radius_factor=1.05, seed=1)
    assert np.array_equal(pts, again)


def test_cameras_on_a_ring_or_off_a_sphere_are_refused(tmp_path) -> None:
    ang = np.linspace(0, 2 * np.pi, 9)[:-1]
    ring = CENTRE + RADIUS * np.c_[np.cos(ang), np.sin(ang), np.zeros_like(ang)]
    assert camera_sphere(_scene(tmp_path, ring)) is None
    bumpy = _dome_eyes() * np.linspace(0.8, 1.2, 14)[:, None]
    with pytest.raises(ValueError, match="do not lie on a sphere"):
        dome_points(_scene(tmp_path, bumpy), 100)


def test_fit_adds_them_to_the_point_cloud_and_refuses_random_init(tmp_path) -> None:
    base = np.zeros((3, 3))
    scene = dataclasses.replace(
        _scene(tmp_path, _dome_eyes()), points=base, point_colors=np.ones((3, 3), np.float32)
    )
    cfg = load_config(None, ["phase1.init_dome_points=200", "phase1.init_from=points"])
    out = with_dome_points(scene, cfg.phase1)
    assert len(out.points) > 3 and np.array_equal(out.points[:3], base)
    assert len(out.point_colors) == len(out.points)
    assert with_dome_points(scene, load_config(None, []).phase1) is scene
    bad = load_config(None, ["phase1.init_dome_points=200", "phase1.init_from=random"])
    with pytest.raises(ConfigError, match="init_dome_points"):
        with_initial_points(scene, bad.phase1)


def test_a_sphere_no_image_sees_gives_no_points(tmp_path) -> None:
    eyes = _dome_eyes()
    scene = _scene(tmp_path, eyes)
    for f in scene.train:  # turn every camera round: the inner sphere is behind them all
        away = look_at_w2c(f.camera.center, 2 * f.camera.center - CENTRE)
        f.camera = dataclasses.replace(f.camera, viewmat=away)
    pts, cols = dome_points(scene, 200, radius_factor=0.5)
    assert pts.shape == (0, 3) and cols.shape == (0, 3)


def test_init_from_chooses_the_source(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SYNC4D_CACHE", str(tmp_path / "cache"))
    multi = load_scene(syn.write_synthetic_scene(tmp_path / "multi", MULTIVIEW))
    root = tmp_path / "mono"
    write_blender(root, n=4, size=24)
    mono = load_scene(root)
    cfg = RunConfig()
    assert cfg.phase1.init_from == "auto"
    got = with_initial_points(multi, cfg.phase1)
    assert got.points is not None and len(got.points) >= 100  # auto: multi-view -> triangulate
    assert with_initial_points(mono, cfg.phase1).points is None  # auto: mono -> random
    random = load_config(None, ["phase1.init_from=random"])
    assert with_initial_points(got, random.phase1).points is None
    assert with_initial_points(got, load_config(None, ["phase1.init_from=points"]).phase1) is got
    with pytest.raises(ConfigError, match="has no point cloud"):
        with_initial_points(mono, load_config(None, ["phase1.init_from=points"]).phase1)
    with pytest.raises(ConfigError, match="init_from: expected one of"):
        with_initial_points(mono, load_config(None, ["phase1.init_from=sfm"]).phase1)
    with pytest.raises(DatasetError, match="at least two training cameras"):
        with_initial_points(mono, load_config(None, ["phase1.init_from=triangulate"]).phase1)
