"""The Dynamic-3DGS layout of CMU Panoptic captures: `train_meta.json` / `test_meta.json` with
`w`, `h`, per-timestep per-camera intrinsics `k` [T][C][3][3] and OpenCV world-to-camera `w2c`
[T][C][4][4], image paths `fn` [T][C] under `ims/`, and optional binary foreground masks
`seg/<cam>/<frame>.png` (label 1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.data.blender import _read_json
from sync4d.data.scene import Camera, DatasetError, Frame, Scene


def _load_meta(root: Path, name: str, resolution_scale: float) -> list[Frame]:
    path = root / name
    meta = _read_json(path)
    for key in ("w", "h", "k", "w2c", "fn"):
        if key not in meta:
            raise DatasetError(path, f"missing '{key}'")
    w, h = int(meta["w"]), int(meta["h"])
    fns = meta["fn"]
    t_count = len(fns)
    if t_count == 0:
        raise DatasetError(path, "'fn' lists no timesteps")
    try:
        ks = np.asarray(meta["k"], dtype=np.float64)
        w2cs = np.asarray(meta["w2c"], dtype=np.float64)
    except ValueError:
        raise DatasetError(path, "'k' and 'w2c' must be rectangular [T][cams] arrays") from None
    cams = len(fns[0])
    if ks.shape != (t_count, cams, 3, 3):
        raise DatasetError(
            path, f"'k' must have shape [{t_count}, {cams}, 3, 3], got {list(ks.shape)}"
        )
    if w2cs.shape != (t_count, cams, 4, 4):
        raise DatasetError(
            path, f"'w2c' must have shape [{t_count}, {cams}, 4, 4], got {list(w2cs.shape)}"
        )
    if not (np.isfinite(ks).all() and np.isfinite(w2cs).all()):
        raise DatasetError(path, "'k' or 'w2c' contains NaN or inf")
    frames: list[Frame] = []
    for t, row in enumerate(fns):
        if len(row) != cams:
            raise DatasetError(path, f"timestep {t} lists {len(row)} cameras, expected {cams}")
        time = t / max(1, t_count - 1)
        for c, fn in enumerate(row):
            img = root / "ims" / fn
            if not img.exists():
                raise DatasetError(img, f"image file is missing (timestep {t} of {name})")
            k = ks[t, c]
            cam = Camera(w2cs[t, c], k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h)
            if resolution_scale != 1.0:
                cam = cam.scaled(resolution_scale)
            seg = root / "seg" / Path(fn).with_suffix(".png")
            label = f"cam{Path(fn).parent.name}_{Path(fn).name}"
            frames.append(Frame(img, cam, time, seg if seg.exists() else None, (w, h), label))
    return frames


def load_panoptic(root: str | Path, resolution_scale: float = 1.0) -> Scene:
    """Load a Dynamic-3DGS Panoptic sequence directory (e.g. `basketball/`)."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(root, "dataset directory does not exist")
    if not (0.0 < resolution_scale <= 1.0):
        raise DatasetError(root, f"resolution scale must be in (0, 1], got {resolution_scale}")
    train = _load_meta(root, "train_meta.json", resolution_scale)
    test = _load_meta(root, "test_meta.json", resolution_scale)
    labels = {0: "background", 1: "foreground"} if any(f.mask_path for f in train) else None
    return Scene(root.name, train, test, labels)
