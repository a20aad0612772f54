"""COLMAP reconstructions of dynamic scenes, read with pycolmap: images in `images/`, the sparse
model (cameras, images, points3D as `.bin` or `.txt`) in `sparse/0/` or `sparse/`, optional
indexed instance masks `masks/<image stem>.png` with `masks/labels.json`.

Each image's time comes from `times.json` (image name -> time; normalised to [0, 1] by min/max
unless already in [0, 1]); without it the images sorted by name are one monocular video with
times evenly spaced over [0, 1]. The test split is `test_images.txt` (one image name per line)
when present, else every 8th image sorted by name (the LLFF / mip-NeRF 360 convention). Only
undistorted pinhole cameras are supported: run `colmap image_undistorter` first otherwise.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sync4d.data.loaders import get
from sync4d.data.scene import (
    Camera,
    DatasetError,
    Frame,
    Scene,
    as_number,
    check_pose,
    read_json,
    read_labels,
)

#: COLMAP camera models read as pinholes; the radial / OpenCV ones only with zero distortion.
PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
ZERO_DISTORTION_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV")
#: Every `test_every`-th image (sorted by name) is held out when there is no test_images.txt.
TEST_EVERY = 8


def find_sparse_model(root: Path) -> Path:
    """The sparse model directory of a COLMAP dataset: `sparse/0/` if present, else `sparse/`."""
    sparse = root / "sparse"
    for cand in (sparse / "0", sparse):
        if any((cand / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
            return cand
    raise DatasetError(
        sparse,
        "COLMAP sparse model is missing: expected cameras, images and points3D (.bin or .txt) "
        "in sparse/0/ or sparse/",
    )


def _read_model(sparse: Path):
    try:
        import pycolmap
    except ImportError:
        raise DatasetError(
            sparse, "reading COLMAP models needs pycolmap: pip install pycolmap"
        ) from None
    try:
        return pycolmap.Reconstruction(str(sparse))
    except Exception as e:  # pycolmap raises ValueError / RuntimeError with COLMAP's check text
        raise DatasetError(sparse, f"pycolmap cannot read the sparse model ({e})") from None


def _intrinsics(sparse: Path, cam) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) of a pycolmap camera, refusing lens distortion."""
    model = str(cam.model_name)
    params = np.asarray(cam.params, dtype=np.float64)
    if model not in PINHOLE_MODELS + ZERO_DISTORTION_MODELS:
        raise DatasetError(
            sparse,
            f"camera {cam.camera_id} has model {model}, which sync4d does not support; "
            "undistort the images with `colmap image_undistorter` (it writes PINHOLE cameras)",
        )
    extra = params[list(cam.extra_params_idxs())]
    if np.any(extra != 0.0):
        raise DatasetError(
            sparse,
            f"camera {cam.camera_id} ({model}) has lens distortion {extra.tolist()}; sync4d "
            "needs undistorted images: run `colmap image_undistorter` and load its output",
        )
    out = (
        float(cam.focal_length_x),
        float(cam.focal_length_y),
        float(cam.principal_point_x),
        float(cam.principal_point_y),
    )
    if not all(math.isfinite(v) for v in out) or out[0] <= 0 or out[1] <= 0:
        raise DatasetError(sparse, f"camera {cam.camera_id} has invalid intrinsics {list(out)}")
    return out


def _viewmat(sparse: Path, image) -> np.ndarray:
    """[4, 4] world-to-camera of a pycolmap image (COLMAP poses are OpenCV cam_from_world).
    The rotation is built from the normalised quaternion: pycolmap does not normalise what it
    reads, and turns an all-zero quaternion into the identity without complaint."""
    pose = image.cam_from_world
    if callable(pose):  # a method in pycolmap >= 3.12 / 4, a property before
        pose = pose()
    what = f"image '{image.name}' pose"
    q = np.asarray(pose.rotation.quat, dtype=np.float64)  # x, y, z, w
    t = np.asarray(pose.translation, dtype=np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise DatasetError(sparse, f"{what} is not finite")
    norm = float(np.linalg.norm(q))
    if norm < 1e-6:
        raise DatasetError(
            sparse,
            f"{what} has a zero rotation quaternion (|q| = {norm:.3g}); "
            "poses must be unit quaternions plus translations",
        )
    x, y, z, w = q / norm
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = t
    check_pose(m, sparse, what)
    return m


def _read_times(root: Path, names: list[str]) -> list[float]:
    """Per-image times in [0, 1]: from `times.json`, else evenly spaced over sorted names."""
    path = root / "times.json"
    if not path.exists():
        n = len(names)
        return [i / max(1, n - 1) for i in range(n)]
    data = read_json(path)
    raw: list[float] = []
    for name in names:
        if name not in data:
            raise DatasetError(path, f"no time for image '{name}'")
        raw.append(as_number(data[name], path, f"the time of '{name}'"))
    lo, hi = min(raw), max(raw)
    if lo >= 0.0 and hi <= 1.0:
        return raw
    return [(t - lo) / (hi - lo) for t in raw]  # hi > lo: not all within [0, 1]


def _read_test_names(root: Path, names: list[str]) -> set[str]:
    """Held-out image names: `test_images.txt` if present, else every 8th sorted name."""
    path = root / "test_images.txt"
    if not path.exists():
        return {n for i, n in enumerate(names) if i % TEST_EVERY == 0}
    known = set(names)
    out: set[str] = set()
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        name = line.strip()
        if not name or name.startswith("#"):
            continue
        if name not in known:
            raise DatasetError(
                path, f"line {lineno} names '{name}', which is not a registered image"
            )
        out.add(name)
    return out


def load_colmap(root: str | Path, resolution_scale: float = 1.0) -> Scene:
    """Load a COLMAP dataset directory (`images/`, `sparse/[0/]`, optional `masks/`,
    `times.json`, `test_images.txt`) with cameras scaled by `resolution_scale` in (0, 1]."""
    return get("colmap").load(root, resolution_scale)


def read(root: Path, resolution_scale: float, test_split: str) -> Scene:
    """The scene in folder `root`, whose arguments the registry checked (`prepare`)."""
    image_dir = root / "images"
    if not image_dir.is_dir():
        raise DatasetError(image_dir, "image folder is missing")
    sparse = find_sparse_model(root)
    rec = _read_model(sparse)
    images = sorted((rec.images[i] for i in rec.reg_image_ids()), key=lambda im: im.name)
    if not images:
        raise DatasetError(sparse, "the sparse model has no registered images")
    names = [im.name for im in images]
    times = _read_times(root, names)
    test_names = _read_test_names(root, names)
    mask_dir = root / "masks"
    has_masks = mask_dir.is_dir()
    train: list[Frame] = []
    test: list[Frame] = []
    for im, time in zip(images, times, strict=True):
        img = image_dir / im.name
        if not img.exists():
            raise DatasetError(img, f"image file is missing (listed in {sparse})")
        col = rec.cameras[im.camera_id]
        fx, fy, cx, cy = _intrinsics(sparse, col)
        w, h = int(col.width), int(col.height)
        if w <= 0 or h <= 0:
            raise DatasetError(sparse, f"camera {col.camera_id} has image size {w}x{h}")
        viewmat = _viewmat(sparse, im)
        cam = Camera(viewmat, fx, fy, cx, cy, w, h)
        if resolution_scale != 1.0:
            cam = cam.scaled(resolution_scale)
        mask = None
        if has_masks:
            mask = mask_dir / Path(im.name).with_suffix(".png")
            if not mask.exists():
                raise DatasetError(mask, f"mask for {im.name} is missing ({mask_dir} has masks)")
        frame = Frame(img, cam, time, mask, (w, h))
        (test if im.name in test_names else train).append(frame)
    if not train:
        raise DatasetError(root, "the split leaves no training frames")
    labels_path = mask_dir / "labels.json"
    labels = read_labels(labels_path) if labels_path.exists() else None
    points = colors = None
    if rec.num_points3D() > 0:
        pts = [rec.points3D[i] for i in sorted(rec.point3D_ids())]
        points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
        colors = np.array([p.color for p in pts], dtype=np.float32).reshape(-1, 3) / 255.0
    return Scene(root.name, train, test, labels, points, colors)
