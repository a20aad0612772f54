"""Settings for every test (deterministic Hypothesis profiles, thread counts) and shared
fixtures; shared functions are in `support`, which no test reaches through this file."""

from __future__ import annotations

import os

import pytest
import torch
from hypothesis import settings

from support.scenes import raster_scene

# Deterministic property tests in CI (the same examples every run); set
# HYPOTHESIS_PROFILE=explore to draw new random examples locally.
settings.register_profile("deterministic", derandomize=True, database=None)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

# Two cores on CI: never oversubscribe (torch + rayon).
torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "2")))


@pytest.fixture
def small_scene() -> dict:
    return raster_scene(40, 48, 40)
