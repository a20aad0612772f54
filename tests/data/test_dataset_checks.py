"""Everything a run reads from a dataset is checked when it loads, before any training: poses
must be rigid, numeric fields real JSON numbers, images and masks readable at their true depth
and of the right size and mode. Each failure is one `DatasetError` naming the file, the frame
and the problem."""

from __future__ import annotations

import json
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support.datasets import (
    corrupt_blender,
    write_blender,
    write_colmap,
    write_hypernerf,
    write_nerfstudio,
    write_panoptic,
)
from sync4d.data import DatasetError, load_scene


def _set_matrix(fn):
    """A `corrupt_blender` mutation applying `fn` to frame 1's transform_matrix (a list of
    lists)."""

    def mutate(d: dict) -> None:
        m = np.asarray(d["frames"][1]["transform_matrix"], dtype=object)
        d["frames"][1]["transform_matrix"] = fn(m).tolist()

    return mutate


def _scaled(m: np.ndarray) -> np.ndarray:
    m[:3, :3] = m[:3, :3] * 1.2
    return m


def _singular(m: np.ndarray) -> np.ndarray:
    m[:3, 2] = 0.0
    return m


def _sheared(m: np.ndarray) -> np.ndarray:
    m[:3, :3] = m[:3, :3] @ np.array([[1.0, 0.4, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    return m


def _reflected(m: np.ndarray) -> np.ndarray:
    m[:3, 0] = -m[:3, 0]
    return m


def _bottom_row(m: np.ndarray) -> np.ndarray:
    m[3] = [0.0, 0.0, 0.5, 1.0]
    return m


@pytest.mark.parametrize(
    "fn,problem",
    [
        (_scaled, r"rotation part is scaled or sheared \(\|R\^T R - I\| = 0\.44"),
        (_singular, "rotation part is singular"),
        (_sheared, r"rotation part is scaled or sheared \(\|R\^T R - I\| = 0\.4"),
        (_reflected, r"rotation part is a reflection \(det = -1"),
        (_bottom_row, r"bottom row is \[0\.0, 0\.0, 0\.5, 1\.0\]"),
    ],
    ids=["scaled", "singular", "sheared", "reflected", "bottom-row"],
)
def test_non_rigid_blender_pose_is_refused(tmp_path: Path, fn, problem: str) -> None:
    write_blender(tmp_path)
    corrupt_blender(tmp_path, "train", _set_matrix(fn))
    with pytest.raises(DatasetError, match=problem) as e:
        load_scene(tmp_path)
    msg = str(e.value)
    assert (
        "transforms_train.json: frame 1 (r_001) 'transform_matrix' is not a rigid transform" in msg
    )
    assert "poses must be rotations plus translations" in msg


def test_rounded_real_poses_pass_the_rigidity_check() -> None:
    """Poses printed with 4 decimals (|R^T R - I| ~1e-4) pass; a 0.1 % scale does not."""
    from sync4d.data.scene import POSE_TOLERANCE, check_pose

    a = 0.7
    r = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0, 0, 1]])
    check_pose(np.round(r, 4), "x.json", "pose")
    with pytest.raises(DatasetError, match="scaled or sheared"):
        check_pose(r * (1.0 + POSE_TOLERANCE), "x.json", "pose")


@pytest.mark.parametrize(
    "value,kind",
    [
        ("0.5", r"a string \('0\.5'\)"),
        ("abc", r"a string \('abc'\)"),
        (True, r"a boolean \(true\)"),
        (None, "null"),
    ],
)
def test_time_that_is_not_a_number_is_refused(tmp_path: Path, value, kind: str) -> None:
    write_blender(tmp_path)
    corrupt_blender(tmp_path, "train", lambda d: d["frames"][2].__setitem__("time", value))
    with pytest.raises(
        DatasetError,
        match=f"transforms_train.json: frame 2 \\(r_002\\) 'time' must be a number, got {kind}",
    ):
        load_scene(tmp_path)


@pytest.mark.parametrize("value", ["0.5", "abc", False, None, [1.0]])
def test_matrix_entry_that_is_not_a_number_is_refused(tmp_path: Path, value) -> None:
    def mutate(d: dict) -> None:
        d["frames"][0]["transform_matrix"][1][2] = value

    write_blender(tmp_path)
    corrupt_blender(tmp_path, "test", mutate)
    with pytest.raises(DatasetError) as e:
        load_scene(tmp_path)
    msg = str(e.value)
    assert msg.startswith(str(tmp_path / "transforms_test.json"))
    if isinstance(value, list):  # a nested list where a number belongs: the shape is wrong
        assert "frame 0 (r_000) 'transform_matrix' must be rectangular" in msg
    else:
        assert "frame 0 (r_000) 'transform_matrix'[1][2] must be a number" in msg


@pytest.mark.parametrize("value", ["0.7", "wide", True, None])
def test_camera_angle_x_that_is_not_a_number_is_refused(tmp_path: Path, value) -> None:
    write_blender(tmp_path)
    corrupt_blender(tmp_path, "train", lambda d: d.__setitem__("camera_angle_x", value))
    with pytest.raises(
        DatasetError, match="transforms_train.json: 'camera_angle_x' must be a number, got"
    ):
        load_scene(tmp_path)


def test_mask_of_the_wrong_size_is_reported_by_load_scene(tmp_path: Path) -> None:
    write_blender(tmp_path)
    Image.fromarray(np.zeros((7, 9), np.uint8), "L").save(tmp_path / "masks/train/r_002.png")
    with pytest.raises(
        DatasetError,
        match=r"r_002.png: mask is 9x7 but the dataset's images are 20x20 "
        r"\(train frame 2, r_002.png\)",
    ):
        load_scene(tmp_path)


def test_rgb_mask_is_reported_by_load_scene(tmp_path: Path) -> None:
    write_blender(tmp_path)
    Image.fromarray(np.zeros((20, 20, 3), np.uint8), "RGB").save(tmp_path / "masks/test/r_001.png")
    with pytest.raises(
        DatasetError,
        match=r"masks[/\\]test[/\\]r_001.png: instance mask must be single-channel .*got mode RGB "
        r"\(test frame 1, r_001.png\)",
    ):
        load_scene(tmp_path)


def test_image_of_another_size_is_reported_by_load_scene(tmp_path: Path) -> None:
    write_blender(tmp_path, masks=False)
    Image.fromarray(np.zeros((10, 20, 4), np.uint8), "RGBA").save(tmp_path / "train/r_002.png")
    with pytest.raises(
        DatasetError,
        match=r"r_002.png: image is 20x10 but the dataset's images are 20x20 \(train frame 2",
    ):
        load_scene(tmp_path)


def _use_image(root: Path, name: str) -> None:
    """Point train frame 0 of a `write_blender` dataset at `root/train/name`."""
    path = f"./train/{name}"
    corrupt_blender(root, "train", lambda d: d["frames"][0].__setitem__("file_path", path))


def test_16bit_grayscale_png_is_read_at_its_real_depth(tmp_path: Path) -> None:
    write_blender(tmp_path, masks=False)
    gray = (np.arange(400, dtype=np.uint16).reshape(20, 20) * 163 + 7).astype(np.uint16)
    Image.fromarray(gray).save(tmp_path / "train/r_000.png")  # mode I;16
    assert Image.open(tmp_path / "train/r_000.png").mode == "I;16"
    scene = load_scene(tmp_path)
    img = scene.train[0].load_image()
    assert img.shape == (20, 20, 3) and img.dtype == np.float32
    expected = gray.astype(np.float32) / 65535.0
    assert np.allclose(img, expected[..., None], atol=1e-7)  # not truncated to 8 bits
    half = load_scene(tmp_path, resolution_scale=0.5).train[0].load_image()
    box = expected.reshape(10, 2, 10, 2).mean(axis=(1, 3))
    assert half.shape == (10, 10, 3) and np.allclose(half[..., 0], box, atol=1e-6)


def _write_png16(path: Path, arr: np.ndarray) -> None:
    """A 16-bit RGB (3 channels) or RGBA (4) PNG, which Pillow cannot write."""
    h, w, c = arr.shape
    raw = b"".join(b"\x00" + arr[y].astype(">u2").tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        crc = struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)
        return struct.pack(">I", len(data)) + tag + data + crc

    header = struct.pack(">IIBBBBB", w, h, 16, {3: 2, 4: 6}[c], 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )


def _cmyk_tiff(p: Path) -> None:
    Image.new("CMYK", (20, 20), (0, 50, 0, 0)).save(p)


def _float_tiff(p: Path) -> None:
    Image.fromarray(np.full((20, 20), 0.5, np.float32), "F").save(p)


def _int32_tiff(p: Path) -> None:
    Image.fromarray(np.full((20, 20), 70000, np.int32), "I").save(p)


def _rgb16_png(p: Path) -> None:
    _write_png16(p, np.full((20, 20, 3), 1000, np.uint16))


@pytest.mark.parametrize(
    "write,name,problem",
    [
        (_cmyk_tiff, "c.tiff", "CMYK image"),
        (_float_tiff, "f.tiff", r"32-bit float image \(mode F\)"),
        (_int32_tiff, "i.tiff", r"32-bit integer image \(mode I"),
        (_rgb16_png, "rgb16.png", r"16-bit colour image \(RGB;16B\).*truncated to 8 bits"),
    ],
    ids=["CMYK", "F", "I32", "RGB16"],
)
def test_unsupported_image_mode_is_refused(tmp_path: Path, write, name, problem) -> None:
    write_blender(tmp_path, masks=False)
    write(tmp_path / "train" / name)
    _use_image(tmp_path, name)
    with pytest.raises(DatasetError, match=f"{name}: {problem}.*\\(train frame 0, {name}\\)"):
        load_scene(tmp_path)
    # Read on its own, the frame refuses it the same way rather than guessing its values.
    from sync4d.data.blender import load_blender

    with pytest.raises(DatasetError, match=f"{name}: {problem}"):
        load_blender(tmp_path).train[0].load_image()


# The other loaders' numeric fields and poses.


def test_nerfstudio_intrinsic_as_a_string_is_refused(tmp_path: Path) -> None:
    data = write_nerfstudio(tmp_path)
    data["fl_x"] = "10.0"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(
        DatasetError, match=r"transforms.json: 'fl_x' must be a number, got a string \('10.0'\)"
    ):
        load_scene(tmp_path)
    data = write_nerfstudio(tmp_path)
    data["frames"][3]["time"] = "6"
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"frame 3 \(f3.png\) 'time' must be a number"):
        load_scene(tmp_path)


def test_nerfstudio_non_rigid_pose_is_refused(tmp_path: Path) -> None:
    data = write_nerfstudio(tmp_path)
    data["frames"][5]["transform_matrix"][0][0] = 2.0
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(
        DatasetError,
        match=r"transforms.json: frame 5 \(f5.png\) 'transform_matrix' is not a rigid transform",
    ):
        load_scene(tmp_path)


def test_hypernerf_camera_fields_are_checked(tmp_path: Path) -> None:
    write_hypernerf(tmp_path)
    cam = tmp_path / "camera" / "001.json"
    data = json.loads(cam.read_text())
    good = dict(data)
    data["focal_length"] = "20"
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"001.json: 'focal_length' must be a number"):
        load_scene(tmp_path)
    data = dict(good, orientation=(np.eye(3) * 0.5).tolist())
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"001.json: 'orientation' is not a rigid transform"):
        load_scene(tmp_path)
    data = dict(good, image_size=[16, "12"])
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match=r"001.json: 'image_size'\[1\] must be a number"):
        load_scene(tmp_path)


def test_panoptic_calibration_is_checked(tmp_path: Path) -> None:
    metas = write_panoptic(tmp_path)
    meta = metas["train_meta.json"]
    meta["k"][1][0][0][0] = "20.0"
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"train_meta.json: 'k'\[1\]\[0\]\[0\]\[0\] must be a"):
        load_scene(tmp_path)
    meta["k"][1][0][0][0] = 20.0
    meta["w2c"][2][1][0][1] = 0.3  # shear
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(
        DatasetError,
        match=r"train_meta.json: timestep 2 camera 1 \(1/000002.jpg\) 'w2c' is not a rigid",
    ):
        load_scene(tmp_path)
    meta["w2c"][2][1][0][1] = 0.0
    meta["w"] = "16"
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"train_meta.json: 'w' must be a number"):
        load_scene(tmp_path)


def test_colmap_zero_quaternion_is_refused(tmp_path: Path) -> None:
    pytest.importorskip("pycolmap")
    write_colmap(tmp_path, n=3, text=True)
    frames = tmp_path / "sparse" / "0" / "frames.txt"
    # pycolmap >= 3.12 keeps the poses in frames.txt (ID, RIG_ID, QW..), older ones in
    # images.txt (ID, QW..): zero the quaternion wherever this version wrote it.
    quat = slice(2, 6)
    if not frames.exists():
        frames, quat = tmp_path / "sparse" / "0" / "images.txt", slice(1, 5)
    lines = []
    for line in frames.read_text().splitlines():
        parts = line.split()
        if len(parts) >= 8 and not line.startswith("#") and parts[0] == "2":
            parts[quat] = ["0", "0", "0", "0"]
        lines.append(" ".join(parts) if parts else line)
    frames.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"image 'frame_00\d.png' pose has a zero rotation"):
        load_scene(tmp_path)
