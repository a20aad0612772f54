"""Pick the loader for a dataset directory by the files it contains."""

from __future__ import annotations

from pathlib import Path

from sync4d.data.scene import DatasetError, Scene, check_scene


def load_scene(root: str | Path, resolution_scale: float = 1.0, test_split: str = "test") -> Scene:
    """Load a dataset directory in any supported layout (`test_split` "val" picks D-NeRF's
    validation frames as the test split): D-NeRF / Blender
    (`transforms_train.json`), Dynamic-3DGS Panoptic (`train_meta.json`), HyperNeRF
    (`dataset.json` + `metadata.json`), nerfstudio with per-frame time (`transforms.json`) or
    COLMAP (`sparse/` + `images/`, read with pycolmap). Every image and mask header is then
    checked (`check_scene`), so a bad file fails here, before any training."""
    scene = _load(Path(root), resolution_scale, test_split)
    check_scene(scene)
    return scene


def _load(root: Path, resolution_scale: float, test_split: str) -> Scene:
    if root.is_file():
        raise DatasetError(
            root, "is a file, not a dataset folder; for a video (or a folder of photos) make a "
            f"dataset first: sync4d process {root} --out DATA, then sync4d fit DATA",
        )  # fmt: skip
    if not root.is_dir():
        raise DatasetError(root, "dataset directory does not exist")
    if (root / "transforms_train.json").exists():
        from sync4d.data.blender import load_blender

        return load_blender(root, resolution_scale, test_split)
    if test_split != "test":
        raise DatasetError(
            root, f"test split '{test_split}' is only available for D-NeRF/Blender datasets"
        )
    if (root / "train_meta.json").exists():
        from sync4d.data.panoptic import load_panoptic

        return load_panoptic(root, resolution_scale)
    if (root / "dataset.json").exists() and (root / "metadata.json").exists():
        from sync4d.data.hypernerf import load_hypernerf

        return load_hypernerf(root, resolution_scale)
    if (root / "transforms.json").exists():
        from sync4d.data.nerfstudio import load_nerfstudio

        return load_nerfstudio(root, resolution_scale)
    if (root / "sparse").exists():
        from sync4d.data.colmap import load_colmap

        return load_colmap(root, resolution_scale)
    raise DatasetError(
        root,
        "unrecognised dataset layout: expected transforms_train.json (D-NeRF/Blender), "
        "train_meta.json (Dynamic-3DGS Panoptic), dataset.json + metadata.json (HyperNeRF), "
        "transforms.json (nerfstudio, e.g. from sync4d process) or sparse/ + images/ (COLMAP)",
    )
