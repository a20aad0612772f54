"""nerfstudio `transforms.json`: intrinsics (`fl_x`, `fl_y`, `cx`, `cy`, `w`, `h`) at the top
level or per frame, OpenGL camera-to-world `transform_matrix`, a per-frame `time`, optional
per-frame `mask_path`, and initial points from `ply_file_path` (nerfstudio's `sparse_pc.ply`).

Time: when no frame has a `time` (the output of nerfstudio's `ns-process-data`), the frames
sorted by file name are one video with times evenly spaced over [0, 1], and the loader says so
once on stderr; some frames with a time and some without is an error. The split comes from
`train_filenames` / `test_filenames` when present, else every `test_every`-th frame (in the
file's order) is held out for testing.

Lens distortion: OpenCV coefficients `k1`, `k2`, `k3`, `k4` (radial, r^2 to r^8) and `p1`,
`p2` (tangential), at the top level or per frame, as nerfstudio writes them. A frame with a
nonzero coefficient is undistorted when its image is read (`UndistortedFrame`: bilinear
resampling onto a pinhole camera with the same principal point and a focal length scaled up
just enough that every pixel has a source inside the image). `camera_model` OPENCV_FISHEYE
and EQUIRECTANGULAR are refused.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.data.loaders import get, prepare
from sync4d.data.scene import (
    Camera,
    DatasetError,
    Frame,
    Scene,
    _resize,
    as_number,
    as_number_array,
    as_string,
    check_pose,
    image_size,
    json_kind,
    opengl_c2w_to_opencv_w2c,
    read_json,
)

__all__ = ["UndistortedFrame", "distort", "load_nerfstudio", "undistorted_camera"]

#: OpenCV distortion coefficients as nerfstudio names them (radial k1..k4, tangential p1, p2).
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
#: nerfstudio camera models that are not a (distorted) pinhole projection.
UNSUPPORTED_MODELS = ("OPENCV_FISHEYE", "EQUIRECTANGULAR", "FISHEYE624")
#: Paths whose "times from the file order" note was printed (once per process).
_TIMES_NOTED: set[Path] = set()


def distort(x: np.ndarray, y: np.ndarray, coeffs: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    """The OpenCV (and nerfstudio) lens model on normalised image coordinates `x`, `y` [...]
    of the pinhole projection: the distorted coordinates (x_d, y_d) [...], for `coeffs` =
    (k1, k2, k3, k4, p1, p2): x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8) + 2 p1 x y +
    p2 (r^2 + 2 x^2), y_d likewise with p1 and p2 swapped."""
    k1, k2, k3, k4, p1, p2 = coeffs
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y)
    return xd, yd


def _source_pixels(source: Camera, target: Camera, coeffs: tuple[float, ...], u, v):
    """Pixel coordinates (pixel centres at +0.5) in the distorted `source` image of the points
    seen at pixel coordinates `u`, `v` of the pinhole `target` (same size, same pose)."""
    xd, yd = distort((u - target.cx) / target.fx, (v - target.cy) / target.fy, coeffs)
    return source.fx * xd + source.cx, source.fy * yd + source.cy


def undistorted_camera(source: Camera, coeffs: tuple[float, ...], path: Path, what: str) -> Camera:
    """The pinhole camera that `UndistortedFrame` resamples a distorted image of `source` onto:
    the same size, pose and principal point, the focal lengths times the smallest factor s >= 1
    at which every pixel of the border maps inside the source image (to within half a pixel).
    `DatasetError` when the lens model folds over within the image (its radial polynomial
    stops growing before the corners) or needs s > 4."""
    w, h = source.width, source.height
    edge = np.linspace(0.0, 1.0, 65)
    u = np.concatenate([edge * w, edge * w, np.zeros(65), np.full(65, float(w))])
    v = np.concatenate([np.zeros(65), np.full(65, float(h)), edge * h, edge * h])

    def inside(scale: float) -> bool:
        target = Camera(source.viewmat, source.fx * scale, source.fy * scale, source.cx,
                        source.cy, w, h)  # fmt: skip
        su, sv = _source_pixels(source, target, coeffs, u, v)
        return bool(((su > -0.5) & (su < w + 0.5) & (sv > -0.5) & (sv < h + 0.5)).all())

    lo, hi = 1.0, 4.0
    if not inside(lo):
        if not inside(hi):
            raise DatasetError(
                path,
                f"{what}: lens distortion {list(coeffs)} is too strong to undistort onto a "
                "pinhole of the same size; undistort the images first (`sync4d process` or "
                "`colmap image_undistorter` write pinhole images)",
            )
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if inside(mid) else (mid, hi)
        lo = hi
    cam = Camera(source.viewmat, source.fx * lo, source.fy * lo, source.cx, source.cy, w, h)
    # The radial factor must grow out to the corners, or pixels fold over.
    corner = max(abs(c) for c in ((0 - cam.cx) / cam.fx, (w - cam.cx) / cam.fx))
    corner_y = max(abs(c) for c in ((0 - cam.cy) / cam.fy, (h - cam.cy) / cam.fy))
    r2 = np.linspace(0.0, corner**2 + corner_y**2, 257)
    k1, k2, k3, k4 = coeffs[:4]
    slope = 1.0 + r2 * (3 * k1 + r2 * (5 * k2 + r2 * (7 * k3 + r2 * 9 * k4)))
    if (slope <= 0).any():
        raise DatasetError(
            path,
            f"{what}: lens distortion {list(coeffs)} folds over within the image (its radial "
            "polynomial is not monotone out to the corners); undistort the images first "
            "(`sync4d process` or `colmap image_undistorter` write pinhole images)",
        )
    return cam


def _remap(img: np.ndarray, su: np.ndarray, sv: np.ndarray, nearest: bool) -> np.ndarray:
    """`img` [H, W, ...] sampled at pixel coordinates (`su`, `sv`) [h, w] (pixel centres at
    +0.5), bilinearly or by nearest neighbour, clamped to the image."""
    h, w = img.shape[:2]
    x = np.clip(su - 0.5, 0.0, w - 1.0)
    y = np.clip(sv - 0.5, 0.0, h - 1.0)
    if nearest:
        return img[np.rint(y).astype(np.intp), np.rint(x).astype(np.intp)]
    x0 = np.minimum(x.astype(np.intp), w - 2) if w > 1 else np.zeros_like(x, np.intp)
    y0 = np.minimum(y.astype(np.intp), h - 2) if h > 1 else np.zeros_like(y, np.intp)
    fx = (x - x0)[..., None].astype(np.float32)
    fy = (y - y0)[..., None].astype(np.float32)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


@dataclass
class UndistortedFrame(Frame):
    """A frame whose image (and mask) file was taken through a lens with OpenCV distortion
    `coefficients` (k1, k2, k3, k4, p1, p2) by `source` (the file's own size): images are
    resampled bilinearly, masks by nearest neighbour, onto the pinhole `pinhole` (the same
    size, `undistorted_camera`), then resized to `camera` (which may be scaled from it)."""

    source: Camera | None = None
    pinhole: Camera | None = None
    coefficients: tuple[float, ...] = ()

    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        assert self.source is not None and self.pinhole is not None
        w, h = self.pinhole.width, self.pinhole.height
        u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
        return _source_pixels(self.source, self.pinhole, self.coefficients, u, v)

    def _as_read(self) -> Frame:
        """A plain frame reading the distorted file at its own size."""
        assert self.source is not None
        return Frame(self.image_path, self.source, self.time, self.mask_path, self.native_size,
                     self.name)  # fmt: skip

    def load_image(self, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
        """The undistorted image as float32 [H, W, 3] in [0, 1] at the camera's size."""
        raw = self._as_read().load_image(background)
        out = _remap(raw, *self._grid(), nearest=False).astype(np.float32)
        return _resize(out, (self.camera.width, self.camera.height), nearest=False)

    def load_mask(self) -> np.ndarray | None:
        """The undistorted instance mask as int32 [H, W], or None when the frame has none."""
        raw = self._as_read().load_mask()
        if raw is None:
            return None
        out = _remap(raw, *self._grid(), nearest=True)
        size = (self.camera.width, self.camera.height)
        return _resize(out.astype(np.int32), size, nearest=True).astype(np.int32)


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


def _frame_times(path: Path, frames: list[dict]) -> list[float]:
    """Each frame's `time`; when no frame has one, the rank of its file name among the sorted
    names (noted once on stderr). Some frames with a time and some without is an error."""
    missing = [i for i, fr in enumerate(frames) if fr.get("time") is None]
    if not missing:
        return [
            as_number(fr["time"], path, f"{_label(i, fr)} 'time'") for i, fr in enumerate(frames)
        ]
    if len(missing) < len(frames):
        first = _label(missing[0], frames[missing[0]])
        raise DatasetError(
            path,
            f"{len(missing)} frames have no 'time' (first: {first})"
            f" while {len(frames) - len(missing)} have one; give every frame a 'time', or none "
            "(the frames sorted by file name are then one video, evenly spaced in time)",
        )
    names = [str(fr.get("file_path", "")) for fr in frames]
    order = sorted(range(len(frames)), key=lambda i: names[i])
    rank = {i: r for r, i in enumerate(order)}
    if path.resolve() not in _TIMES_NOTED:
        _TIMES_NOTED.add(path.resolve())
        logging.getLogger("sync4d").warning(
            "%s: no frame has a 'time'; reading the %d frames, sorted by file name, as one "
            "video evenly spaced over [0, 1]", path, len(frames))
    return [float(rank[i]) for i in range(len(frames))]


def _distortion(path: Path, i: int, frame: dict, top: dict) -> tuple[float, ...]:
    """(k1, k2, k3, k4, p1, p2) of frame `i` (per frame, else top level, else 0)."""
    coeffs = []
    for key in DISTORTION_KEYS:
        v = frame.get(key, top.get(key))
        where = f"{_label(i, frame)} '{key}'" if key in frame else f"'{key}'"
        coeffs.append(0.0 if v is None else as_number(v, path, where))
    return tuple(coeffs)


def _read_points(root: Path, path: Path, data: dict) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The initial points and colours of `ply_file_path`, if given."""
    from sync4d.data.ply import read_ply_points

    if data.get("ply_file_path") in (None, ""):
        return None, None
    ply = root / as_string(data["ply_file_path"], path, "'ply_file_path'")
    if not ply.exists():
        raise DatasetError(ply, f"point cloud file is missing (the 'ply_file_path' of {path.name})")
    return read_ply_points(ply)


def load_nerfstudio(root: str | Path, resolution_scale: float = 1.0, test_every: int = 8) -> Scene:
    """Load a nerfstudio-format directory (`transforms.json`; see the module docstring)."""
    path, _ = prepare(root, resolution_scale, "test", get("nerfstudio"))
    return read(path, resolution_scale, "test", test_every)


def read(root: Path, resolution_scale: float, test_split: str, test_every: int = 8) -> Scene:
    """The scene in folder `root`, whose arguments the registry checked (`prepare`);
    `test_every` as in `load_nerfstudio`."""
    path = root / "transforms.json"
    data = read_json(path)
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(path, "missing or empty 'frames' list")
    for i, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(path, f"frame {i} must be an object, got {json_kind(fr)}")
    model = data.get("camera_model")
    if model in UNSUPPORTED_MODELS:
        raise DatasetError(
            path,
            f"camera_model {model} is not supported (sync4d renders pinhole cameras); process "
            "the capture with a perspective camera model (ns-process-data --camera-type "
            "perspective, or `sync4d process`, which writes undistorted pinhole images)",
        )
    times = _frame_times(path, frames)
    times_from_order = all(fr.get("time") is None for fr in frames)
    t_lo, t_hi = min(times), max(times)
    out: list[Frame] = []
    names: list[str] = []
    undistorted = 0
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
            w, h = image_size(img)
        cam = Camera(
            opengl_c2w_to_opencv_w2c(m),
            _intrinsic(path, i, fr, data, "fl_x"),
            _intrinsic(path, i, fr, data, "fl_y"),
            _intrinsic(path, i, fr, data, "cx"),
            _intrinsic(path, i, fr, data, "cy"),
            w,
            h,
        )
        coeffs = _distortion(path, i, fr, data)
        source = None
        if any(coeffs):
            source, cam = cam, undistorted_camera(cam, coeffs, path, label)
            undistorted += 1
        pinhole = cam
        if resolution_scale != 1.0:
            cam = cam.scaled(resolution_scale)
        # Times are normalised to [0, 1] over the sequence.
        t = (times[i] - t_lo) / (t_hi - t_lo) if t_hi > t_lo else 0.0
        mask = None
        if fr.get("mask_path") not in (None, ""):
            mask = root / as_string(fr["mask_path"], path, f"{label} 'mask_path'")
        if mask is not None and not mask.exists():
            raise DatasetError(mask, f"mask file is missing (frame {i} of {path.name})")
        if source is None:
            out.append(Frame(img, cam, t, mask, (w, h)))
        else:
            out.append(UndistortedFrame(img, cam, t, mask, (w, h), "", source, pinhole, coeffs))
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
    points, colors = _read_points(root, path, data)
    extra = {"undistorted_frames": undistorted, "times_from_order": times_from_order}
    return Scene(root.name, train, test, points=points, point_colors=colors, extra=extra)
