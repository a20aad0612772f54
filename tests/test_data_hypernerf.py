"""HyperNeRF loader on a small fixture: Nerfies cameras, times, scale folders, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from sync4d.data import DatasetError, load_scene
from sync4d.data.hypernerf import load_hypernerf


def _write(root: Path) -> None:
    ids = [f"{i:03d}" for i in range(4)]
    (root / "camera").mkdir(parents=True)
    for scale, (w, h) in (("1x", (16, 12)), ("2x", (8, 6))):
        (root / "rgb" / scale).mkdir(parents=True)
        for i in ids:
            Image.fromarray(np.full((h, w, 3), 100, np.uint8)).save(
                root / "rgb" / scale / f"{i}.png"
            )
    for k, i in enumerate(ids):
        cam = {
            "orientation": np.eye(3).tolist(),
            "position": [0.0, 0.0, -4.0 - k],
            "focal_length": 20.0,
            "pixel_aspect_ratio": 1.0,
            "principal_point": [8.0, 6.0],
            "image_size": [16, 12],
        }
        (root / "camera" / f"{i}.json").write_text(json.dumps(cam))
    (root / "dataset.json").write_text(
        json.dumps({"ids": ids, "train_ids": ids[:3], "val_ids": ids[3:]})
    )
    (root / "metadata.json").write_text(
        json.dumps({i: {"time_id": 2 * k} for k, i in enumerate(ids)})
    )


def test_cameras_times_and_scale_folders(tmp_path: Path) -> None:
    _write(tmp_path)
    scene = load_scene(tmp_path)
    assert len(scene.train) == 3 and len(scene.test) == 1
    assert [f.time for f in scene.train] == pytest.approx([0.0, 1 / 3, 2 / 3])
    uv, z = scene.train[1].camera.project(np.array([[0.5, 0.0, 0.0]]))
    assert z[0] == pytest.approx(5.0) and uv[0] == pytest.approx([8.0 + 20.0 * 0.1, 6.0])
    half = load_hypernerf(tmp_path, resolution_scale=0.5)
    f = half.train[0]
    assert f.image_path.parent.name == "2x"
    assert (f.camera.width, f.camera.height) == (8, 6) and f.camera.fx == pytest.approx(10.0)
    assert f.load_image().shape == (6, 8, 3)


def test_errors_name_the_file(tmp_path: Path) -> None:
    _write(tmp_path)
    (tmp_path / "metadata.json").write_text(json.dumps({"000": {}}))
    with pytest.raises(DatasetError, match="metadata.json: id '000' has no 'time_id'"):
        load_hypernerf(tmp_path)
    _write(tmp_path / "b")
    cam = tmp_path / "b" / "camera" / "001.json"
    data = json.loads(cam.read_text())
    del data["focal_length"]
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="001.json: missing camera field 'focal_length'"):
        load_hypernerf(tmp_path / "b")
    _write(tmp_path / "c")
    (tmp_path / "c" / "rgb" / "1x" / "002.png").unlink()
    with pytest.raises(DatasetError, match="002.png: image file is missing"):
        load_hypernerf(tmp_path / "c")
