"""D-NeRF / Blender loader: the camera convention, resolution scaling, masks, and one clear
error per malformed input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support import SHARED_DATA
from support.cameras import look_at_gl
from support.datasets import corrupt_blender, write_blender
from sync4d.data import DatasetError
from sync4d.data.blender import load_blender
from sync4d.data.scene import opengl_c2w_to_opencv_w2c

SHARED = SHARED_DATA / "dnerf" / "bouncingballs"


def test_known_point_lands_on_the_same_pixel_as_under_opengl(tmp_path: Path) -> None:
    """Project points with the OpenGL convention by hand and with the converted camera."""
    write_blender(tmp_path)
    scene = load_blender(tmp_path)
    raw = json.loads((tmp_path / "transforms_train.json").read_text())["frames"]
    rng = np.random.default_rng(0)
    for frame, fr in zip(scene.train, raw, strict=True):
        cam = frame.camera
        pts = rng.normal(size=(10, 3)) * 0.5
        uv, z = cam.project(pts)
        # OpenGL, from the file's own camera-to-world: camera looks down -z, y up, and pixel
        # rows grow downwards.
        c2w = np.asarray(fr["transform_matrix"])
        pg = (np.linalg.inv(c2w) @ np.c_[pts, np.ones(10)].T).T[:, :3]
        f = 0.5 * cam.width / math.tan(0.35)
        u = cam.width / 2 + f * pg[:, 0] / -pg[:, 2]
        v = cam.height / 2 - f * pg[:, 1] / -pg[:, 2]
        assert np.allclose(uv, np.stack([u, v], 1), atol=1e-9)
        assert np.allclose(z, -pg[:, 2])
        assert (z > 0).all()  # the origin is in front of every camera


def test_conversion_matches_an_explicit_axis_flip() -> None:
    c2w = look_at_gl(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    w2c = opengl_c2w_to_opencv_w2c(c2w)
    # The world origin is straight ahead: x = y = 0, z = distance.
    p = w2c @ np.array([0.0, 0.0, 0.0, 1.0])
    assert np.allclose(p[:3], [0.0, 0.0, math.sqrt(14.0)])
    assert np.allclose(w2c[:3, :3] @ w2c[:3, :3].T, np.eye(3))


def test_images_masks_times_and_scaling(tmp_path: Path) -> None:
    write_blender(tmp_path, size=20)
    scene = load_blender(tmp_path, resolution_scale=0.5)
    f = scene.train[1]
    assert f.time == pytest.approx(0.5)
    assert (f.camera.width, f.camera.height) == (10, 10)
    assert f.camera.fx == pytest.approx(0.5 * 20 / math.tan(0.35) * 0.5)
    img = f.load_image(background=(1.0, 1.0, 1.0))
    assert img.shape == (10, 10, 3) and img.dtype == np.float32
    assert np.allclose(img[0, 0], 1.0)  # transparent → white background
    assert np.allclose(img[-1, -1], [200 / 255, 0, 0], atol=1e-6)
    black = f.load_image(background=(0.0, 0.0, 0.0))
    assert np.allclose(black[0, 0], 0.0)
    mask = f.load_mask()
    assert mask.shape == (10, 10) and set(np.unique(mask)) == {0, 2}
    assert scene.labels == {0: "background", 2: "ball"}
    assert scene.has_masks


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda d: d["frames"][1].pop("time"), "frame 1 .* has no 'time'"),
        (lambda d: d["frames"][0].__setitem__("transform_matrix", [[1, 0, 0]]), "must be 4x4"),
        (lambda d: d.pop("camera_angle_x"), "missing 'camera_angle_x'"),
        (lambda d: d["frames"][2].__setitem__("time", 1.5), "expected a value in \\[0, 1\\]"),
        (
            lambda d: d["frames"][0].__setitem__("file_path", "./train/nope"),
            "image file is missing",
        ),
        (lambda d: d.__setitem__("frames", []), "empty 'frames'"),
    ],
)
def test_malformed_transforms_name_the_file(tmp_path: Path, mutate, match) -> None:
    write_blender(tmp_path)
    corrupt_blender(tmp_path, "train", mutate)
    with pytest.raises(DatasetError, match=match) as e:
        load_blender(tmp_path)
    assert "transforms_train.json" in str(e.value) or "nope" in str(e.value)


def test_missing_files_and_mismatched_masks(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="dataset directory does not exist"):
        load_blender(tmp_path / "absent")
    write_blender(tmp_path)
    (tmp_path / "transforms_test.json").write_text("{not json")
    with pytest.raises(DatasetError, match="transforms_test.json: invalid JSON"):
        load_blender(tmp_path)
    write_blender(tmp_path)
    (tmp_path / "masks" / "train" / "r_001.png").unlink()
    with pytest.raises(DatasetError, match="r_001.png: mask for r_001.png is missing"):
        load_blender(tmp_path)
    write_blender(tmp_path)
    Image.fromarray(np.zeros((7, 9), np.uint8), "L").save(tmp_path / "masks/train/r_002.png")
    scene = load_blender(tmp_path)
    with pytest.raises(
        DatasetError, match="r_002.png: mask is 9x7 but the dataset's images are 20x20"
    ):
        scene.train[2].load_mask()
    (tmp_path / "train" / "r_000.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="r_000.png: cannot read image"):
        load_blender(tmp_path)


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data is not present (user clone)")
def test_real_bouncingballs_loads_with_masks() -> None:
    scene = load_blender(SHARED, resolution_scale=0.5)
    assert len(scene.train) == 150 and scene.has_masks
    assert scene.labels[1] == "red ball"
    f = scene.train[0]
    assert (f.camera.width, f.camera.height) == (400, 400)
    img, mask = f.load_image(), f.load_mask()
    assert img.shape == (400, 400, 3) and mask.shape == (400, 400)
    assert set(np.unique(mask)) <= {0, 1, 2, 3}
    # The scene centre projects inside every training image.
    for fr in scene.train[::10]:
        uv, z = fr.camera.project(np.zeros((1, 3)))
        assert z[0] > 0 and 0 <= uv[0, 0] < 400 and 0 <= uv[0, 1] < 400
