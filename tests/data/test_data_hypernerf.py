"""HyperNeRF loader on a small fixture: Nerfies cameras, times, scale folders, errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from support.datasets import write_hypernerf
from sync4d.data import DatasetError, load_scene
from sync4d.data.hypernerf import load_hypernerf


def test_cameras_times_and_scale_folders(tmp_path: Path) -> None:
    write_hypernerf(tmp_path)
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
    write_hypernerf(tmp_path)
    (tmp_path / "metadata.json").write_text(json.dumps({"000": {}}))
    with pytest.raises(DatasetError, match="metadata.json: id '000' has no 'time_id'"):
        load_hypernerf(tmp_path)
    write_hypernerf(tmp_path / "b")
    cam = tmp_path / "b" / "camera" / "001.json"
    data = json.loads(cam.read_text())
    del data["focal_length"]
    cam.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="001.json: missing camera field 'focal_length'"):
        load_hypernerf(tmp_path / "b")
    write_hypernerf(tmp_path / "c")
    (tmp_path / "c" / "rgb" / "1x" / "002.png").unlink()
    with pytest.raises(DatasetError, match="002.png: image file is missing"):
        load_hypernerf(tmp_path / "c")
