"""Dynamic-3DGS Panoptic loader: OpenCV cameras as stored, per-timestep times, binary masks,
and clear errors for malformed metadata."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from support import SHARED_DATA
from support.datasets import write_panoptic
from sync4d.data import DatasetError
from sync4d.data.panoptic import load_panoptic

SHARED = SHARED_DATA / "panoptic" / "basketball"


def test_cameras_times_and_masks(tmp_path: Path) -> None:
    write_panoptic(tmp_path)
    scene = load_panoptic(tmp_path)
    assert len(scene.train) == 3 * 2 and len(scene.test) == 3
    assert sorted({f.time for f in scene.train}) == [0.0, 0.5, 1.0]
    # Every camera folder holds the same file names: frame names carry the camera.
    names = [f.name for f in scene.train]
    assert len(set(names)) == len(names) and names[1].startswith("cam")
    f = scene.train[1]
    # w2c is stored in OpenCV axes already: the world origin sits 5 units ahead.
    uv, z = f.camera.project(np.zeros((1, 3)))
    assert z[0] == pytest.approx(5.0)
    assert uv[0] == pytest.approx([20.0 * 0.1 / 5.0 + 8.0, 6.0])
    mask = f.load_mask()
    assert mask.shape == (12, 16) and mask.sum() == 12 and set(np.unique(mask)) == {0, 1}
    assert scene.labels == {0: "background", 1: "foreground"} and scene.has_masks
    assert scene.test[0].mask_path is None
    img = f.load_image()
    assert img.shape == (12, 16, 3)
    half = load_panoptic(tmp_path, resolution_scale=0.5).train[0]
    assert (half.camera.width, half.camera.height) == (8, 6)
    assert half.load_mask().shape == (6, 8)


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda m: m.pop("w2c"), "missing 'w2c'"),
        (lambda m: m["k"].pop(), "'k' must have shape"),
        (lambda m: m["k"][0].pop(), "must be rectangular"),
        (lambda m: m["fn"][1].pop(), "must be rectangular|timestep 1 lists 1 cameras"),
        (lambda m: m["w2c"][0][0][0].__setitem__(0, float("nan")), "NaN or inf"),
    ],
)
def test_malformed_meta_names_the_file(tmp_path: Path, mutate, match) -> None:
    metas = write_panoptic(tmp_path)
    meta = metas["train_meta.json"]
    mutate(meta)
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=match) as e:
        load_panoptic(tmp_path)
    assert "train_meta.json" in str(e.value)


def test_missing_image_is_named(tmp_path: Path) -> None:
    write_panoptic(tmp_path)
    (tmp_path / "ims" / "1" / "000002.jpg").unlink()
    with pytest.raises(DatasetError, match=r"000002.jpg: image file is missing \(timestep 2"):
        load_panoptic(tmp_path)


@pytest.mark.skipif(not SHARED.is_dir(), reason="../shared/data is not present (user clone)")
def test_real_basketball() -> None:
    scene = load_panoptic(SHARED)
    assert len(scene.train) == 40 * 27 and len(scene.test) == 40 * 4
    f = scene.train[0]
    assert f.load_image().shape == (360, 640, 3)
    assert f.load_mask().shape == (360, 640)
