"""A small PLY point-cloud reader and writer (no dependency beyond numpy): the `vertex`
element's x, y, z and optional red, green, blue, in ASCII or binary (either byte order) files,
e.g. the `sparse_pc.ply` that nerfstudio's `ns-process-data` and `sync4d process` write. Other
elements (faces) and other vertex properties (normals) are skipped."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.data.scene import DatasetError

__all__ = ["read_ply_points", "write_ply_points"]

#: PLY scalar types and their numpy equivalents (both spellings of the standard).
_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def _header(path: Path, raw: bytes) -> tuple[str, list[tuple[str, int, list]], int]:
    """(format, [(element, count, [(property, numpy type) or ("list", ...)])], the offset of
    the data after the header)."""
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    newline = raw.find(b"\n", end)
    offset = len(raw) if newline < 0 else newline + 1
    fmt = ""
    elements: list[tuple[str, int, list]] = []
    for line in raw[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1][2].append(("list", words[2], words[3], words[4]))
            elif words[1] in _TYPES and len(words) == 3:
                elements[-1][2].append((words[2], _TYPES[words[1]]))
            else:
                raise DatasetError(path, f"PLY header: cannot read the line '{line.strip()}'")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(path, f"PLY header: unknown format '{fmt}'")
    return fmt, elements, offset


def read_ply_points(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Points [N, 3] float64 and colours [N, 3] float32 in [0, 1] (None when the vertices have
    no red/green/blue) of a PLY file; `DatasetError` naming the file when it cannot be read."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DatasetError(path, f"cannot read the point cloud ({e.strerror or e})") from None
    fmt, elements, offset = _header(path, raw)
    if not elements or elements[0][0] != "vertex":
        raise DatasetError(path, "PLY file: its first element must be 'vertex'")
    _, count, props = elements[0]
    if any(p[0] == "list" for p in props):
        raise DatasetError(path, "PLY vertices with list properties are not supported")
    names = [p[0] for p in props]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(path, f"PLY vertices need x, y, z; found {', '.join(names)}")
    try:
        if fmt == "ascii":
            rows = [ln.split() for ln in raw[offset:].decode("ascii").split("\n")[:count]]
            table = np.array(rows, dtype=np.float64).reshape(count, len(props))
            columns = {n: table[:, i] for i, n in enumerate(names)}
        else:
            order = "<" if fmt == "binary_little_endian" else ">"
            dtype = np.dtype([(n, order + t) for n, t in props])
            data = np.frombuffer(raw, dtype=dtype, count=count, offset=offset)
            columns = {n: data[n].astype(np.float64) for n in names}
    except (ValueError, UnicodeDecodeError):
        raise DatasetError(
            path, f"PLY data is truncated or malformed (expected {count} vertices)"
        ) from None
    points = np.stack([columns["x"], columns["y"], columns["z"]], 1)
    if not np.isfinite(points).all():
        raise DatasetError(path, "PLY vertices contain NaN or inf")
    colors = None
    if {"red", "green", "blue"} <= set(names):
        kind = dict(props)["red"]
        scale = 255.0 if kind == "u1" else 65535.0 if kind == "u2" else 1.0
        rgb = np.stack([columns["red"], columns["green"], columns["blue"]], 1) / scale
        colors = np.clip(rgb, 0.0, 1.0).astype(np.float32)
    return points, colors


def write_ply_points(path: str | Path, points: np.ndarray, colors: np.ndarray) -> Path:
    """Write points [N, 3] and colours [N, 3] in [0, 1] as an ASCII PLY (float x, y, z and
    uint8 red, green, blue: the layout of nerfstudio's `sparse_pc.ply`)."""
    path = Path(path)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    rgb = (np.clip(np.asarray(colors, np.float64).reshape(-1, 3), 0, 1) * 255 + 0.5).astype(int)
    if len(rgb) != len(pts):
        raise ValueError(f"write_ply_points: {len(pts)} points but {len(rgb)} colours")
    header = (
        f"ply\nformat ascii 1.0\nelement vertex {len(pts)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uint8 red\nproperty uint8 green\nproperty uint8 blue\nend_header\n"
    )
    rows = [
        f"{x:.7g} {y:.7g} {z:.7g} {r} {g} {b}\n"
        for (x, y, z), (r, g, b) in zip(pts, rgb, strict=True)
    ]
    path.write_text(header + "".join(rows), encoding="ascii")
    return path
