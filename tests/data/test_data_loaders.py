"""The loader registry (sync4d.data.loaders): each layout named once, the detection order the
docs state, one shared preamble, and a loader registered from outside picked by load_scene."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from support import ROOT
from sync4d.config import RunConfig
from sync4d.data import DatasetError, load_scene
from sync4d.data import loaders as reg
from sync4d.data.scene import Camera, Frame, Scene
from sync4d.settings import allowed

ORDER = ("blender", "panoptic", "hypernerf", "nerfstudio", "colmap")


def test_each_loader_is_named_once_in_the_documented_order() -> None:
    assert reg.names() == ORDER
    assert len({lo.title for lo in reg.loaders()}) == len(ORDER)
    assert [lo.name for lo in reg.BUILTIN] == list(ORDER)
    # docs/datasets.md lists the layouts in the same order (its table is generated from them).
    rows = [line for line in (ROOT / "docs" / "datasets.md").read_text().splitlines()
            if line.startswith("| ") and not line.startswith("| layout")]  # fmt: skip
    titles = [row.split(" | ")[0][2:] for row in rows[: len(ORDER)]]
    assert [t.split(" (")[0] for t in titles] == [lo.title for lo in reg.loaders()]
    with pytest.raises(ValueError, match="already registered"):
        reg.register(reg.get("colmap"))
    with pytest.raises(KeyError, match="loaders: blender, panoptic"):
        reg.get("nope")


def test_every_reader_resolves_and_loaders_import_no_other_loader() -> None:
    modules = {lo.read.partition(":")[0] for lo in reg.BUILTIN if isinstance(lo.read, str)}
    assert len(modules) == len(ORDER)
    for lo in reg.loaders():
        assert callable(lo.reader())
    for module in modules:
        path = ROOT / (module.replace(".", "/") + ".py")
        imported = {n.module for n in ast.walk(ast.parse(path.read_text()))
                    if isinstance(n, ast.ImportFrom)}  # fmt: skip
        assert not imported & (modules - {module}), f"{module} imports another loader"


@pytest.mark.parametrize(
    ("markers", "expected"),
    [
        (["transforms_train.json", "transforms.json", "train_meta.json", "sparse/"], "blender"),
        (["train_meta.json", "dataset.json", "metadata.json", "transforms.json"], "panoptic"),
        (["dataset.json", "metadata.json", "transforms.json", "sparse/"], "hypernerf"),
        (["dataset.json", "transforms.json", "sparse/"], "nerfstudio"),
        (["metadata.json", "sparse/"], "colmap"),
    ],
)
def test_detection_order_decides_between_markers(
    tmp_path: Path, markers: list[str], expected: str
) -> None:
    for m in markers:
        (tmp_path / m.rstrip("/")).mkdir() if m.endswith("/") else (tmp_path / m).write_text("{}")
    assert reg.detect(tmp_path).name == expected


def test_shared_preamble(tmp_path: Path) -> None:
    (tmp_path / "train_meta.json").write_text("{}")
    with pytest.raises(DatasetError, match="'val' is only available for D-NeRF/Blender datasets"):
        load_scene(tmp_path, test_split="val")
    with pytest.raises(DatasetError, match=r"resolution scale must be in \(0, 1\], got 0"):
        load_scene(tmp_path, resolution_scale=0.0)
    with pytest.raises(DatasetError, match="is a file, not a dataset folder"):
        load_scene(tmp_path / "train_meta.json")
    with pytest.raises(DatasetError, match="dataset directory does not exist"):
        reg.get("hypernerf").load(tmp_path / "absent")
    assert reg.offered_splits() == ("test", "val")
    assert allowed(RunConfig.__dataclass_fields__["test_split"]).choices == ("test", "val")


def test_a_registered_loader_is_picked_then_forgotten(tmp_path: Path) -> None:
    Image.fromarray(np.zeros((4, 6, 3), np.uint8)).save(tmp_path / "toy.png")
    (tmp_path / "toy.json").write_text("{}")
    (tmp_path / "transforms.json").write_text("{}")  # nerfstudio's marker too
    seen: list[tuple[Path, float, str]] = []

    def read(root: Path, resolution_scale: float, test_split: str) -> Scene:
        seen.append((root, resolution_scale, test_split))
        cam = Camera(np.eye(4), 5.0, 5.0, 3.0, 2.0, 6, 4)
        return Scene("toy", [Frame(root / "toy.png", cam, 0.0)], [])

    toy = reg.Loader("toy", "Toy", ("toy.json",), read, note="a test's")
    reg.register(toy, before="nerfstudio")
    try:
        assert reg.names() == ("blender", "panoptic", "hypernerf", "toy", "nerfstudio", "colmap")
        scene = load_scene(str(tmp_path), 0.5)
        assert scene.name == "toy" and seen == [(tmp_path, 0.5, "test")]
        empty = tmp_path / "empty"
        empty.mkdir()
        with pytest.raises(DatasetError, match=r"\(HyperNeRF\), toy.json \(Toy, a test's\), "):
            load_scene(empty)
    finally:
        assert reg.unregister("toy") is toy
    assert reg.names() == ORDER
    with pytest.raises(DatasetError, match="missing or empty 'frames' list"):
        load_scene(tmp_path)  # nerfstudio's now


def test_the_registry_imports_neither_numpy_nor_a_loader() -> None:
    code = (
        "import sys, sync4d.data.loaders as r; r.names(); r.titles(); "
        "assert not {'numpy', 'sync4d.data.blender', 'sync4d.data.colmap'} & set(sys.modules)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
    assert done.returncode == 0, done.stderr
