"""Datasets behind one `Scene` interface: images, cameras (OpenCV, world-to-camera), per-frame
time in [0, 1], optional instance masks, and a train/test split.

Loaders convert every on-disk convention to that one camera contract; `loaders` is their
registry (one entry per layout, in detection order). Malformed input raises `DatasetError`
naming the file and the problem.
"""

from importlib import import_module

#: Public names and the module that defines each, imported on first use (the registry, which
#: `sync4d --help` reads, needs neither numpy nor a loader).
_EXPORTS = {
    "Camera": "scene", "DatasetError": "scene", "Frame": "scene", "Scene": "scene",
    "load_scene": "detect",
}  # fmt: skip

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):  # noqa: ANN202 - PEP 562 module attribute
    if name not in _EXPORTS:
        raise AttributeError(f"module 'sync4d.data' has no attribute {name!r}")
    module = import_module(f"sync4d.data.{_EXPORTS[name]}")
    return getattr(module, name)
