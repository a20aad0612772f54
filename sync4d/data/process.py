"""`sync4d process`: your own video or photos -> a dataset that `sync4d fit` reads.

Design. A monocular capture has no poses, so they are recovered with COLMAP through pycolmap,
the way nerfstudio's `ns-process-data` does, and written in nerfstudio's layout
(`transforms.json`, `images/`, `sparse_pc.ply`), which `sync4d.data.nerfstudio` reads and
nerfstudio itself can open. Frames are decoded with PyAV (a video: sampled at `--fps` and
evenly thinned to `--max-frames`) or read in file-name order (a folder of photos), bounded to
`--max-size` pixels, and every frame shares one camera (one device, one zoom). SIFT features
are matched sequentially (each frame with its 10 successors and those 2^k frames on) or
exhaustively, and COLMAP's incremental mapper keeps the largest model. Its RANSAC and
reprojection thresholds scale with the image size (COLMAP's 4-pixel defaults suit images of
~1600 pixels; on the 256-pixel test video they let points on the moving objects into the
model: median camera rotation error 1.2 degrees, max 1.4, against 0.2 and 0.5 at 1 pixel).
Features and matches are computed a run of frames (pairs) per pycolmap call, so that the
progress bars move; nothing reads COLMAP's database while pycolmap writes it (Python's own
SQLite polling it for progress crashed pycolmap with SIGBUS). Each registered frame is
undistorted by pycolmap onto a PINHOLE camera, so the dataset's images and intrinsics are
pinhole; frames COLMAP did not register are left out and named. The world is then moved so
that the points' median is the origin, the cameras' mean up direction is +z, and the cameras'
median distance to the origin is 4 (the embedded scene's and D-NeRF's camera radius), because
D_theta's offsets and the initial Gaussians' sizes are in world units. Frame times are the
video's timestamps (the file-name order for photos) normalised to [0, 1]. A dynamic scene
breaks COLMAP's static-world assumption; texture on the static background, overlap and a slow
camera are what make it work (docs/datasets.md, "Your own capture").
"""

from __future__ import annotations

import contextlib
import json
import math
import shutil
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from sync4d.data.ply import write_ply_points
from sync4d.data.scene import DatasetError
from sync4d.progress import Progress

__all__ = [
    "CAMERA_MODELS",
    "IMAGE_SUFFIXES",
    "MATCHERS",
    "ProcessOptions",
    "ProcessResult",
    "process_capture",
    "sample_indices",
]

#: Photo file types read from an image folder (case-insensitive).
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
#: COLMAP camera models `process` offers for the shared camera.
CAMERA_MODELS = ("SIMPLE_RADIAL", "OPENCV", "PINHOLE")
MATCHERS = ("sequential", "exhaustive")
#: What `process` writes into its output folder (and what --force replaces).
OUTPUTS = ("transforms.json", "images", "sparse_pc.ply", "colmap")
#: Camera distance to the scene centre after normalisation (world units).
CAMERA_DISTANCE = 4.0
#: Frames each frame is matched with in sequential matching (COLMAP's default overlap).
SEQUENTIAL_OVERLAP = 10
MIN_FRAMES = 3

T = TypeVar("T")


@dataclass(frozen=True)
class ProcessOptions:
    """How `process_capture` samples frames and runs COLMAP.

    `fps`: frames per second of video time to keep (None: every frame); `max_frames`: at most
    this many, evenly spaced; `max_size`: bound on the longest image side (pixels);
    `camera_model`: the COLMAP model of the one shared camera; `matcher`: sequential (video)
    or exhaustive; `min_registered`: the fraction of frames COLMAP must register; `threads`:
    COLMAP's threads (None: all cores); `verbose`: keep COLMAP's own log."""

    fps: float | None = None
    max_frames: int = 150
    max_size: int = 960
    camera_model: str = "SIMPLE_RADIAL"
    matcher: str = "sequential"
    min_registered: float = 0.5
    threads: int | None = None
    verbose: bool = False


@dataclass
class ProcessResult:
    """What `process_capture` did: the dataset folder `out`, the `frames` sampled from the
    input (of `source_frames` in it), the `registered` and `dropped` frame names, the pinhole
    `camera` written (w, h, fl_x, fl_y, cx, cy), COLMAP's estimate `colmap_camera` (model and
    parameters, before undistortion), the number of sparse `points`, and `seconds` per
    stage."""

    out: Path
    source_frames: int
    frames: list[str]
    registered: list[str]
    dropped: list[str]
    camera: dict[str, float]
    colmap_camera: dict[str, Any]
    points: int
    seconds: dict[str, float] = field(default_factory=dict)


def sample_indices(times: np.ndarray, fps: float | None, max_frames: int) -> np.ndarray:
    """Indices into frames with presentation `times` [N] (seconds, increasing) to keep: the
    frame nearest each tick of a 1/`fps` grid from the first frame (all frames when `fps` is
    None), then at most `max_frames` of those, evenly spaced (first and last kept)."""
    n = len(times)
    idx = np.arange(n)
    if fps is not None and n > 1:
        grid = np.arange(times[0], times[-1] + 1e-9, 1.0 / fps)
        right = np.clip(np.searchsorted(times, grid), 1, n - 1)
        left = right - 1
        nearest = np.where(np.abs(times[left] - grid) <= np.abs(times[right] - grid), left, right)
        idx = np.unique(nearest)
    if len(idx) > max_frames:
        picks = np.unique(np.round(np.linspace(0, len(idx) - 1, max_frames)).astype(int))
        idx = idx[picks]
    return idx


def _fit_size(image, max_size: int):
    """The PIL `image` with its longest side bounded by `max_size` (Lanczos)."""
    from PIL import Image

    w, h = image.size
    if max(w, h) <= max_size:
        return image
    s = max_size / max(w, h)
    return image.resize((max(1, round(w * s)), max(1, round(h * s))), Image.Resampling.LANCZOS)


def _video_times(path: Path) -> tuple[np.ndarray, float]:
    """Presentation times [N] (seconds, sorted) of every packet of the first video stream of
    `path`, from demuxing alone (no decode), and the stream's frame rate."""
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError) as e:
        raise DatasetError(
            path,
            f"cannot open as a video ({e.__class__.__name__}: {getattr(e, 'strerror', '') or e}); "
            "give a video file FFmpeg reads (mp4, mov, mkv, ...) or a folder of photos",
        ) from None
    with container:
        if not container.streams.video:
            raise DatasetError(path, "has no video stream; give a video file or a photo folder")
        stream = container.streams.video[0]
        rate = float(stream.average_rate or stream.guessed_rate or 30)
        pts: list[int | None] = []
        try:
            for packet in container.demux(stream):
                if packet.size:
                    pts.append(packet.pts)
        except av.FFmpegError:
            pass  # a damaged tail: decode what came before it
        base = float(stream.time_base) if stream.time_base else 1.0 / rate
    if pts and all(p is not None for p in pts):
        times = np.sort(np.asarray(pts, dtype=np.float64)) * base
    else:  # e.g. a raw H.264 stream without timestamps
        times = np.arange(len(pts)) / rate
    return times, rate


def _extract_video(
    path: Path, frames_dir: Path, opts: ProcessOptions
) -> tuple[list[str], list[float], int]:
    """Decode the sampled frames of video `path` into `frames_dir` as PNGs named
    `frame_NNNNN.png` (N: the frame's number in the video, from 1); (names, times in seconds,
    frames in the video)."""
    import av
    from PIL import Image

    times, rate = _video_times(path)
    if len(times) == 0:
        raise DatasetError(path, "has no video frames; give a video with frames, or photos")
    keep = set(sample_indices(times, opts.fps, opts.max_frames).tolist())
    names: list[str] = []
    stamps: list[float] = []
    bar = Progress(len(keep), desc="frames", log_every=max(1, len(keep) // 4))
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        i, failure = -1, ""
        try:
            for i, frame in enumerate(container.decode(stream)):
                if i not in keep:
                    continue
                rgb = frame.to_ndarray(format="rgb24")
                turns = int(round((getattr(frame, "rotation", 0) or 0) / 90.0)) % 4
                image = _fit_size(Image.fromarray(np.rot90(rgb, turns).copy()), opts.max_size)
                name = f"frame_{i + 1:05d}.png"
                image.save(frames_dir / name)
                names.append(name)
                stamps.append(float(frame.time) if frame.time is not None else i / rate)
                bar.update(len(names))
        except av.FFmpegError as e:
            failure = f"{e.__class__.__name__}: {getattr(e, 'strerror', '') or e}"
            if names:
                bar.message(f"process: {path}: decoding stopped after frame {i + 1} "
                            f"({failure}); using the {len(names)} frames before it")  # fmt: skip
    bar.close()
    if not names:
        raise DatasetError(
            path,
            f"no video frame could be decoded{f' ({failure})' if failure else ''}; re-encode it "
            "(e.g. ffmpeg -i VIDEO -c:v libx264 OUT.mp4) or give a folder of photos",
        )
    return names, stamps, len(times)


def _read_images(folder: Path, frames_dir: Path, opts: ProcessOptions) -> tuple[list[str], int]:
    """Copy the sampled photos of `folder` (sorted by name, EXIF orientation applied) into
    `frames_dir` as PNGs named by their stems; (names, photos in the folder)."""
    from PIL import Image, ImageOps, UnidentifiedImageError

    files = sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if not files:
        raise DatasetError(
            folder, f"has no photos ({', '.join(IMAGE_SUFFIXES)}); give a video or a photo folder"
        )
    stems = [p.stem for p in files]
    twice = sorted({s for s in stems if stems.count(s) > 1})
    if twice:
        raise DatasetError(
            folder, f"photos share a name up to the suffix ({twice[0]}.*); rename them"
        )
    picked = [
        files[i] for i in sample_indices(np.arange(len(files), dtype=float), None, opts.max_frames)
    ]
    names: list[str] = []
    size: tuple[int, int] | None = None
    bar = Progress(len(picked), desc="frames", log_every=max(1, len(picked) // 4))
    for p in picked:
        try:
            with Image.open(p) as im:
                image = ImageOps.exif_transpose(im).convert("RGB")
        except (UnidentifiedImageError, OSError) as e:
            raise DatasetError(p, f"cannot read the photo ({e}); remove it or convert it") from None
        if size is not None and image.size != size:
            raise DatasetError(
                p,
                f"is {image.size[0]}x{image.size[1]} but {picked[0].name} is {size[0]}x{size[1]}; "
                "sync4d process gives all photos one camera, so they must share one size",
            )
        size = image.size
        name = f"{p.stem}.png"
        _fit_size(image, opts.max_size).save(frames_dir / name)
        names.append(name)
        bar.update(len(names))
    bar.close()
    return names, len(files)


def _chunks(items: list[T], count: int, least: int) -> list[list[T]]:
    """`items` in at most `count` consecutive runs of (nearly) equal length, each of at least
    `least` items but the last (each pycolmap call costs a set-up: measured ~0.3 s)."""
    size = max(least, math.ceil(len(items) / max(1, count)))
    return [items[k : k + size] for k in range(0, len(items), size)]


def sequential_pairs(names: list[str], overlap: int = SEQUENTIAL_OVERLAP) -> list[tuple[str, str]]:
    """The image pairs COLMAP's sequential matcher (quadratic overlap, no loop detection)
    matches among frames `names` in time order: each frame with its `overlap` successors and
    the frames 2^k on, for k < `overlap`."""
    pairs: dict[tuple[int, int], None] = {}
    for i in range(len(names)):
        for k in range(overlap):
            for j in (i + k + 1, i + (1 << k)):
                if j < len(names):
                    pairs[(i, j)] = None
    return [(names[i], names[j]) for i, j in pairs]


def exhaustive_pairs(names: list[str], block: int = 25) -> list[tuple[str, str]]:
    """Every pair of frames `names`, block by block (`block` frames against `block` frames,
    as COLMAP's exhaustive matcher goes, so that a run of pairs reads few images)."""
    n = len(names)
    out = []
    for a in range(0, n, block):
        for b in range(a, n, block):
            for i in range(a, min(a + block, n)):
                for j in range(max(b, i + 1), min(b + block, n)):
                    out.append((names[i], names[j]))
    return out


def _features(db: Path, frames_dir: Path, names: list[str], opts: ProcessOptions) -> None:
    """SIFT features of every frame into the database `db`, all frames sharing one camera of
    `opts.camera_model` (the first run of frames creates it, the others reuse it)."""
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = opts.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = opts.threads or -1
    bar = Progress(len(names), desc="features", log_every=1)
    done = 0
    for run in _chunks(names, 12, 8):
        pycolmap.extract_features(db, frames_dir, image_names=run,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction)  # fmt: skip
        reader.existing_camera_id = 1  # the first camera of the fresh database
        done += len(run)
        bar.update(done)
    bar.close()


def _match(db: Path, work: Path, names: list[str], opts: ProcessOptions, error_px: float) -> None:
    """Match and geometrically verify the frame pairs of `opts.matcher` (RANSAC threshold
    `error_px`), a run of pairs at a time (listed in `work/pairs.txt`)."""
    import pycolmap

    pairs = exhaustive_pairs(names) if opts.matcher == "exhaustive" else sequential_pairs(names)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = opts.threads or -1
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.max_error = error_px
    listing = work / "pairs.txt"
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(listing)
    bar = Progress(len(pairs), desc="matching", log_every=1)
    done = 0
    for run in _chunks(pairs, 10, 200):
        listing.write_text("".join(f"{a} {b}\n" for a, b in run))
        pycolmap.match_image_pairs(db, matching_options=matching, pairing_options=pairing,
                                   verification_options=verification)  # fmt: skip
        done += len(run)
        bar.update(done)
    bar.close()
    listing.unlink()


def _map(db: Path, frames_dir: Path, work: Path, n: int, opts: ProcessOptions, error_px: float):
    """COLMAP's incremental mapper with thresholds `error_px`; the largest model (a
    pycolmap.Reconstruction), or None when it built none. Runs in a thread, so that Ctrl-C
    cancels it and the progress bar follows the frames it registers."""
    import pycolmap

    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = opts.threads or -1
    options.random_seed = 0
    options.min_model_size = MIN_FRAMES
    options.mapper.init_max_error = error_px
    options.mapper.abs_pose_max_error = 3.0 * error_px
    options.mapper.filter_max_reproj_error = error_px
    options.triangulation.merge_max_reproj_error = error_px
    options.triangulation.complete_max_reproj_error = error_px
    token = pycolmap.CancellationToken()
    registered = [0]
    box: dict[str, Any] = {}

    def one_more(k: int = 1) -> None:
        registered[0] += k

    def work_() -> None:
        try:
            box["models"] = pycolmap.incremental_mapping(
                db, frames_dir, work / "models", options,
                initial_image_pair_callback=lambda: one_more(2), next_image_callback=one_more,
                cancellation_token=token,
            )  # fmt: skip
        except BaseException as e:  # re-raised in the caller's thread
            box["error"] = e

    bar = Progress(n, desc="mapping", log_every=max(1, n // 4))
    thread = threading.Thread(target=work_, name="sync4d-mapping", daemon=True)
    thread.start()
    shown = 0
    try:
        while thread.is_alive():
            thread.join(0.25)
            if min(n, registered[0]) > shown:
                shown = min(n, registered[0])
                bar.update(shown)
    except KeyboardInterrupt:
        token.cancel()
        thread.join()
        raise
    finally:
        bar.close()
    if "error" in box:
        raise box["error"]
    models = box.get("models") or {}
    shutil.rmtree(work / "models", ignore_errors=True)
    return max(models.values(), key=lambda r: r.num_reg_images()) if models else None


def _undistort(rec, frames_dir: Path, images_dir: Path, names: list[str]) -> dict[str, Any]:
    """Undistort the registered frames `names` of model `rec` onto COLMAP's PINHOLE camera for
    them (cropped to pixels with a source: no blank border) into `images_dir`; that camera as
    transforms.json's intrinsics (w, h, fl_x, fl_y, cx, cy)."""
    import pycolmap
    from PIL import Image

    options = pycolmap.UndistortCameraOptions()
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    pinhole = None
    bar = Progress(len(names), desc="undistortion", log_every=max(1, len(names) // 4))
    for k, name in enumerate(names):
        with Image.open(frames_dir / name) as im:
            bitmap = pycolmap.Bitmap.from_array(np.asarray(im.convert("RGB")))
        camera = rec.cameras[by_name[name].camera_id]
        image, pinhole = pycolmap.undistort_image(options, bitmap, camera)
        Image.fromarray(np.asarray(image.to_array(), np.uint8)).save(images_dir / name)
        bar.update(k + 1)
    bar.close()
    assert pinhole is not None  # names is not empty
    fx, fy, cx, cy = (float(v) for v in pinhole.params[:4])
    return {"w": int(pinhole.width), "h": int(pinhole.height),
            "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}  # fmt: skip


def _write(rec, out: Path, names: list[str], times: dict[str, float], camera: dict) -> dict:
    """Write `transforms.json` (pinhole `camera`, OpenGL camera-to-world poses of the frames
    `names` in the normalised world, their `times` in [0, 1]) and `sparse_pc.ply`; the world
    transform applied to COLMAP's (scale, rotation, centre)."""
    by_name = {rec.images[i].name: rec.images[i] for i in rec.reg_image_ids()}
    bar = Progress(2, desc="writing", log_every=1)
    centres, rotations = [], []
    for name in names:
        pose = by_name[name].cam_from_world
        pose = pose() if callable(pose) else pose  # a method in pycolmap >= 3.12
        r = np.asarray(pose.rotation.matrix(), np.float64)
        centres.append(-r.T @ np.asarray(pose.translation, np.float64))
        rotations.append(r.T)
    centres_arr, rot_arr = np.stack(centres), np.stack(rotations)
    ids = sorted(rec.point3D_ids())
    points = np.array([rec.points3D[i].xyz for i in ids], np.float64).reshape(-1, 3)
    colours = np.array([rec.points3D[i].color for i in ids], np.float64).reshape(-1, 3) / 255.0
    scale, world_rot, centre = _normalisation(centres_arr, rot_arr, points)
    write_ply_points(out / "sparse_pc.ply", scale * (points - centre) @ world_rot.T, colours)
    bar.update(1)
    frames = []
    for name, c, r in zip(names, centres_arr, rot_arr, strict=True):
        c2w = np.eye(4)
        c2w[:3, :3] = world_rot @ r @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL axes
        c2w[:3, 3] = scale * world_rot @ (c - centre)
        frames.append({"file_path": f"images/{name}",
                       "transform_matrix": np.round(c2w, 10).tolist(),
                       "time": times[name],
                       "colmap_im_id": int(by_name[name].image_id)})  # fmt: skip
    doc = {"camera_model": "OPENCV", **camera, "ply_file_path": "sparse_pc.ply", "frames": frames}
    (out / "transforms.json").write_text(json.dumps(doc, indent=1))
    bar.update(2)
    bar.close()
    return {"scale": scale, "rotation": world_rot.tolist(), "centre": centre.tolist(),
            "points": len(points)}  # fmt: skip


def _error_threshold(longest_side: int) -> float:
    """Reprojection / RANSAC threshold in pixels: COLMAP's 4 px at 1600-pixel images, scaled
    with the image (the same angle), never below 1 px."""
    return float(min(4.0, max(1.0, longest_side / 400.0)))


@contextlib.contextmanager
def _colmap_log(verbose: bool):
    """Silence COLMAP's log (but fatal errors) unless `verbose`: process reports itself."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 3  # glog: 0 info, 1 warning, 2 error, 3 fatal
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """Rotation [3, 3] taking the unit vector `up` to +z (the identity when it is +z)."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, z)
    s, c = np.linalg.norm(axis), float(up @ z)
    if s < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    angle = math.atan2(s, c)
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def _normalisation(
    centres: np.ndarray, c2w_rot: np.ndarray, points: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R [3, 3], c [3]) with x' = s R (x - c): the points' median (the cameras'
    mean when there are few points) to the origin, the cameras' mean up (-y of OpenCV
    cameras, `c2w_rot` [N, 3, 3]) to +z, the cameras' median distance to `CAMERA_DISTANCE`."""
    c = np.median(points, axis=0) if len(points) >= 10 else centres.mean(0)
    up = -c2w_rot[:, :, 1].mean(0)
    rot = _rotation_to_z(up / np.linalg.norm(up)) if np.linalg.norm(up) > 1e-6 else np.eye(3)
    dist = float(np.median(np.linalg.norm(centres - c, axis=1)))
    return (CAMERA_DISTANCE / dist if dist > 1e-9 else 1.0), rot, c


def _check_output(source: Path, out: Path, force: bool) -> bool:
    """Refuse an output folder that is not empty (unless `force`: then remove what an earlier
    run wrote there) or that holds the input. Whether `out` is new."""
    if out.exists() and not out.is_dir():
        raise DatasetError(out, "is a file; --out must be a folder (new or empty)")
    src, dst = source.resolve(), out.resolve()
    if src == dst or dst in src.parents:
        raise DatasetError(out, f"holds the input {source}; choose an --out outside it")
    if not out.exists():
        return True
    if any(out.iterdir()):
        if not force:
            raise DatasetError(
                out, "is not empty; choose a new --out, or pass --force to replace what an "
                "earlier `sync4d process` wrote there"
            )  # fmt: skip
        _remove_outputs(out)
    return False


def _remove_outputs(out: Path) -> None:
    for name in OUTPUTS:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


def process_capture(
    source: str | Path, out: str | Path, options: ProcessOptions | None = None, force: bool = False
) -> ProcessResult:
    """Turn a video file or a folder of photos `source` into a nerfstudio dataset in `out`
    (`transforms.json` with pinhole intrinsics, OpenGL camera-to-world poses and per-frame
    times, undistorted `images/`, `sparse_pc.ply`, COLMAP's database and model in `colmap/`).
    Raises `DatasetError` naming the file and what to try; on any failure what it wrote is
    removed."""
    opts = options or ProcessOptions()
    source, out = Path(source), Path(out)
    if not source.exists():
        raise DatasetError(source, "does not exist; give a video file or a folder of photos")
    if opts.camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model must be one of {CAMERA_MODELS}, got {opts.camera_model!r}")
    if opts.matcher not in MATCHERS:
        raise ValueError(f"matcher must be one of {MATCHERS}, got {opts.matcher!r}")
    if source.is_dir() and opts.fps is not None:
        raise DatasetError(source, "--fps samples a video; a photo folder is read whole "
                           "(use --max-frames to thin it)")  # fmt: skip
    created = _check_output(source, out, force)
    try:
        with _colmap_log(opts.verbose):
            return _process(source, out, opts)
    except BaseException:
        if created:
            shutil.rmtree(out, ignore_errors=True)
        else:
            _remove_outputs(out)
        raise


def _process(source: Path, out: Path, opts: ProcessOptions) -> ProcessResult:
    """The stages of `process_capture`, each timed."""
    from PIL import Image

    seconds: dict[str, float] = {}
    work = out / "colmap"
    frames_dir = work / "frames"
    frames_dir.mkdir(parents=True)
    t0 = time.perf_counter()
    if source.is_dir():
        names, source_frames = _read_images(source, frames_dir, opts)
        stamps = [float(i) for i in range(len(names))]
    else:
        names, stamps, source_frames = _extract_video(source, frames_dir, opts)
    seconds["frames"] = time.perf_counter() - t0
    if len(names) < MIN_FRAMES:
        raise DatasetError(
            source,
            f"gives {len(names)} frame(s) (of {source_frames}); COLMAP needs at least "
            f"{MIN_FRAMES}, and a good capture 30 or more: a longer video, a higher --fps or "
            "more photos",
        )
    with Image.open(frames_dir / names[0]) as im:
        error_px = _error_threshold(max(im.size))
    db = work / "database.db"

    t0 = time.perf_counter()
    _features(db, frames_dir, names, opts)
    seconds["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _match(db, work, names, opts, error_px)
    seconds["matching"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    rec = _map(db, frames_dir, work, len(names), opts, error_px)
    seconds["mapping"] = time.perf_counter() - t0
    registered = sorted(rec.images[i].name for i in rec.reg_image_ids()) if rec else []
    need = max(MIN_FRAMES, math.ceil(opts.min_registered * len(names)))
    if rec is None or len(registered) < need:
        raise DatasetError(
            source,
            f"COLMAP registered {len(registered)} of {len(names)} frames (need at least "
            f"{need}): the camera poses could not be recovered; try a capture with more "
            "texture on the static background and more overlap between frames (a slower "
            "camera), a higher --fps, --matcher exhaustive, or larger frames (--max-size)",
        )
    (work / "sparse" / "0").mkdir(parents=True)
    rec.write(work / "sparse" / "0")
    kept = set(registered)
    dropped = [n for n in names if n not in kept]

    t0 = time.perf_counter()
    (out / "images").mkdir()
    camera = _undistort(rec, frames_dir, out / "images", registered)
    seconds["undistortion"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    t_lo, t_hi = min(stamps), max(stamps)
    times = {n: (t - t_lo) / (t_hi - t_lo) if t_hi > t_lo else 0.0
             for n, t in zip(names, stamps, strict=True)}  # fmt: skip
    world = _write(rec, out, registered, times, camera)
    shutil.rmtree(frames_dir)
    seconds["writing"] = time.perf_counter() - t0
    raw = rec.cameras[rec.images[next(iter(rec.reg_image_ids()))].camera_id]
    colmap_camera = {
        "model": str(raw.model_name),
        "size": [int(raw.width), int(raw.height)],
        "params": [float(v) for v in raw.params],
    }
    result = ProcessResult(out, source_frames, names, registered, dropped, camera, colmap_camera,
                           world.pop("points"), seconds)  # fmt: skip
    record = asdict(result) | {
        "out": str(out),
        "source": str(source),
        "options": asdict(opts),
        "error_threshold_px": error_px,
        "world_from_colmap": world,
    }
    (work / "process.json").write_text(json.dumps(record, indent=1))
    return result
