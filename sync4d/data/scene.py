"""The dataset contract shared by every loader and every phase.

Cameras are OpenCV pinhole cameras (x right, y down, z forward) given by a 4x4 world-to-camera
matrix and intrinsics in pixels, exactly what :func:`sync4d.raster.rasterize` takes. Frames
carry a time in [0, 1] and load their image (and instance mask, if any) lazily.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


def cache_dir() -> Path:
    """Where sync4d caches generated data: `$SYNC4D_CACHE`, else `$XDG_CACHE_HOME/sync4d`,
    else `~/.cache/sync4d`."""
    base = os.environ.get("SYNC4D_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "sync4d"
    )
    return Path(base)


class DatasetError(ValueError):
    """Malformed dataset input; the message names the file and the problem."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


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


def _resize(img: np.ndarray, size: tuple[int, int], nearest: bool) -> np.ndarray:
    from PIL import Image

    w, h = size
    if img.shape[1] == w and img.shape[0] == h:
        return img
    if nearest:
        return np.asarray(Image.fromarray(img).resize((w, h), Image.Resampling.NEAREST))
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
        to the camera's size."""
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(self.image_path) as im:
                im.load()
                arr = np.asarray(
                    im.convert("RGBA") if im.mode in ("RGBA", "LA", "P") else im.convert("RGB")
                )
        except FileNotFoundError:
            raise DatasetError(self.image_path, "image file is missing") from None
        except (UnidentifiedImageError, OSError) as e:
            raise DatasetError(self.image_path, f"cannot read image ({e})") from None
        self._check_size(self.image_path, arr, "image")
        arr = _resize(arr, (self.camera.width, self.camera.height), nearest=False)
        rgb = arr[..., :3].astype(np.float32) / 255.0
        if arr.shape[-1] == 4:
            a = arr[..., 3:4].astype(np.float32) / 255.0
            rgb = rgb * a + np.asarray(background, np.float32) * (1.0 - a)
        return rgb

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
        from PIL import Image, UnidentifiedImageError

        try:
            with Image.open(self.mask_path) as im:
                im.load()
                if im.mode == "1":  # binary foreground mask: label 1
                    arr = (np.asarray(im.convert("L")) > 0).astype(np.uint8)
                elif im.mode in ("L", "P", "I", "I;16"):
                    arr = np.asarray(im)
                else:
                    raise DatasetError(
                        self.mask_path, f"instance mask must be single-channel, got mode {im.mode}"
                    )
        except FileNotFoundError:
            raise DatasetError(self.mask_path, "mask file is missing") from None
        except (UnidentifiedImageError, OSError) as e:
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
