"""Pick the loader for a dataset directory by the files it contains (the registry and its
detection order: `sync4d.data.loaders`)."""

from __future__ import annotations

from pathlib import Path

from sync4d.data.loaders import prepare
from sync4d.data.scene import Scene, check_scene


def load_scene(root: str | Path, resolution_scale: float = 1.0, test_split: str = "test") -> Scene:
    """Load a dataset directory in any registered layout: the first loader in detection order
    that recognises its files reads it (`sync4d.data.loaders`, listed in docs/datasets.md),
    after the shared checks (`prepare`; `test_split` "val" picks D-NeRF's validation frames
    as the test split). Every image and mask header is then checked (`check_scene`), so a bad
    file fails here, before any training."""
    path, loader = prepare(root, resolution_scale, test_split)
    scene = loader.reader()(path, resolution_scale, test_split)
    check_scene(scene)
    return scene
