"""Phase 1 initialisation: the canonical Gaussians a run starts from (the dataset's point
cloud, or random points in a cube around where the cameras look, optionally with a shell of
points on a capture dome's wall), and the scene measures the trainers use (3DGS's camera
extent, the cameras' focus point).
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import numpy as np
import torch

from sync4d.data import DatasetError
from sync4d.data.scene import Scene
from sync4d.data.triangulate import (
    TriangulationConfig,
    is_multiview,
    triangulate_scene,
    views_at_one_instant,
)
from sync4d.events import InitialPoints, Triangulating, emit
from sync4d.phase1.deform import DeformConfig
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.settings import ConfigError

__all__ = ["INIT_SOURCES", "camera_sphere", "dome_points", "initial_model", "scene_extent",
           "scene_focus", "scene_scale", "with_dome_points", "with_initial_points"]  # fmt: skip

#: Where the initial points come from (`Phase1Config.init_from`).
INIT_SOURCES = ("auto", "points", "triangulate", "random")


class Phase1Settings(Protocol):
    """The initialisation settings of `sync4d.phase1.config.Phase1Config` these read."""

    init_from: str
    init_dome_points: int
    init_dome_radius: float
    seed: int


def scene_extent(scene: Scene) -> float:
    """Radius of the training cameras around their centroid, times 1.1 (3DGS's extent)."""
    centres = np.stack([f.camera.center for f in scene.train])
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max() + 1e-6)


def scene_scale(scene: Scene) -> float:
    """The scene's size in world units for the watchdog's divergence bounds: the larger of
    `scene_extent` and the farthest training camera's distance from the origin (a single
    camera has no extent)."""
    centres = np.stack([f.camera.center for f in scene.train])
    return max(scene_extent(scene), float(np.linalg.norm(centres, axis=1).max()))


def scene_focus(scene: Scene) -> tuple[np.ndarray, float]:
    """Point [3] closest (least squares) to every training camera's optical axis, and the mean
    camera distance to it: where an object-centric capture looks, and from how far."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    centres = []
    for f in scene.train:
        c = f.camera.center
        d = f.camera.viewmat[2, :3]  # optical axis (camera +z) in world coordinates
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
        centres.append(c)
    centres_arr = np.stack(centres)
    if np.linalg.cond(a) > 1e8:  # parallel axes (e.g. a forward-facing rig): use the centroid
        focus = centres_arr.mean(0)
    else:
        focus = np.linalg.solve(a, b)
    dist = float(np.linalg.norm(centres_arr - focus, axis=1).mean())
    return focus, max(dist, 1e-6)


#: Largest spread of the camera distances from the fitted sphere's centre, as a fraction of its
#: radius, for `camera_sphere` to call the cameras a dome (Panoptic's 31 HD cameras: 0.4 %).
DOME_TOLERANCE = 0.05


def camera_sphere(scene: Scene) -> tuple[np.ndarray, float] | None:
    """Centre [3] and radius of the sphere through every camera of `scene` (least squares), or
    None when the cameras do not fix one or do not lie on it (fewer than 4 distinct cameras,
    all of them on one plane, or a distance off by more than `DOME_TOLERANCE` of the
    radius)."""
    centres = np.unique(
        np.round(np.stack([f.camera.center for f in scene.train + scene.test]), 6), axis=0
    )
    a = np.c_[2.0 * centres, np.ones(len(centres))]
    if len(centres) < 4 or np.linalg.matrix_rank(a) < 4:  # too few, or all on one plane
        return None
    sol, *_ = np.linalg.lstsq(a, (centres**2).sum(1), rcond=None)
    centre = sol[:3]
    r2 = sol[3] + centre @ centre
    if not np.isfinite(r2) or r2 <= 0:
        return None
    radius = float(np.sqrt(r2))
    spread = np.abs(np.linalg.norm(centres - centre, axis=1) - radius).max() / radius
    return (centre, radius) if spread <= DOME_TOLERANCE else None


def dome_points(
    scene: Scene, count: int, radius_factor: float = 1.03, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Points [M, 3] float64 and colours [M, 3] float32 on the wall of a capture dome: `count`
    directions uniform on the sphere through the cameras (`camera_sphere`), at `radius_factor`
    times its radius (just behind the cameras, which hang on the wall), each coloured by the
    median of the training images it projects into at the instant triangulation uses
    (`views_at_one_instant`); directions no such image sees are dropped. Raises ValueError
    when the cameras are not on a sphere."""
    sphere = camera_sphere(scene)
    if sphere is None:
        raise ValueError(
            f"scene '{scene.name}': its cameras do not lie on a sphere (a capture dome), so "
            "there is no dome wall to place points on; set init_dome_points = 0"
        )
    centre, radius = sphere
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(count, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    pts = centre + radius_factor * radius * dirs
    samples: list[np.ndarray] = []
    owners: list[np.ndarray] = []
    for f in views_at_one_instant(scene.train)[1]:
        cam = f.camera
        uv, z = cam.project(pts)
        u, v = uv[:, 0], uv[:, 1]
        inside = (z > 1e-3) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        idx = np.nonzero(inside)[0]
        img = f.load_image()
        samples.append(img[v[idx].astype(int), u[idx].astype(int)])
        owners.append(idx)
    owner = np.concatenate(owners)
    colour = np.concatenate(samples)
    if len(owner) == 0:  # no image sees the sphere
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    order = np.argsort(owner, kind="stable")
    owner, colour = owner[order], colour[order]
    seen, starts = np.unique(owner, return_index=True)
    medians = np.stack([np.median(c, axis=0) for c in np.split(colour, starts[1:])])
    return pts[seen], medians.astype(np.float32)


def initial_model(
    scene: Scene,
    num_random: int = 20_000,
    sh_degree: int = 3,
    deform: DeformConfig | None = None,
    box_fraction: float = 0.33,
    seed: int = 42,
    near: float = 0.01,
    init_scale: float = 0.02,
) -> DeformableGaussians:
    """Canonical Gaussians for `scene`: its points (and colours) when it has a point cloud
    (COLMAP), otherwise `num_random` points uniform in a cube of half-size `box_fraction` times
    the camera distance around the point the cameras look at (D-NeRF: about [-1.3, 1.3]^3);
    `near`: the model's near clipping plane, `init_scale` every Gaussian's initial scale (world
    units)."""
    g = torch.Generator().manual_seed(seed)
    if scene.points is not None and len(scene.points) > 0:
        pts = torch.as_tensor(np.asarray(scene.points), dtype=torch.float32)
        cols = scene.point_colors
        colors = None if cols is None else torch.as_tensor(np.asarray(cols), dtype=torch.float32)
        return DeformableGaussians(
            pts, colors, sh_degree=sh_degree, config=deform, generator=g, near=near,
            init_scale=init_scale,
        )  # fmt: skip
    focus, dist = scene_focus(scene)
    half = box_fraction * dist
    lo = torch.as_tensor(focus - half, dtype=torch.float32)
    hi = torch.as_tensor(focus + half, dtype=torch.float32)
    return DeformableGaussians.random_in_box(
        num_random, lo, hi, generator=g, sh_degree=sh_degree, config=deform, near=near,
        init_scale=init_scale,
    )  # fmt: skip


def with_initial_points(scene: Scene, p1: Phase1Settings, threads: int = 1) -> Scene:
    """`scene` with the point cloud `p1.init_from` asks for: its own points, points
    triangulated (on `threads` threads) from one instant of a multi-view capture, or none
    (random initialisation)."""
    source = p1.init_from
    if source not in INIT_SOURCES:
        raise ConfigError(f"init_from: expected one of {', '.join(INIT_SOURCES)}, got {source!r}")
    has_points = scene.points is not None and len(scene.points) > 0
    if source == "auto":
        source = "points" if has_points else "triangulate" if is_multiview(scene) else "random"
    if source == "points":
        if not has_points:
            raise ConfigError(
                f"phase1.init_from=points: the dataset '{scene.name}' has no point cloud; "
                "use phase1.init_from=triangulate (multi-view) or random"
            )
        return with_dome_points(scene, p1)
    if source == "random":
        if p1.init_dome_points > 0:
            raise ConfigError(
                "phase1.init_dome_points adds to a point cloud; use phase1.init_from=points or "
                "triangulate with it, or set phase1.init_dome_points = 0"
            )
        return dataclasses.replace(scene, points=None, point_colors=None)
    emit(Triangulating(scene.name))
    tri = triangulate_scene(scene, TriangulationConfig(threads=threads))
    if len(tri.points) == 0:
        raise DatasetError(
            scene.train[0].image_path.parent,
            "triangulation found no points (too little texture?); use phase1.init_from=random",
        )
    emit(InitialPoints("triangulation", len(tri.points), tri.views, float(tri.time),
                       float(tri.seconds), bool(tri.cached)))  # fmt: skip
    return with_dome_points(
        dataclasses.replace(scene, points=tri.points, point_colors=tri.colors), p1
    )


def with_dome_points(scene: Scene, p1: Phase1Settings) -> Scene:
    """`scene` with `p1.init_dome_points` points on its capture dome's wall added to its point
    cloud (unchanged when that is 0); ConfigError when the cameras are not on a sphere."""
    if p1.init_dome_points <= 0:
        return scene
    try:
        pts, cols = dome_points(scene, p1.init_dome_points, p1.init_dome_radius, p1.seed)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    emit(InitialPoints("dome", len(pts)))
    base = np.zeros((0, 3)) if scene.points is None else np.asarray(scene.points, np.float64)
    base_cols = scene.point_colors
    if base_cols is None:
        base_cols = np.full((len(base), 3), 0.5, np.float32)
    return dataclasses.replace(
        scene,
        points=np.concatenate([base, pts]),
        point_colors=np.concatenate([np.asarray(base_cols, np.float32), cols]),
    )
