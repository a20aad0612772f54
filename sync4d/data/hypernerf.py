"""HyperNeRF / Nerfies captures: `dataset.json` (`ids`, `train_ids`, `val_ids`),
`metadata.json` (per id `time_id`, or `warp_id`), `camera/<id>.json` (Nerfies cameras:
`orientation` = world-to-camera rotation in OpenCV axes, `position` = camera centre,
`focal_length`, `pixel_aspect_ratio`, `principal_point`, `image_size`) and images in
`rgb/{1x,2x,4x,...}/<id>.png`. Lens distortion is not modelled; a pinhole is assumed."""

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


def _camera(path: Path) -> Camera:
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
    vm = np.eye(4)
    vm[:3, :3] = r
    vm[:3, 3] = -r @ pos
    return Camera(vm, f, f * aspect, float(pp[0]), float(pp[1]), w, h)


def load_hypernerf(root: str | Path, resolution_scale: float = 1.0) -> Scene:
    """Load a HyperNeRF capture; `resolution_scale` 1, 0.5, 0.25 ... reads `rgb/1x`, `rgb/2x`,
    `rgb/4x` ... when present (else resizes from `rgb/1x`)."""
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
    factor = round(1.0 / resolution_scale)
    folder = root / "rgb" / f"{factor}x"
    stored_scale = 1.0 / factor
    if abs(stored_scale - resolution_scale) > 1e-9 or not folder.is_dir():
        folder, stored_scale = root / "rgb" / "1x", 1.0
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
            cam = _camera(root / "camera" / f"{i}.json")
            native = cam.scaled(stored_scale)
            img = folder / f"{i}.png"
            if not img.exists():
                raise DatasetError(img, f"image file is missing (id {i!r})")
            cam = cam.scaled(resolution_scale)
            out.append(Frame(img, cam, times[i] / t_max, None, (native.width, native.height)))
        return out

    return Scene(root.name, frames(ds["train_ids"]), frames(ds["val_ids"]))
