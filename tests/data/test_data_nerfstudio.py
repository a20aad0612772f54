"""nerfstudio transforms.json with per-frame time, and layout detection."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from support.datasets import write_nerfstudio
from sync4d.data import DatasetError, load_scene
from sync4d.data.nerfstudio import load_nerfstudio


def test_cameras_times_split(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path)
    scene = load_nerfstudio(tmp_path)
    assert len(scene.test) == 2 and len(scene.train) == 8  # every 8th frame held out
    times = sorted(f.time for f in scene.train + scene.test)
    assert times[0] == 0.0 and times[-1] == 1.0  # normalised from [0, 18]
    cam = scene.train[0].camera
    # A point right of the origin (+x world) lands right of the principal point, and one
    # above it (+y world, OpenGL up) lands above it (smaller row).
    uv, z = cam.project(np.array([[0.3, 0.0, 0.0], [0.0, 0.3, 0.0]]))
    assert z == pytest.approx([3.0, 3.0])
    assert uv[0] == pytest.approx([6.0 + 10.0 * 0.1, 4.0])
    assert uv[1] == pytest.approx([6.0, 4.0 - 11.0 * 0.1])
    assert isinstance(load_scene(tmp_path).train[0].camera.fx, float)


def test_explicit_split(tmp_path: Path) -> None:
    write_nerfstudio(tmp_path, split_keys=True)
    scene = load_nerfstudio(tmp_path)
    assert [f.image_path.name for f in scene.test] == ["f3.png"]
    assert len(scene.train) == 9


def test_errors(tmp_path: Path) -> None:
    data = write_nerfstudio(tmp_path)
    del data["frames"][4]["time"]
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="transforms.json: 1 frames have no 'time'"):
        load_nerfstudio(tmp_path)
    data = write_nerfstudio(tmp_path)
    del data["fl_y"]
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="frame 0 has no 'fl_y'"):
        load_nerfstudio(tmp_path)
    data = write_nerfstudio(tmp_path)
    data["frames"][2]["transform_matrix"] = [[math.nan] * 4] * 4
    (tmp_path / "transforms.json").write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="frame 2 'transform_matrix' must be a finite 4x4"):
        load_nerfstudio(tmp_path)


def test_unknown_layout_is_explained(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="unrecognised dataset layout"):
        load_scene(tmp_path)
