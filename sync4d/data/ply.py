"""PLY point clouds through plyfile: the `vertex` element's x, y, z and optional red, green,
blue, in ASCII or binary files, e.g. the `sparse_pc.ply` that nerfstudio's `ns-process-data` and
`sync4d process` write. Other elements (faces) and vertex properties (normals) are ignored."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement, PlyHeaderParseError, PlyParseError

from sync4d.data.scene import DatasetError

__all__ = ["read_ply_points", "write_ply_points"]


def read_ply_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points [N, 3] float64 and colours [N, 3] float32 in [0, 1] (None when the vertices have
    no red/green/blue) of a PLY file; `DatasetError` naming the file when it cannot be read."""
    path = Path(path)
    try:
        ply = PlyData.read(str(path))
    except OSError as e:
        raise DatasetError(path, f"cannot read the point cloud ({e.strerror or e})") from None
    except PlyHeaderParseError as e:
        raise DatasetError(path, f"not a readable PLY header ({e})") from None
    except (PlyParseError, ValueError, EOFError):
        raise DatasetError(path, "PLY data is truncated or malformed") from None
    if not ply.elements or ply.elements[0].name != "vertex":
        raise DatasetError(path, "PLY file: its first element must be 'vertex'")
    vertex = ply["vertex"].data
    names = set(vertex.dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise DatasetError(path, f"PLY vertices need x, y, z; found {', '.join(sorted(names))}")
    points = np.stack([vertex[a].astype(np.float64) for a in "xyz"], 1)
    if not np.isfinite(points).all():
        raise DatasetError(path, "PLY vertices contain NaN or inf")
    colors = None
    if {"red", "green", "blue"} <= names:
        kind = vertex.dtype["red"]
        scale = 255.0 if kind == np.uint8 else 65535.0 if kind == np.uint16 else 1.0
        rgb = np.stack([vertex[c].astype(np.float64) for c in ("red", "green", "blue")], 1)
        colors = np.clip(rgb / scale, 0.0, 1.0).astype(np.float32)
    return points, colors


def write_ply_points(path: str | Path, points: np.ndarray, colors: np.ndarray) -> Path:
    """Write points [N, 3] and colours [N, 3] in [0, 1] as an ASCII PLY (float x, y, z and
    uint8 red, green, blue: the layout of nerfstudio's `sparse_pc.ply`)."""
    path = Path(path)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    rgb = (np.clip(np.asarray(colors, np.float64).reshape(-1, 3), 0, 1) * 255 + 0.5).astype(int)
    if len(rgb) != len(pts):
        raise ValueError(f"write_ply_points: {len(pts)} points but {len(rgb)} colours")
    vertex = np.empty(len(pts), [("x", "f4"), ("y", "f4"), ("z", "f4"),
                                 ("red", "u1"), ("green", "u1"), ("blue", "u1")])  # fmt: skip
    for k, name in enumerate(("x", "y", "z")):
        vertex[name] = pts[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        vertex[name] = rgb[:, k]
    PlyData([PlyElement.describe(vertex, "vertex")], text=True).write(str(path))
    return path
