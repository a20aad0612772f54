"""Datasets behind one `Scene` interface: images, cameras (OpenCV, world-to-camera), per-frame
time in [0, 1], optional instance masks, and a train/test split.

Loaders convert every on-disk convention to that one camera contract. Malformed input raises
`DatasetError` naming the file and the problem.
"""

from sync4d.data.detect import load_scene
from sync4d.data.scene import Camera, DatasetError, Frame, Scene

__all__ = ["Camera", "DatasetError", "Frame", "Scene", "load_scene"]
