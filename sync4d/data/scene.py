"""The dataset contract shared by every loader and every phase.

Cameras are OpenCV pinhole cameras (x right, y down, z forward) given by a 4x4 world-to-camera
matrix and intrinsics in pixels, exactly what :func:`sync4d.raster.rasterize` takes. Frames
carry a time in [0, 1] and load their image (and instance mask, if any) lazily.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sync4d.errors import Sync4dError


def cache_dir() -> Path:
    """Where sync4d caches generated data: `$SYNC4D_CACHE`, else `$XDG_CACHE_HOME/sync4d`,
    else `~/.cache/sync4d`."""
    base = os.environ.get("SYNC4D_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "sync4d"
    )
    return Path(base)


class DatasetError(Sync4dError, ValueError):
    """Malformed dataset input; the message names the file and the problem."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


def json_kind(value: object) -> str:
    """How a JSON value reads in an error message: `a string ('abc')`, `a boolean (true)`,
    `null`, `an object`, `a list`, or the number itself."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"a boolean ({str(value).lower()})"
    if isinstance(value, str):
        return f"a string ({value[:40]!r})"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return "a list"
    return repr(value)


def _is_number(value: object) -> bool:
    # JSON numbers load as int or float; bool is an int subclass but a JSON true/false.
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def as_number(
    value: object, path: str | Path, what: str, *, integer: bool = False, positive: bool = False
) -> float:
    """`value` as a finite float when it is a JSON number (not a string, boolean or null),
    else `DatasetError(path, ...)` naming `what` (e.g. "frame 3 (r_003) 'time'").
    `integer` also requires a whole number, `positive` a value > 0."""
    if not _is_number(value):
        raise DatasetError(path, f"{what} must be a number, got {json_kind(value)}")
    v = float(value)  # type: ignore[arg-type]
    if not math.isfinite(v):
        raise DatasetError(path, f"{what} must be finite, got {v}")
    if integer and v != int(v):
        raise DatasetError(path, f"{what} must be a whole number, got {v}")
    if positive and v <= 0:
        raise DatasetError(path, f"{what} must be positive, got {v:g}")
    return v


def _first_non_number(value: object, index: str = "") -> tuple[str, object] | None:
    if isinstance(value, list):
        for j, v in enumerate(value):
            bad = _first_non_number(v, f"{index}[{j}]")
            if bad is not None:
                return bad
        return None
    return None if _is_number(value) else (index, value)


def as_number_array(value: object, path: str | Path, what: str) -> np.ndarray:
    """A (nested) JSON list of numbers as a float64 array, else `DatasetError(path, ...)`
    naming `what` and the first entry that is not a number (strings such as "0.5", booleans
    and null are refused, not converted). The caller checks the shape."""
    bad = _first_non_number(value)
    if bad is not None:
        index, v = bad
        entry = f"{what}{index}" if index else what
        raise DatasetError(path, f"{entry} must be a number, got {json_kind(v)}")
    try:
        return np.asarray(value, dtype=np.float64)
    except ValueError:  # ragged nesting: rows of different lengths
        raise DatasetError(
            path,
            f"{what} must be rectangular: a nested list of numbers whose rows have equal lengths",
        ) from None


def as_string(value: object, path: str | Path, what: str) -> str:
    """`value` when it is a non-empty JSON string, else `DatasetError(path, ...)`."""
    if not isinstance(value, str) or not value:
        raise DatasetError(path, f"{what} must be a non-empty string, got {json_kind(value)}")
    return value


def read_json(path: Path) -> dict:
    """The JSON object in file `path`, else `DatasetError(path, ...)`: the file is missing, is
    not valid JSON (with the line of the first error) or holds something other than an object
    at the top level. Every loader reads its JSON files through this one function."""
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise DatasetError(path, "file is missing") from None
    except json.JSONDecodeError as e:
        raise DatasetError(path, f"invalid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, dict):
        raise DatasetError(path, "expected a JSON object at the top level")
    return data


def read_labels(path: Path) -> dict[int, str]:
    """`labels.json`: an object of integer mask label (as a string key) -> name string."""
    raw = read_json(path)
    labels: dict[int, str] = {}
    for k, v in raw.items():
        try:
            label = int(k)
        except ValueError:
            raise DatasetError(path, f"key {k!r} is not an integer mask label") from None
        labels[label] = as_string(v, path, f"the name of label {k}")
    return labels


#: Largest max-abs entry of |R^T R - I| accepted for a pose's 3x3 rotation part. Real poses are
#: stored rounded, so they are never exactly orthonormal. Measured: D-NeRF's float32-printed
#: transform_matrix reaches 1.4e-6 (bouncingballs train; lego, hook, hellwarrior <= 7.4e-7 over
#: every frame of every split), Panoptic basketball's w2c 1.3e-10; rounding the D-NeRF rotations
#: to 6 decimals gives 1.8e-6, to 4 decimals 1.5e-4 (3 decimals: 1.4e-3, refused). 1e-3 leaves a
#: 700x margin over the real data and still refuses any scale off by more than 0.05 %
#: (|s^2 - 1| > 1e-3) and any shear of that size, which the rasterizer would render wrongly.
POSE_TOLERANCE = 1e-3


def check_pose(matrix: np.ndarray, path: str | Path, what: str) -> None:
    """Refuse a pose that is not a rigid transform: `matrix` [3, 3] (rotation), [3, 4] or
    [4, 4] (rotation plus translation) must be finite, its rotation part R orthonormal within
    `POSE_TOLERANCE` (max |R^T R - I|) with det(R) > 0, and a 4x4's bottom row [0, 0, 0, 1].
    `what` names the pose in the message (e.g. "frame 3 (r_003) 'transform_matrix'")."""
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape not in ((3, 3), (3, 4), (4, 4)):
        raise DatasetError(path, f"{what} must be 3x3, 3x4 or 4x4, got shape {list(m.shape)}")
    if not np.isfinite(m).all():
        raise DatasetError(path, f"{what} contains NaN or inf")
    lead = f"{what} is not a rigid transform"
    tail = "poses must be rotations plus translations"
    bottom_off = m.shape == (4, 4) and np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > POSE_TOLERANCE
    if bottom_off:
        raise DatasetError(
            path, f"{lead}: its bottom row is {m[3].tolist()}, expected [0, 0, 0, 1]; {tail}"
        )
    r = m[:3, :3]
    sv = np.linalg.svd(r, compute_uv=False)
    if sv[-1] < 1e-6 * max(sv[0], 1.0):
        raise DatasetError(
            path,
            f"{lead}: its rotation part is singular (singular values "
            f"{sv.round(6).tolist()}); {tail}",
        )
    dev = float(np.abs(r.T @ r - np.eye(3)).max())
    if dev > POSE_TOLERANCE:
        raise DatasetError(
            path,
            f"{lead}: its rotation part is scaled or sheared (|R^T R - I| = {dev:.3g}, "
            f"tolerance {POSE_TOLERANCE:g}); {tail}",
        )
    if np.linalg.det(r) <= 0:
        raise DatasetError(
            path,
            f"{lead}: its rotation part is a reflection (det = {np.linalg.det(r):.3g}); {tail} "
            "(check the handedness of the axis convention)",
        )


@dataclass(frozen=True)
class Camera:
    """Pinhole camera: `viewmat` [4, 4] world-to-camera (OpenCV axes), intrinsics in pixels."""

    viewmat: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def K(self) -> np.ndarray:
        """[3, 3] intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        r, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -r.T @ t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [N, 3] to pixel coordinates [N, 2] (pixel centres at +0.5)
        and camera depths [N]."""
        pc = points @ self.viewmat[:3, :3].T + self.viewmat[:3, 3]
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = np.stack([self.fx * pc[:, 0] / z + self.cx, self.fy * pc[:, 1] / z + self.cy], 1)
        return uv, z

    def scaled(self, scale: float) -> Camera:
        """The same camera for an image resized by `scale` (sizes rounded to whole pixels)."""
        w = max(1, round(self.width * scale))
        h = max(1, round(self.height * scale))
        sx, sy = w / self.width, h / self.height
        return Camera(self.viewmat, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h)


def opengl_c2w_to_opencv_w2c(c2w: np.ndarray) -> np.ndarray:
    """Convert a camera-to-world matrix in OpenGL axes (x right, y up, camera looks down -z;
    Blender, D-NeRF, nerfstudio) to a world-to-camera matrix in OpenCV axes."""
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    c2w_cv = np.asarray(c2w, dtype=np.float64) @ flip
    r, t = c2w_cv[:3, :3], c2w_cv[:3, 3]
    w2c = np.eye(4)
    w2c[:3, :3] = r.T
    w2c[:3, 3] = -r.T @ t
    return w2c


#: Image modes read at 8 bits per channel (Pillow converts them to RGB, or RGBA with alpha).
IMAGE_MODES_8BIT = ("1", "L", "LA", "P", "PA", "RGB", "RGBA")
#: Grayscale modes read at their full 16 bits and scaled by 1/65535 (a 16-bit grayscale PNG
#: opens as I;16). Mode I (32-bit integers) is read only when the file's pixels are 16-bit.
IMAGE_MODES_16BIT = ("I;16", "I;16B", "I;16L", "I;16N")
#: Instance-mask modes: single-channel integer labels (1 = binary foreground, label 1).
MASK_MODES = ("1", "L", "P", "I", "I;16", "I;16B", "I;16L", "I;16N")


def _rawmode(im) -> str:
    """The pixel layout Pillow decodes `im` from (e.g. 'RGB;16B' for a 16-bit RGB PNG, which
    Pillow truncates to mode RGB); known from the header, before `im.load()`."""
    if not im.tile:
        return im.mode
    args = im.tile[0][3]
    if isinstance(args, tuple):
        args = args[0] if args else ""
    return args if isinstance(args, str) else im.mode


def image_depth(im, path: str | Path) -> int:
    """Bits per channel (8 or 16) at which sync4d reads the opened, not yet decoded PIL image
    `im` of file `path`, or `DatasetError` saying why its mode is refused. Header only."""
    mode, raw = im.mode, _rawmode(im)
    if mode in IMAGE_MODES_16BIT or (mode == "I" and raw.startswith("I;16")):
        return 16
    if mode in IMAGE_MODES_8BIT:
        if ";16" in raw:
            raise DatasetError(
                path,
                f"16-bit colour image ({raw}): Pillow can only read it truncated to 8 bits, so "
                "sync4d refuses it; save it as 8-bit RGB/RGBA (or as 16-bit grayscale)",
            )
        return 8
    if mode == "F":
        why = "32-bit float image (mode F): its values have no fixed range for sync4d to scale"
    elif mode == "I":
        why = f"32-bit integer image (mode I, {raw}): its values have no fixed range"
    elif mode == "CMYK":
        why = "CMYK image: sync4d does no colour management; convert it to RGB"
    else:
        why = f"image mode {mode} is not supported"
    raise DatasetError(
        path,
        f"{why}; supported: 8-bit {'/'.join(IMAGE_MODES_8BIT)} and 16-bit grayscale PNG",
    )


def _open_header(path: Path, what: str, where: str):
    """Open `path` with Pillow (reads the header only), mapping failures to DatasetError."""
    from PIL import Image, UnidentifiedImageError

    suffix = f" ({where})" if where else ""
    try:
        return Image.open(path)
    except FileNotFoundError:
        raise DatasetError(path, f"{what} file is missing{suffix}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise DatasetError(path, f"cannot read {what} ({e}){suffix}") from None


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of image file `path` from its header, or `DatasetError`."""
    with _open_header(path, "image", "") as im:
        return im.size


def _resize(img: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    from PIL import Image

    w, h = size
    if img.shape[1] == w and img.shape[0] == h:
        return img
    if nearest:
        return np.asarray(Image.fromarray(img).resize((w, h), Image.Resampling.NEAREST))
    if img.dtype == np.float32:  # one float channel at a time (Pillow's mode F)
        chans = [
            Image.fromarray(img[..., c]).resize((w, h), Image.Resampling.BOX)
            for c in range(img.shape[-1])
        ]
        return np.stack([np.asarray(c) for c in chans], -1)
    return np.asarray(Image.fromarray(img).resize((w, h), Image.Resampling.BOX))


@dataclass
class Frame:
    """One posed image at one time; `mask_path` is an indexed instance mask (0 = background)."""

    image_path: Path
    camera: Camera
    time: float
    mask_path: Path | None = None
    #: (width, height) of the files on disk; `camera` may be scaled from it.
    native_size: tuple[int, int] | None = None
    #: Unique name of the frame within its split (reports, render file names); defaults to
    #: the image's file name. Multi-view loaders prefix the camera (`cam10_000000.jpg`).
    name: str = ""

    def __post_init__(self) -> None:
        if not self.name:
            self.name = self.image_path.name

    def load_image(self, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> np.ndarray:
        """The image as float32 [H, W, 3] in [0, 1], RGBA composited on `background`, resized
        to the camera's size. 8-bit modes are scaled by 1/255, 16-bit grayscale by 1/65535;
        other modes raise `DatasetError` (see `image_depth`)."""
        premultiplied, alpha = self.load_layers()
        if alpha is None:
            return premultiplied
        return premultiplied + np.asarray(background, np.float32) * (1.0 - alpha)

    def has_alpha(self) -> bool:
        """Whether the image has an alpha channel (read from its header): its colour depends
        on the background it is composited on (`load_image`)."""
        with _open_header(self.image_path, "image", "") as im:
            return im.mode in ("RGBA", "LA", "P", "PA") and image_depth(im, self.image_path) == 8

    def load_layers(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The image as its colour times alpha, float32 [H, W, 3] in [0, 1], and its alpha
        [H, W, 1] (None for an image without alpha), resized to the camera's size: the image
        on background `b` is ``colour + b * (1 - alpha)`` (`load_image`), a background drawn
        anew at each training step costs no file read."""
        im = _open_header(self.image_path, "image", "")
        try:
            with im:
                depth = image_depth(im, self.image_path)
                im.load()
                if depth == 16:
                    arr = np.asarray(im).astype(np.float32) / 65535.0
                else:
                    rgba = im.mode in ("RGBA", "LA", "P", "PA")
                    arr = np.asarray(im.convert("RGBA" if rgba else "RGB"))
        except OSError as e:  # truncated or corrupt pixel data
            raise DatasetError(self.image_path, f"cannot read image ({e})") from None
        self._check_size(self.image_path, arr, "image")
        size = (self.camera.width, self.camera.height)
        if depth == 16:
            gray = _resize(arr[..., None], size, nearest=False)
            return np.repeat(gray, 3, axis=-1), None
        arr = _resize(arr, size, nearest=False)
        rgb = arr[..., :3].astype(np.float32) / 255.0
        if arr.shape[-1] != 4:
            return rgb, None
        a = arr[..., 3:4].astype(np.float32) / 255.0
        return rgb * a, a

    def _check_size(self, path: Path, arr: np.ndarray, what: str) -> None:
        if self.native_size is not None and (arr.shape[1], arr.shape[0]) != self.native_size:
            w, h = self.native_size
            raise DatasetError(
                path,
                f"{what} is {arr.shape[1]}x{arr.shape[0]} but the dataset's images are {w}x{h}",
            )

    def load_mask(self) -> np.ndarray | None:
        """The instance mask as int32 [H, W] (0 = background), resized by nearest neighbour,
        or None when the frame has none."""
        if self.mask_path is None:
            return None
        im = _open_header(self.mask_path, "mask", "")
        try:
            with im:
                if im.mode not in MASK_MODES:
                    raise DatasetError(
                        self.mask_path, f"instance mask must be single-channel, got mode {im.mode}"
                    )
                im.load()
                if im.mode == "1":  # binary foreground mask: label 1
                    arr = (np.asarray(im.convert("L")) > 0).astype(np.uint8)
                else:
                    arr = np.asarray(im)
        except OSError as e:
            raise DatasetError(self.mask_path, f"cannot read mask ({e})") from None
        self._check_size(self.mask_path, arr, "mask")
        return _resize(arr, (self.camera.width, self.camera.height), nearest=True).astype(np.int32)


@dataclass
class Scene:
    """A dynamic scene: train and test frames, optional instance-label names and initial points."""

    name: str
    train: list[Frame]
    test: list[Frame]
    labels: dict[int, str] | None = None
    #: [N, 3] float64 world points to initialise the Gaussians from (e.g. COLMAP's sparse cloud).
    points: np.ndarray | None = None
    #: [N, 3] float32 RGB in [0, 1] of `points` (same length), or None when uncoloured.
    point_colors: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    @property
    def has_masks(self) -> bool:
        """Whether every training frame has an instance mask."""
        return bool(self.train) and all(f.mask_path is not None for f in self.train)


def check_scene(scene: Scene) -> None:
    """Check every frame's image and mask file from its header alone (no pixel decode), so a
    bad file fails at load time rather than when training first reads it: each image must be
    readable, in a mode sync4d reads at its true depth (`image_depth`) and of the frame's
    native size (when unknown, the size of its split's first image); each mask must be
    single-channel (`MASK_MODES`) and of its image's size. Raises `DatasetError` naming the
    file, the split and the frame."""
    for split, frames in (("train", scene.train), ("test", scene.test)):
        first: tuple[int, int] | None = None
        for i, f in enumerate(frames):
            where = f"{split} frame {i}, {f.name}"
            with _open_header(f.image_path, "image", where) as im:
                try:
                    image_depth(im, f.image_path)
                except DatasetError as e:
                    raise DatasetError(f.image_path, f"{e.problem} ({where})") from None
                size = im.size
            expected = f.native_size or first or size
            first = first or size
            if size != expected:
                raise DatasetError(
                    f.image_path,
                    f"image is {size[0]}x{size[1]} but the dataset's images are "
                    f"{expected[0]}x{expected[1]} ({where})",
                )
            if f.mask_path is None:
                continue
            with _open_header(f.mask_path, "mask", where) as m:
                mode, msize = m.mode, m.size
            if mode not in MASK_MODES:
                raise DatasetError(
                    f.mask_path,
                    f"instance mask must be single-channel ({'/'.join(MASK_MODES)}), got mode "
                    f"{mode} ({where})",
                )
            if msize != size:
                raise DatasetError(
                    f.mask_path,
                    f"mask is {msize[0]}x{msize[1]} but the dataset's images are "
                    f"{size[0]}x{size[1]} ({where})",
                )
