"""The Dynamic-3DGS layout of CMU Panoptic captures: `train_meta.json` / `test_meta.json` with
`w`, `h`, per-timestep per-camera intrinsics `k` [T][C][3][3] and OpenCV world-to-camera `w2c`
[T][C][4][4], image paths `fn` [T][C] under `ims/`, and optional binary foreground masks
`seg/<cam>/<frame>.png` (label 1)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.data.loaders import get
from sync4d.data.scene import (
    Camera,
    DatasetError,
    Frame,
    Scene,
    as_number,
    as_number_array,
    as_string,
    check_pose,
    read_json,
)


def _load_meta(root: Path, name: str, resolution_scale: float) -> list[Frame]:
    path = root / name
    meta = read_json(path)
    for key in ("w", "h", "k", "w2c", "fn"):
        if key not in meta:
            raise DatasetError(path, f"missing '{key}'")
    w = int(as_number(meta["w"], path, "'w'", integer=True, positive=True))
    h = int(as_number(meta["h"], path, "'h'", integer=True, positive=True))
    fns = meta["fn"]
    if not isinstance(fns, list) or not all(isinstance(row, list) for row in fns):
        raise DatasetError(path, "'fn' must be a [T][cams] list of image paths")
    t_count = len(fns)
    if t_count == 0:
        raise DatasetError(path, "'fn' lists no timesteps")
    ks = as_number_array(meta["k"], path, "'k'")
    w2cs = as_number_array(meta["w2c"], path, "'w2c'")
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
            fn = as_string(fn, path, f"'fn'[{t}][{c}]")
            img = root / "ims" / fn
            if not img.exists():
                raise DatasetError(img, f"image file is missing (timestep {t} of {name})")
            check_pose(w2cs[t, c], path, f"timestep {t} camera {c} ({fn}) 'w2c'")
            k = ks[t, c]
            if k[0, 0] <= 0 or k[1, 1] <= 0:
                raise DatasetError(
                    path,
                    f"timestep {t} camera {c} ({fn}) 'k' has focal lengths {k[0, 0]:g}, "
                    f"{k[1, 1]:g}; they must be positive",
                )
            cam = Camera(w2cs[t, c], k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h)
            if resolution_scale != 1.0:
                cam = cam.scaled(resolution_scale)
            seg = root / "seg" / Path(fn).with_suffix(".png")
            label = f"cam{Path(fn).parent.name}_{Path(fn).name}"
            frames.append(Frame(img, cam, time, seg if seg.exists() else None, (w, h), label))
    return frames


def load_panoptic(root: str | Path, resolution_scale: float = 1.0) -> Scene:
    """Load a Dynamic-3DGS Panoptic sequence directory (e.g. `basketball/`)."""
    return get("panoptic").load(root, resolution_scale)


def read(root: Path, resolution_scale: float, test_split: str) -> Scene:
    """The scene in folder `root`, whose arguments the registry checked (`prepare`)."""
    train = _load_meta(root, "train_meta.json", resolution_scale)
    test = _load_meta(root, "test_meta.json", resolution_scale)
    labels = {0: "background", 1: "foreground"} if any(f.mask_path for f in train) else None
    return Scene(root.name, train, test, labels)
