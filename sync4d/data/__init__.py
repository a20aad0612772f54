"""Datasets behind one `Scene` interface: images, cameras (OpenCV, world-to-camera), per-frame
time in [0, 1], optional instance masks, and a train/test split.

Loaders convert every on-disk convention to that one camera contract; `loaders` is their
registry (one entry per layout, in detection order). Malformed input raises `DatasetError`
naming the file and the problem.
"""

from sync4d.lazy import lazy_exports

#: Public names and the module that defines each, imported on first use (the registry, which
#: `sync4d --help` reads, needs neither numpy nor a loader).
_EXPORTS = {
    "Camera": "scene", "DatasetError": "scene", "Frame": "scene", "Scene": "scene",
    "load_scene": "detect",
}  # fmt: skip

__all__, __getattr__ = lazy_exports(__name__, _EXPORTS)
