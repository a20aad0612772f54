"""nerfstudio `transforms.json` with a per-frame `time`: intrinsics (`fl_x`, `fl_y`, `cx`,
`cy`, `w`, `h`) at the top level or per frame, OpenGL camera-to-world `transform_matrix`,
optional per-frame `mask_path`. The split comes from `train_filenames` / `test_filenames` when
present, else every `test_every`-th frame is held out for testing. Lens distortion
coefficients, if any, are not modelled (a pinhole is assumed) and are reported in
`Scene.extra["ignored_distortion"]`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sync4d.data.blender import _image_size, _read_json
from sync4d.data.scene import (
    Camera,
    DatasetError,
    Frame,
    Scene,
    as_number,
    as_number_array,
    as_string,
    check_pose,
    json_kind,
    opengl_c2w_to_opencv_w2c,
)

_DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")


def _intrinsic(path: Path, i: int, frame: dict, top: dict, key: str) -> float:
    v = frame.get(key, top.get(key))
    if v is None:
        raise DatasetError(path, f"frame {i} has no '{key}' (neither per frame nor at the top)")
    where = f"{_label(i, frame)} '{key}'" if key in frame else f"'{key}'"
    return as_number(v, path, where, integer=key in ("w", "h"), positive=key not in ("cx", "cy"))


def _label(i: int, frame: dict) -> str:
    """`frame 3 (f3.png)` for messages; just `frame 3` when the file path is unusable."""
    fp = frame.get("file_path")
    return f"frame {i} ({Path(fp).name})" if isinstance(fp, str) and fp else f"frame {i}"


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
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(path, f"frame {i} must be an object, got {json_kind(fr)}")
    missing = [i for i, fr in enumerate(frames) if fr.get("time") is None]
    if missing:
        raise DatasetError(
            path,
            f"{len(missing)} frames have no 'time' (first: frame {missing[0]}); "
            "sync4d needs a time per frame for dynamic scenes",
        )
    times = [as_number(fr["time"], path, f"{_label(i, fr)} 'time'") for i, fr in enumerate(frames)]
    t_lo, t_hi = min(times), max(times)
    out: list[Frame] = []
    names: list[str] = []
    for i, fr in enumerate(frames):
        if "file_path" not in fr:
            raise DatasetError(path, f"frame {i} has no 'file_path'")
        file_path = as_string(fr["file_path"], path, f"frame {i} 'file_path'")
        names.append(Path(file_path).as_posix())
        label = _label(i, fr)
        img = root / file_path
        if not img.exists():
            raise DatasetError(img, f"image file is missing (frame {i} of {path.name})")
        if "transform_matrix" not in fr:
            raise DatasetError(path, f"{label} has no 'transform_matrix'")
        m = as_number_array(fr["transform_matrix"], path, f"frame {i} 'transform_matrix'")
        if m.shape == (3, 4):
            m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
        if m.shape != (4, 4) or not np.isfinite(m).all():
            raise DatasetError(path, f"frame {i} 'transform_matrix' must be a finite 4x4 (or 3x4)")
        check_pose(m, path, f"{label} 'transform_matrix'")
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
        t = (times[i] - t_lo) / (t_hi - t_lo) if t_hi > t_lo else 0.0
        mask = None
        if fr.get("mask_path") not in (None, ""):
            mask = root / as_string(fr["mask_path"], path, f"{label} 'mask_path'")
        if mask is not None and not mask.exists():
            raise DatasetError(mask, f"mask file is missing (frame {i} of {path.name})")
        out.append(Frame(img, cam, t, mask, (w, h)))
    if "train_filenames" in data or "test_filenames" in data:
        listed = data.get("test_filenames", [])
        if not isinstance(listed, list):
            raise DatasetError(path, f"'test_filenames' must be a list, got {json_kind(listed)}")
        test_names = {
            Path(as_string(n, path, f"'test_filenames'[{j}]")).as_posix()
            for j, n in enumerate(listed)
        }
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
