"""COLMAP loader (via pycolmap): poses and intrinsics against COLMAP's own projection, times,
splits, points, masks, resolution scaling, and one clear error per malformed input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support.datasets import COLMAP_SIZE, write_colmap
from sync4d.data import DatasetError, load_scene
from sync4d.data.colmap import load_colmap

pycolmap = pytest.importorskip("pycolmap")

W, H = COLMAP_SIZE


def _names(frames) -> list[str]:
    return [f.image_path.name for f in frames]


def test_loads_with_every_8th_split_and_index_times(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=10)
    scene = load_colmap(tmp_path)
    assert scene.name == tmp_path.name
    assert len(scene.train) + len(scene.test) == 10
    assert _names(scene.test) == ["frame_000.png", "frame_008.png"]
    assert "frame_001.png" in _names(scene.train) and len(scene.train) == 8
    frames = sorted(scene.train + scene.test, key=lambda f: f.image_path.name)
    assert [f.time for f in frames] == pytest.approx([i / 9 for i in range(10)])
    assert scene.labels is None and not scene.has_masks
    img = frames[0].load_image()
    assert img.shape == (H, W, 3) and img.dtype == np.float32


def test_text_model_in_sparse_and_explicit_split_and_times(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=5, text=True, sub0=False)
    (tmp_path / "test_images.txt").write_text("frame_003.png\n\n")
    times = {f"frame_{i:03d}.png": 10.0 + 2.0 * i for i in range(5)}
    (tmp_path / "times.json").write_text(json.dumps(times))
    scene = load_colmap(tmp_path)
    assert _names(scene.test) == ["frame_003.png"]
    assert _names(scene.train) == [
        "frame_000.png",
        "frame_001.png",
        "frame_002.png",
        "frame_004.png",
    ]
    assert [f.time for f in scene.train] == pytest.approx([0.0, 0.25, 0.5, 1.0])
    assert scene.test[0].time == pytest.approx(0.75)
    # Times already in [0, 1] are kept as they are.
    (tmp_path / "times.json").write_text(json.dumps({k: 0.1 * i for i, k in enumerate(times)}))
    scene = load_colmap(tmp_path)
    assert [f.time for f in scene.train] == pytest.approx([0.0, 0.1, 0.2, 0.4])


@pytest.mark.parametrize(
    "model,params",
    [
        ("PINHOLE", (20.0, 22.0, 12.5, 7.5)),
        ("SIMPLE_PINHOLE", (21.0, 11.0, 8.0)),
        ("SIMPLE_RADIAL", (21.0, 11.0, 8.0, 0.0)),
        ("OPENCV", (20.0, 22.0, 12.5, 7.5, 0.0, 0.0, 0.0, 0.0)),
    ],
)
def test_known_points_land_on_colmaps_own_projection(
    tmp_path: Path, model: str, params: tuple[float, ...]
) -> None:
    rec = write_colmap(tmp_path, n=6, model=model, params=params)
    scene = load_colmap(tmp_path)
    by_name = {im.name: im for im in rec.images.values()}
    rng = np.random.default_rng(0)
    for frame in scene.train + scene.test:
        im = by_name[frame.image_path.name]
        pts = rng.normal(size=(8, 3)) * 0.5
        uv, z = frame.camera.project(pts)
        expected = np.stack([im.project_point(p) for p in pts])
        assert np.allclose(uv, expected, atol=1e-9)
        cam_pts = im.cam_from_world() * pts
        assert np.allclose(z, cam_pts[:, 2]) and (z > 0).all()
    # Explicitly: pixel centres at +0.5 like ours, so (cx, cy) is the principal point as given.
    cam = scene.train[0].camera
    assert (cam.width, cam.height) == (W, H)
    if model == "PINHOLE":
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == (20.0, 22.0, 12.5, 7.5)


def test_points_and_colours(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=3)
    scene = load_colmap(tmp_path)
    assert scene.points.dtype == np.float64 and scene.points.shape == (2, 3)
    assert np.allclose(scene.points, [[0.1, 0.2, 0.3], [-0.5, 0.0, 0.2]])
    assert scene.point_colors.dtype == np.float32
    assert np.allclose(scene.point_colors, [[1.0, 0.0, 0.2], [0.0, 1.0, 0.4]])


def test_resolution_scale_halves_intrinsics(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=3)
    full = load_colmap(tmp_path).train[0]
    half = load_colmap(tmp_path, resolution_scale=0.5).train[0]
    c, f = half.camera, full.camera
    assert (c.width, c.height) == (W // 2, H // 2)
    assert (c.fx, c.fy, c.cx, c.cy) == pytest.approx((f.fx / 2, f.fy / 2, f.cx / 2, f.cy / 2))
    assert np.array_equal(c.viewmat, f.viewmat)
    assert half.native_size == (W, H)
    assert half.load_image().shape == (H // 2, W // 2, 3)
    with pytest.raises(DatasetError, match="resolution scale must be in"):
        load_colmap(tmp_path, resolution_scale=1.5)


def test_masks_and_labels(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=3)
    (tmp_path / "masks").mkdir()
    for i in range(3):
        m = np.zeros((H, W), np.uint8)
        m[2:6, 3:9] = 1
        Image.fromarray(m, "L").save(tmp_path / "masks" / f"frame_{i:03d}.png")
    (tmp_path / "masks" / "labels.json").write_text(json.dumps({"0": "background", "1": "ball"}))
    scene = load_colmap(tmp_path, resolution_scale=0.5)
    assert scene.has_masks and scene.labels == {0: "background", 1: "ball"}
    mask = scene.train[0].load_mask()
    assert mask.shape == (H // 2, W // 2) and set(np.unique(mask)) == {0, 1}
    # A mask of the wrong size is reported when the frame loads it.
    Image.fromarray(np.zeros((5, 7), np.uint8), "L").save(tmp_path / "masks/frame_001.png")
    scene = load_colmap(tmp_path)
    with pytest.raises(DatasetError, match="frame_001.png: mask is 7x5 but the dataset's images"):
        scene.train[0].load_mask()
    (tmp_path / "masks/frame_002.png").unlink()
    with pytest.raises(DatasetError, match="frame_002.png: mask for frame_002.png is missing"):
        load_colmap(tmp_path)


def _rm_images(root: Path) -> None:
    for p in (root / "images").iterdir():
        p.unlink()
    (root / "images").rmdir()


def _bad_text_model(root: Path) -> None:
    """A text model whose camera line has too few parameters (COLMAP's check fails).

    (A truncated .bin is not used: pycolmap may read a garbage count from it and spin.)"""
    sparse = root / "sparse" / "0"
    for p in sparse.iterdir():
        p.unlink()
    (sparse / "cameras.txt").write_text("1 PINHOLE 24 16 20 22\n")
    (sparse / "images.txt").write_text("")
    (sparse / "points3D.txt").write_text("")


@pytest.mark.parametrize(
    "corrupt,match",
    [
        (_rm_images, r"images: image folder is missing"),
        (
            lambda r: [p.unlink() for p in (r / "sparse" / "0").iterdir()],
            r"sparse: COLMAP sparse model is missing",
        ),
        (_bad_text_model, r"sparse[/\\]0: pycolmap cannot read the sparse model"),
        (
            lambda r: (r / "images/frame_004.png").unlink(),
            r"frame_004.png: image file is missing \(listed in .*sparse[/\\]0\)",
        ),
        (
            lambda r: (r / "times.json").write_text(json.dumps({"frame_000.png": 0.0})),
            r"times.json: no time for image 'frame_001.png'",
        ),
        (
            lambda r: (r / "times.json").write_text(
                json.dumps({f"frame_{i:03d}.png": "nan" for i in range(10)})
            ),
            r"times.json: the time of 'frame_000.png' must be a number, got a string \('nan'\)",
        ),
        (
            lambda r: (r / "test_images.txt").write_text("frame_001.png\nnope.png\n"),
            r"test_images.txt: line 2 names 'nope.png', which is not a registered image",
        ),
        (
            lambda r: (r / "masks").mkdir() or (r / "masks" / "labels.json").write_text("[1]"),
            r"frame_000.png: mask for frame_000.png is missing",
        ),
    ],
)
def test_malformed_inputs_name_the_file(tmp_path: Path, corrupt, match) -> None:
    write_colmap(tmp_path, n=10)
    corrupt(tmp_path)
    with pytest.raises(DatasetError, match=match):
        load_colmap(tmp_path)


def test_distorted_camera_is_refused(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=3, model="OPENCV", params=(20.0, 22.0, 12.5, 7.5, 0.1, 0.0, 0.0, 0.0))
    with pytest.raises(
        DatasetError, match=r"sparse[/\\]0: camera 1 \(OPENCV\) has lens distortion"
    ) as e:
        load_colmap(tmp_path)
    assert "colmap image_undistorter" in str(e.value)


def test_unsupported_camera_model_is_refused(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=3, model="OPENCV_FISHEYE", params=(20.0, 22.0, 12.5, 7.5, 0, 0, 0, 0))
    with pytest.raises(DatasetError, match="OPENCV_FISHEYE.*colmap image_undistorter"):
        load_colmap(tmp_path)


def test_no_registered_images(tmp_path: Path) -> None:
    (tmp_path / "images").mkdir()
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[20, 20, 12, 8], camera_id=1)
    )
    (tmp_path / "sparse").mkdir()
    rec.write(str(tmp_path / "sparse"))
    with pytest.raises(DatasetError, match="sparse: the sparse model has no registered images"):
        load_colmap(tmp_path)


def test_missing_pycolmap_is_explained(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    write_colmap(tmp_path, n=3)
    monkeypatch.setitem(sys.modules, "pycolmap", None)  # makes `import pycolmap` fail
    with pytest.raises(DatasetError, match="pip install pycolmap"):
        load_colmap(tmp_path)


def test_load_scene_detects_colmap(tmp_path: Path) -> None:
    write_colmap(tmp_path, n=9)
    scene = load_scene(tmp_path, resolution_scale=0.5)
    assert len(scene.train) == 7 and len(scene.test) == 2
    assert scene.train[0].camera.width == W // 2
    assert scene.points is not None
