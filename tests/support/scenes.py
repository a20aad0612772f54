"""Seeded scenes the tests build: random Gaussians for the rasterizer and for Phase 1, the orbit
scene rendered from known Gaussians, and small configurations of the embedded synthetic scene.
Same arguments, same tensors: each builder draws from its own seeded generator, in a fixed
order."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from sync4d.data import synthetic as syn
from sync4d.data.scene import Camera, Frame, Scene
from sync4d.phase1.densify import PER_GAUSSIAN
from sync4d.phase1.gaussians import DeformableGaussians


def raster_scene(
    n: int,
    width: int,
    height: int,
    channels: int = 3,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> dict:
    """The rasterizer's inputs (a dict of tensors, the camera and the image size): ``n``
    overlapping Gaussians in front of an identity camera, seeded."""
    g = torch.Generator().manual_seed(seed)
    f = 0.9 * max(width, height)
    z = torch.rand(n, generator=g, dtype=torch.float64) * 2.0 + 2.0
    x = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * z * width / (2 * f)
    y = (torch.rand(n, generator=g, dtype=torch.float64) * 2 - 1) * z * height / (2 * f)
    scene = {
        "means": torch.stack([x, y, z], 1),
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": torch.exp(
            torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.4 + math.log(0.08)
        ),
        "opacities": torch.rand(n, generator=g, dtype=torch.float64) * 0.85 + 0.1,
        "features": torch.rand(n, channels, generator=g, dtype=torch.float64),
        "viewmat": torch.eye(4, dtype=torch.float64),
        "K": torch.tensor(
            [[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64
        ),
        "width": width,
        "height": height,
    }
    for k in ("means", "quats", "scales", "opacities", "features"):
        scene[k] = scene[k].to(dtype)
    return scene


def random_gaussians(
    n: int,
    generator: torch.Generator | int,
    *,
    spread: float = 1.0,
    scale: float | None = None,
    opacity_logit: float | None = None,
    **options,
) -> DeformableGaussians:
    """A Phase 1 model of ``n`` Gaussians at normal positions (std ``spread``) with uniform
    random colours, then initialised by the model itself, all drawn from ``generator`` (an int
    seeds a new one; pass a generator to keep drawing from it after). ``scale`` and
    ``opacity_logit`` set every Gaussian's; ``options`` go to `DeformableGaussians`
    (``sh_degree``, ``config``)."""
    g = torch.Generator().manual_seed(generator) if isinstance(generator, int) else generator
    points = torch.randn(n, 3, generator=g)
    if spread != 1.0:
        points = points * spread
    model = DeformableGaussians(points, torch.rand(n, 3, generator=g), generator=g, **options)
    with torch.no_grad():
        if scale is not None:
            model.log_scales.fill_(math.log(scale))
        if opacity_logit is not None:
            model.opacity_logits.fill_(opacity_logit)
    return model


def densify_case() -> tuple[DeformableGaussians, torch.optim.Adam]:
    """Six Gaussians for densification (3 and 4 large: they split; 5 transparent: it is
    pruned) and an Adam over them that has taken one step (its moments are not zero)."""
    model = random_gaussians(6, 0)
    with torch.no_grad():
        model.log_scales[3:5] = math.log(0.5)  # large: will split
        model.opacity_logits[5] = -10.0  # transparent: will be pruned
    params = [getattr(model, n) for n in PER_GAUSSIAN]
    opt = torch.optim.Adam(
        [{"params": [p], "name": n} for n, p in zip(PER_GAUSSIAN, params, strict=True)]
        + [{"params": model.deform.parameters()}],
        lr=1e-3,
    )
    loss = sum((getattr(model, n) ** 2).sum() for n in PER_GAUSSIAN)
    loss.backward()
    opt.step()
    return model, opt


def orbit_camera(angle: float, w: int = 40, h: int = 32) -> Camera:
    """A camera 3 units from the origin at `angle` around the y axis, looking at it (y up)."""
    eye = np.array([3.0 * math.sin(angle), 0.3, -3.0 * math.cos(angle)])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross([0.0, 1.0, 0.0], fwd)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd])  # rows: camera axes in world coordinates (OpenCV)
    vm = np.eye(4)
    vm[:3, :3] = r
    vm[:3, 3] = -r @ eye
    return Camera(vm, 40.0, 40.0, w / 2, h / 2, w, h)


def orbit_scene(tmp_path: Path) -> tuple[Scene, DeformableGaussians]:
    """Six 40x32 views on an orbit (`orbit_camera`) of 40 known static Gaussians (seed 0),
    written as PNGs under `tmp_path`, at times 0..1; the first two are also the test frames.
    Returns the scene and the Gaussians that drew it."""
    gt = random_gaussians(40, 0, spread=0.4, scale=0.12, opacity_logit=2.0, sh_degree=0)
    frames = []
    for i in range(6):
        cam = orbit_camera(2 * math.pi * i / 6)
        with torch.no_grad():
            img = gt.render(cam, 0.0, background=torch.ones(3), threads=1).features
        path = tmp_path / f"f{i}.png"
        Image.fromarray((img.clamp(0, 1).numpy() * 255).round().astype(np.uint8)).save(path)
        frames.append(Frame(path, cam, i / 5))
    return Scene("synthetic", frames, frames[:2]), gt


def orbit_student(gt: DeformableGaussians, seed: int, jitter: float = 0.0) -> DeformableGaussians:
    """A model to train on the orbit scene: at `gt`'s positions (plus normal noise of std
    `jitter` when not 0), grey, small (scale 0.1), D_theta drawn from `seed`."""
    g = torch.Generator().manual_seed(seed)
    if jitter:
        means = gt.means.data + torch.randn(gt.num_gaussians, 3, generator=g) * jitter
    else:
        means = gt.means.data.clone()
    model = DeformableGaussians(means, None, sh_degree=0, generator=g)
    with torch.no_grad():
        model.log_scales.fill_(math.log(0.1))
    return model


def small_synthetic(
    size: int = 48,
    frames: int = 6,
    train_cameras: int = 4,
    test_every: int = 3,
    supersample: int = 1,
    **changes,
) -> syn.SyntheticConfig:
    """A small embedded synthetic scene (one test camera; no supersampling unless asked):
    seconds to write, yet every object seen and masked."""
    return syn.SyntheticConfig(size=size, frames=frames, train_cameras=train_cameras,
                               test_cameras=1, test_every=test_every, supersample=supersample,
                               **changes)  # fmt: skip


#: The embedded scene with nothing moving (`still=True`), supersampled as by default.
STILL_SCENE = small_synthetic(still=True, supersample=2)
