"""D-NeRF / Blender synthetic scenes: `transforms_{train,val,test}.json` with `camera_angle_x`
and per-frame `file_path`, `time` and an OpenGL camera-to-world `transform_matrix`; optional
indexed instance masks in `masks/{split}/<name>.png` with `masks/labels.json`."""

from __future__ import annotations

import math
from pathlib import Path

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
    image_size,
    opengl_c2w_to_opencv_w2c,
    read_json,
    read_labels,
)


def _resolve_image(root: Path, file_path: str, json_path: Path, index: int) -> Path:
    p = (root / file_path).resolve()
    if p.suffix == "":
        p = p.with_suffix(".png")
    if not p.exists():
        raise DatasetError(p, f"image file is missing (frame {index} of {json_path.name})")
    return p


def load_split(
    root: Path, split: str, resolution_scale: float = 1.0, with_masks: bool = True
) -> list[Frame]:
    """Frames of `transforms_{split}.json` under `root`, cameras converted to OpenCV
    world-to-camera and scaled by `resolution_scale`."""
    path = root / f"transforms_{split}.json"
    data = read_json(path)
    if "camera_angle_x" not in data:
        raise DatasetError(path, "missing 'camera_angle_x'")
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(path, "missing or empty 'frames' list")
    angle = as_number(data["camera_angle_x"], path, "'camera_angle_x'")
    if not (0.0 < angle < math.pi):
        raise DatasetError(path, f"'camera_angle_x' must be in (0, pi), got {angle}")
    out: list[Frame] = []
    native: tuple[int, int] | None = None
    mask_dir = root / "masks" / split
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict) or "file_path" not in fr:
            raise DatasetError(path, f"frame {i} has no 'file_path'")
        file_path = as_string(fr["file_path"], path, f"frame {i} 'file_path'")
        label = f"frame {i} ({Path(file_path).stem})"
        if "time" not in fr:
            raise DatasetError(path, f"{label} has no 'time'")
        t = as_number(fr["time"], path, f"{label} 'time'")
        if not (0.0 <= t <= 1.0):
            raise DatasetError(path, f"{label} has time {t}, expected a value in [0, 1]")
        if "transform_matrix" not in fr:
            raise DatasetError(path, f"{label} has no 'transform_matrix'")
        m = as_number_array(fr["transform_matrix"], path, f"{label} 'transform_matrix'")
        if m.shape != (4, 4):
            raise DatasetError(
                path, f"{label} 'transform_matrix' must be 4x4, got shape {list(m.shape)}"
            )
        check_pose(m, path, f"{label} 'transform_matrix'")
        img = _resolve_image(root, file_path, path, i)
        if native is None:
            native = image_size(img)
        w, h = native
        fx = 0.5 * w / math.tan(0.5 * angle)
        cam = Camera(opengl_c2w_to_opencv_w2c(m), fx, fx, 0.5 * w, 0.5 * h, w, h)
        if resolution_scale != 1.0:
            cam = cam.scaled(resolution_scale)
        mask = None
        if with_masks and mask_dir.is_dir():
            mask = mask_dir / (img.stem + ".png")
            if not mask.exists():
                raise DatasetError(mask, f"mask for {img.name} is missing ({mask_dir} has masks)")
        out.append(Frame(img, cam, t, mask, native))
    return out


def load_blender(
    root: str | Path, resolution_scale: float = 1.0, test_split: str = "test"
) -> Scene:
    """Load a D-NeRF / Blender scene directory (`test_split` = "test" or "val")."""
    return get("blender").load(root, resolution_scale, test_split)


def read(root: Path, resolution_scale: float, test_split: str) -> Scene:
    """The scene in folder `root`, whose arguments the registry checked (`prepare`)."""
    train = load_split(root, "train", resolution_scale)
    test = load_split(root, test_split, resolution_scale)
    labels = None
    labels_path = root / "masks" / "labels.json"
    if labels_path.exists():
        labels = read_labels(labels_path)
    return Scene(root.name, train, test, labels)
