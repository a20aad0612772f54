"""Initial points for multi-view captures that ship without a point cloud (e.g. the Panoptic
layout): SIFT features matched across every training camera at one time instant and
triangulated with the dataset's own (fixed) poses through pycolmap.

Rigid structure-from-motion needs a static scene; a synchronised multi-camera rig sees the
scene frozen at each instant, so triangulating one instant is exact even when things move.
Results are cached under `$SYNC4D_CACHE/points/` keyed by the images and cameras used.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
import time as _time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.data.scene import DatasetError, Frame, Scene, cache_dir, image_depth

#: Bumped whenever the triangulation recipe changes, so old cache entries are not reused.
_VERSION = 1


@dataclass(frozen=True)
class TriangulationConfig:
    """SIFT, matching and filtering options of :func:`triangulate_scene`."""

    #: SIFT detector peak threshold (COLMAP's default 0.0067 finds too few keypoints on the
    #: low-texture walls of capture domes).
    peak_threshold: float = 0.0015
    #: Guided matching (re-match under the verified epipolar geometry) for longer tracks.
    guided_matching: bool = True
    #: Points whose mean reprojection error exceeds this many pixels are dropped.
    max_reprojection_error: float = 2.0
    #: Points seen by fewer views than this are dropped.
    min_track_length: int = 2
    #: CPU threads for feature extraction and matching.
    threads: int = 2


@dataclass(frozen=True)
class TriangulatedPoints:
    """A sparse point cloud: `points` [N, 3] float64 world coordinates, `colors` [N, 3]
    float32 RGB in [0, 1], the instant it was taken at and the number of views used."""

    points: np.ndarray
    colors: np.ndarray
    time: float
    views: int
    seconds: float
    cached: bool


def views_at_one_instant(frames: list[Frame]) -> tuple[float, list[Frame]]:
    """The training frames of the instant seen by the most cameras (the earliest on a tie):
    (time, frames). One frame per time (a monocular video) returns a single frame."""
    by_time: dict[float, list[Frame]] = {}
    for f in frames:
        by_time.setdefault(round(float(f.time), 9), []).append(f)
    t = min(by_time, key=lambda k: (-len(by_time[k]), k))
    return t, by_time[t]


def is_multiview(scene: Scene) -> bool:
    """Whether at least two training cameras see the scene at the same instant."""
    return bool(scene.train) and len(views_at_one_instant(scene.train)[1]) >= 2


def _reads_file_as_is(frame: Frame) -> bool:
    """Whether `frame`'s image is its file (a plain `Frame`), not a transform of it (e.g. a
    nerfstudio frame undistorted on load), which must be matched as the loader gives it."""
    return type(frame) is Frame


def _native_intrinsics(frame: Frame) -> tuple[int, int, list[float]]:
    """(width, height, [fx, fy, cx, cy]) of `frame`'s camera at the size its view is matched
    at: the image file's own size, or the camera's for a frame transformed on load."""
    cam = frame.camera
    w, h = frame.native_size or (cam.width, cam.height)
    if not _reads_file_as_is(frame):
        w, h = cam.width, cam.height
    sx, sy = w / cam.width, h / cam.height
    return w, h, [cam.fx * sx, cam.fy * sy, cam.cx * sx, cam.cy * sy]


def _cache_key(frames: list[Frame], cfg: TriangulationConfig) -> str:
    h = hashlib.sha256()
    options = {k: v for k, v in cfg.__dict__.items() if k != "threads"}
    h.update(json.dumps([_VERSION, options], sort_keys=True).encode())
    for f in frames:
        st = f.image_path.stat()
        h.update(str(f.image_path.resolve()).encode())
        h.update(f"{st.st_size}:{st.st_mtime_ns}".encode())
        h.update(np.asarray(f.camera.viewmat, np.float64).tobytes())
        h.update(np.asarray(_native_intrinsics(f)[2], np.float64).tobytes())
    return h.hexdigest()[:24]


def _run_pycolmap(
    frames: list[Frame], work: Path, cfg: TriangulationConfig
) -> tuple[np.ndarray, np.ndarray]:
    import pycolmap
    from PIL import Image

    images = work / "images"
    images.mkdir()
    names = []
    for i, f in enumerate(frames):
        name = f"view{i:04d}.png"
        if not _reads_file_as_is(f):  # e.g. undistorted on load: match what the loader gives
            rgb = (f.load_image() * 255.0).round().clip(0, 255).astype(np.uint8)
            Image.fromarray(rgb).save(images / name)
            names.append(name)
            continue
        try:
            with Image.open(f.image_path) as im:
                if image_depth(im, f.image_path) == 16:  # convert("RGB") would clip at 255
                    im.load()
                    gray = np.asarray(im).astype(np.float64) / 257.0
                    Image.fromarray(gray.round().astype(np.uint8)).convert("RGB").save(
                        images / name
                    )
                else:
                    im.convert("RGB").save(images / name)
        except OSError as e:
            raise DatasetError(f.image_path, f"cannot read image ({e})") from None
        names.append(name)

    db_path = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = cfg.threads
    extract.sift.peak_threshold = cfg.peak_threshold
    pycolmap.extract_features(
        db_path, images, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader, extraction_options=extract, device=pycolmap.Device.cpu,
    )  # fmt: skip

    # Give every database camera the dataset's intrinsics before geometric verification.
    db = pycolmap.Database.open(db_path)
    try:
        ids = {im.name: (im.image_id, im.camera_id) for im in db.read_all_images()}
        for name, f in zip(names, frames, strict=True):
            cam = db.read_camera(ids[name][1])
            cam.params = _native_intrinsics(f)[2]
            db.update_camera(cam)
    finally:
        db.close()

    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = cfg.threads
    match.guided_matching = cfg.guided_matching
    pycolmap.match_exhaustive(db_path, matching_options=match, device=pycolmap.Device.cpu)

    rec = pycolmap.Reconstruction()
    for name, f in zip(names, frames, strict=True):
        image_id, camera_id = ids[name]
        w, h, params = _native_intrinsics(f)
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="PINHOLE", width=w, height=h, params=params, camera_id=camera_id)
        )
        viewmat = np.asarray(f.camera.viewmat, np.float64)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(viewmat[:3, :3]), viewmat[:3, 3])
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=camera_id, image_id=image_id), pose
        )
    out = work / "sparse"
    out.mkdir()
    options = pycolmap.IncrementalPipelineOptions()
    options.fix_existing_frames = True  # the dataset's poses are the truth: refine points only
    options.num_threads = cfg.threads
    rec = pycolmap.triangulate_points(rec, db_path, images, out, options=options)
    pts, cols = [], []
    for p in rec.points3D.values():
        if p.error <= cfg.max_reprojection_error and p.track.length() >= cfg.min_track_length:
            pts.append(p.xyz)
            cols.append(p.color)
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.float32)
    return np.asarray(pts, np.float64), np.asarray(cols, np.float32) / 255.0


def triangulate_scene(
    scene: Scene, config: TriangulationConfig | None = None, use_cache: bool = True
) -> TriangulatedPoints:
    """Triangulate a sparse coloured point cloud from the training views of one instant of a
    multi-view `scene` (see :func:`views_at_one_instant`), with the dataset's poses held fixed.
    Raises DatasetError when fewer than two cameras see one instant."""
    cfg = config or TriangulationConfig()
    t, frames = views_at_one_instant(scene.train)
    if len(frames) < 2:
        where = frames[0].image_path.parent if frames else scene.name
        raise DatasetError(
            where, "triangulation needs at least two training cameras at one instant; "
            "this scene is monocular (use init_from = \"random\")",
        )  # fmt: skip
    t0 = _time.perf_counter()
    key = _cache_key(frames, cfg)
    path = cache_dir() / "points" / f"{key}.npz"
    if use_cache and path.exists():
        with np.load(path) as z:
            pts, cols = z["points"], z["colors"]
        return TriangulatedPoints(pts, cols, t, len(frames), _time.perf_counter() - t0, True)
    work = Path(tempfile.mkdtemp(prefix="sync4d-triangulate-"))
    try:
        _quiet_pycolmap()
        pts, cols = _run_pycolmap(frames, work, cfg)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if use_cache and len(pts):
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, points=pts, colors=cols)
        tmp.replace(path)
    return TriangulatedPoints(pts, cols, t, len(frames), _time.perf_counter() - t0, False)


def _quiet_pycolmap() -> None:
    """Keep COLMAP's per-image INFO log lines off the terminal (warnings still show)."""
    import pycolmap

    try:
        pycolmap.logging.minloglevel = pycolmap.logging.Level.WARNING.value
    except AttributeError:  # older pycolmap: leave logging as it is
        pass
