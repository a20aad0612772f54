"""Phase 1 initialisation: the canonical Gaussians a run starts from (the dataset's point
cloud, or random points in a cube around where the cameras look), and the scene measures the
trainers use (3DGS's camera extent, the cameras' focus point).
"""

from __future__ import annotations

import numpy as np
import torch

from sync4d.data.scene import Scene
from sync4d.phase1.deform import DeformConfig
from sync4d.phase1.gaussians import DeformableGaussians

__all__ = ["initial_model", "scene_extent", "scene_focus"]


def scene_extent(scene: Scene) -> float:
    """Radius of the training cameras around their centroid, times 1.1 (3DGS's extent)."""
    centres = np.stack([f.camera.center for f in scene.train])
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max() + 1e-6)


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


def initial_model(
    scene: Scene,
    num_random: int = 20_000,
    sh_degree: int = 3,
    deform: DeformConfig | None = None,
    box_fraction: float = 0.33,
    seed: int = 42,
    near: float = 0.01,
) -> DeformableGaussians:
    """Canonical Gaussians for `scene`: its points (and colours) when it has a point cloud
    (COLMAP), otherwise `num_random` points uniform in a cube of half-size `box_fraction` times
    the camera distance around the point the cameras look at (D-NeRF: about [-1.3, 1.3]^3);
    `near`: the model's near clipping plane (world units)."""
    g = torch.Generator().manual_seed(seed)
    if scene.points is not None and len(scene.points) > 0:
        pts = torch.as_tensor(np.asarray(scene.points), dtype=torch.float32)
        cols = scene.point_colors
        colors = None if cols is None else torch.as_tensor(np.asarray(cols), dtype=torch.float32)
        return DeformableGaussians(
            pts, colors, sh_degree=sh_degree, config=deform, generator=g, near=near
        )
    focus, dist = scene_focus(scene)
    half = box_fraction * dist
    lo = torch.as_tensor(focus - half, dtype=torch.float32)
    hi = torch.as_tensor(focus + half, dtype=torch.float32)
    return DeformableGaussians.random_in_box(
        num_random, lo, hi, generator=g, sh_degree=sh_degree, config=deform, near=near
    )
