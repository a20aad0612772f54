"""Shared fixtures: deterministic thread counts and small seeded scenes."""

from __future__ import annotations

import math
import os

import pytest
import torch
from hypothesis import settings

# Deterministic property tests in CI (the same examples every run); set
# HYPOTHESIS_PROFILE=explore to draw new random examples locally.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

# Two cores on CI: never oversubscribe (torch + rayon).
torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))

SHARED_DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")


def make_scene(
    n: int,
    width: int,
    height: int,
    channels: int = 3,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
) -> dict:
    """A seeded random scene of ``n`` overlapping Gaussians in front of an identity camera."""
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


@pytest.fixture
def small_scene() -> dict:
    return make_scene(40, 48, 40)
