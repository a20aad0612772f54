"""Look-at camera poses for the test scenes and dataset writers."""

from __future__ import annotations

import numpy as np


def look_at_gl(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] OpenGL camera-to-world from `eye` looking at `target` (z up world)."""
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
    return m


def look_at_w2c(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[4, 4] OpenCV world-to-camera from `eye` towards `target` (z up world; x up when looking
    along z; y down in the image)."""
    fwd = (target - eye) / np.linalg.norm(target - eye)
    up = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    r = np.stack([right, down, fwd])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, -r @ eye
    return m
