"""nerfstudio `transforms.json` with a per-frame `time`: intrinsics (`fl_x`, `fl_y`, `cx`,
`cy`, `w`, `h`) at the top level or per frame, OpenGL camera-to-world `transform_matrix`,
optional per-frame `mask_path`. The split comes from `train_filenames` / `test_filenames` when
present, else every `test_every`-th frame is held out for testing. Lens distortion
coefficients, if any, are not modelled (a pinhole is assumed) and are reported in
`Scene.extra["ignored_distortion"]`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sync4d.data.blender import _image_size, _read_json
from sync4d.data.scene import Camera, DatasetError, Frame, Scene, opengl_c2w_to_opencv_w2c

_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def _intrinsic(path: Path, i: int, frame: dict, top: dict, key: str) -> float:
    v = frame.get(key, top.get(key))
    if v is None:
        raise DatasetError(path, f"frame {i} has no '{key}' (neither per frame nor at the top)")
    v = float(v)
    if not math.isfinite(v):
        raise DatasetError(path, f"frame {i} '{key}' is not finite")
    return v


def load_nerfstudio(root: str | Path, resolution_scale: float = 1.0, test_every: int = 8) -> Scene:
    """Load a nerfstudio-format directory whose `transforms.json` frames carry `time`."""
    root = Path(root)
    path = root / "transforms.json"
    if not root.is_dir():
        raise DatasetError(root, "dataset directory does not exist")
    if not (0.0 < resolution_scale <= 1.0):
        raise DatasetError(root, f"resolution scale must be in (0, 1], got {resolution_scale}")
    data = _read_json(path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(path, "missing or empty 'frames' list")
    times = [fr.get("time") if isinstance(fr, dict) else None for fr in frames]
    missing = [i for i, t in enumerate(times) if t is None]
    if missing:
        raise DatasetError(
            path,
            f"{len(missing)} frames have no 'time' (first: frame {missing[0]}); "
            "sync4d needs a time per frame for dynamic scenes",
        )
    t_lo, t_hi = min(map(float, times)), max(map(float, times))
    out: list[Frame] = []
    for i, fr in enumerate(frames):
        if "file_path" not in fr:
            raise DatasetError(path, f"frame {i} has no 'file_path'")
        img = root / fr["file_path"]
        if not img.exists():
            raise DatasetError(img, f"image file is missing (frame {i} of {path.name})")
        m = np.asarray(fr.get("transform_matrix"), dtype=np.float64)
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise DatasetError(path, f"frame {i} 'transform_matrix' must be a finite 4x4 (or 3x4)")
        if "w" in fr or "w" in data:
            w = int(_intrinsic(path, i, fr, data, "w"))
            h = int(_intrinsic(path, i, fr, data, "h"))
        else:
            w, h = _image_size(img)
        cam = Camera(
            opengl_c2w_to_opencv_w2c(m),
            _intrinsic(path, i, fr, data, "fl_x"),
            _intrinsic(path, i, fr, data, "fl_y"),
            _intrinsic(path, i, fr, data, "cx"),
            _intrinsic(path, i, fr, data, "cy"),
            w,
            h,
        )
        if resolution_scale != 1.0:
            cam = cam.scaled(resolution_scale)
        # Times are normalised to [0, 1] over the sequence.
        t = (float(fr["time"]) - t_lo) / (t_hi - t_lo) if t_hi > t_lo else 0.0
        mask = root / fr["mask_path"] if fr.get("mask_path") else None
        if mask is not None and not mask.exists():
            raise DatasetError(mask, f"mask file is missing (frame {i} of {path.name})")
        out.append(Frame(img, cam, t, mask, (w, h)))
    names = [Path(fr["file_path"]).as_posix() for fr in frames]
    if "train_filenames" in data or "test_filenames" in data:
        test_names = {Path(n).as_posix() for n in data.get("test_filenames", [])}
        test = [f for f, n in zip(out, names, strict=True) if n in test_names]
        train = [f for f, n in zip(out, names, strict=True) if n not in test_names]
    else:
        if test_every < 2:
            raise DatasetError(path, f"test_every must be >= 2, got {test_every}")
        test = out[::test_every]
        train = [f for i, f in enumerate(out) if i % test_every != 0]
    if not train:
        raise DatasetError(path, "the split leaves no training frames")
    ignored = {k: data[k] for k in _DISTORTION if data.get(k)}
    return Scene(root.name, train, test, extra={"ignored_distortion": ignored})
