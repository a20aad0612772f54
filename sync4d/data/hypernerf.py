"""HyperNeRF / Nerfies captures, in the layout 4D LangSplat's HyperNeRF annotations assume:
`dataset.json` (`ids`, `train_ids`, `val_ids`), `metadata.json` (per id `time_id`, or
`warp_id`; `camera_id` and `appearance_id` are not used), `camera/<id>.json` (Nerfies cameras:
`orientation` = world-to-camera rotation in OpenCV axes, `position` = camera centre,
`focal_length`, `pixel_aspect_ratio`, `principal_point`, `image_size` of the 1x images), images
in `rgb/{1x,2x,4x,...}/<id>.png`, and optionally:

- `scene.json` (`center` [3], `scale`, `near`, `far`): camera centres and points are
  normalised as HyperNeRF's own loader does (hypernerf/datasets/nerfies.py `load_camera`,
  `load_points`): x -> (x - center) * scale; `near` and `far` (already in those units) are
  recorded in `Scene.extra`;
- `points.npy` [N, 3] float: the starting points of the Gaussians, normalised the same way;
- `masks/<id>.png` (indexed instance labels, 0 = background) with names in
  `masks/labels.json`: every train and val image then needs one.

Lens distortion is not modelled; a pinhole is assumed."""

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
    read_labels,
)


def _normalisation(root: Path) -> tuple[np.ndarray, float, dict]:
    """(center [3], scale, extra) from `scene.json`; the identity without one."""
    path = root / "scene.json"
    if not path.exists():
        return np.zeros(3), 1.0, {}
    doc = read_json(path)
    if not isinstance(doc, dict) or "center" not in doc or "scale" not in doc:
        raise DatasetError(path, "needs 'center' (3 numbers) and 'scale' (HyperNeRF's scene.json)")
    center = as_number_array(doc["center"], path, "'center'")
    if center.shape != (3,) or not np.isfinite(center).all():
        raise DatasetError(path, f"'center' must be 3 finite numbers, got {doc['center']!r}")
    scale = as_number(doc["scale"], path, "'scale'", positive=True)
    extra = {"scene_center": center.tolist(), "scene_scale": scale}
    for key in ("near", "far"):
        if key in doc:
            extra[key] = as_number(doc[key], path, f"'{key}'", positive=True)
    return center, scale, extra


def _points(root: Path, center: np.ndarray, scale: float) -> np.ndarray | None:
    """`points.npy` [N, 3], normalised by `scene.json`; None without the file."""
    path = root / "points.npy"
    if not path.exists():
        return None
    try:
        pts = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise DatasetError(path, f"not a readable .npy array ({e})") from None
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.issubdtype(pts.dtype, np.number):
        raise DatasetError(path, f"expected an [N, 3] array of numbers, got shape "
                           f"{list(pts.shape)} of {pts.dtype}")  # fmt: skip
    pts = pts.astype(np.float64)
    if not len(pts) or not np.isfinite(pts).all():
        raise DatasetError(path, "no points, or NaN or inf among them")
    return (pts - center) * scale


def _rgb_folder(root: Path, resolution_scale: float) -> tuple[Path, float]:
    """The image folder and its scale: `rgb/<1/scale>x` when present, else `rgb/1x`, else the
    finest `rgb/<k>x` there is (4D LangSplat's data has `rgb/2x` only)."""
    factor = round(1.0 / resolution_scale)
    folder = root / "rgb" / f"{factor}x"
    if abs(1.0 / factor - resolution_scale) <= 1e-9 and folder.is_dir():
        return folder, 1.0 / factor
    if (root / "rgb" / "1x").is_dir():
        return root / "rgb" / "1x", 1.0
    found = sorted(int(d.name[:-1]) for d in (root / "rgb").glob("*x")
                   if d.is_dir() and d.name[:-1].isdigit() and int(d.name[:-1]) > 0)  # fmt: skip
    if not found:
        raise DatasetError(root / "rgb", "no image folder rgb/1x, rgb/2x, ... ")
    return root / "rgb" / f"{found[0]}x", 1.0 / found[0]


def _camera(path: Path, center: np.ndarray | None = None, scale: float = 1.0) -> Camera:
    c = read_json(path)
    for key in ("orientation", "position", "focal_length", "principal_point", "image_size"):
        if key not in c:
            raise DatasetError(path, f"missing camera field '{key}'")
    r = as_number_array(c["orientation"], path, "'orientation'")
    pos = as_number_array(c["position"], path, "'position'")
    pp = as_number_array(c["principal_point"], path, "'principal_point'")
    size = as_number_array(c["image_size"], path, "'image_size'")
    if r.shape != (3, 3) or pos.shape != (3,):
        raise DatasetError(
            path,
            f"'orientation' must be 3x3 and 'position' 3 values, got "
            f"{list(r.shape)} and {list(pos.shape)}",
        )
    if pp.shape != (2,) or size.shape != (2,):
        raise DatasetError(
            path,
            f"'principal_point' and 'image_size' must be 2 values each, got "
            f"{list(pp.shape)} and {list(size.shape)}",
        )
    if not (np.isfinite(pos).all() and np.isfinite(pp).all()):
        raise DatasetError(path, "camera contains NaN or inf")
    check_pose(r, path, "'orientation'")
    f = as_number(c["focal_length"], path, "'focal_length'", positive=True)
    aspect = as_number(
        c.get("pixel_aspect_ratio", 1.0), path, "'pixel_aspect_ratio'", positive=True
    )
    w, h = (
        int(as_number(v, path, f"'image_size'[{j}]", integer=True, positive=True))
        for j, v in enumerate(c["image_size"])
    )
    if center is not None:
        pos = (pos - center) * scale
    vm = np.eye(4)
    vm[:3, :3] = r
    vm[:3, 3] = -r @ pos
    return Camera(vm, f, f * aspect, float(pp[0]), float(pp[1]), w, h)


def load_hypernerf(root: str | Path, resolution_scale: float = 1.0) -> Scene:
    """Load a HyperNeRF capture; `resolution_scale` 1, 0.5, 0.25 ... reads `rgb/1x`, `rgb/2x`,
    `rgb/4x` ... when present (else resizes from `rgb/1x`, or reads the finest folder there is
    at its own size)."""
    return get("hypernerf").load(root, resolution_scale)


def read(root: Path, resolution_scale: float, test_split: str) -> Scene:
    """The scene in folder `root`, whose arguments the registry checked (`prepare`)."""
    ds_path, meta_path = root / "dataset.json", root / "metadata.json"
    ds, meta = read_json(ds_path), read_json(meta_path)
    for key in ("train_ids", "val_ids"):
        if not isinstance(ds.get(key), list):
            raise DatasetError(ds_path, f"missing '{key}' list")
        for j, i in enumerate(ds[key]):
            as_string(i, ds_path, f"'{key}'[{j}]")
    folder, stored_scale = _rgb_folder(root, resolution_scale)
    # a coarser folder than asked for: read it at its own size rather than upsampling it
    scale_to = min(resolution_scale, stored_scale)
    center, scale, extra = _normalisation(root)
    mask_dir = root / "masks"
    has_masks = mask_dir.is_dir()
    times: dict[str, float] = {}
    for i in ds["train_ids"] + ds["val_ids"]:
        entry = meta.get(i)
        if not isinstance(entry, dict) or ("time_id" not in entry and "warp_id" not in entry):
            raise DatasetError(meta_path, f"id {i!r} has no 'time_id' (or 'warp_id')")
        key = "time_id" if "time_id" in entry else "warp_id"
        times[i] = as_number(entry[key], meta_path, f"id {i!r} '{key}'")
        if times[i] < 0:
            raise DatasetError(meta_path, f"id {i!r} '{key}' must be >= 0, got {times[i]:g}")
    t_max = max(times.values()) or 1.0

    def frames(ids: list[str]) -> list[Frame]:
        out = []
        for i in ids:
            cam = _camera(root / "camera" / f"{i}.json", center, scale)
            native = cam.scaled(stored_scale)
            img = folder / f"{i}.png"
            if not img.exists():
                raise DatasetError(img, f"image file is missing (id {i!r})")
            mask = None
            if has_masks:
                mask = mask_dir / f"{i}.png"
                if not mask.exists():
                    raise DatasetError(mask, f"mask of id {i!r} is missing ({mask_dir} has "
                                       "masks)")  # fmt: skip
            cam = cam.scaled(scale_to)
            out.append(Frame(img, cam, times[i] / t_max, mask, (native.width, native.height)))
        return out

    labels_path = mask_dir / "labels.json"
    labels = read_labels(labels_path) if labels_path.exists() else None
    return Scene(root.name, frames(ds["train_ids"]), frames(ds["val_ids"]), labels,
                 _points(root, center, scale), None, extra)  # fmt: skip
