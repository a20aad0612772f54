"""Tiny dataset folders in each loader's layout, written by the tests that load them and by the
tests that need any small dataset on disk (a D-NeRF / Blender one, mostly)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

from support.cameras import look_at_gl, look_at_w2c

if TYPE_CHECKING:
    import pycolmap


def write_blender(root: Path, n: int = 3, size: int = 20, masks: bool = True) -> None:
    """A D-NeRF / Blender dataset: `n` RGBA `size` x `size` frames per split (red, the top half
    transparent) on a circle around the origin, times 0..1, and (`masks`) instance masks with
    a 4x4 square of label 2 ("ball") and labels.json."""
    angle = 0.7
    for split in ("train", "test"):
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i in range(n):
            rgba = np.zeros((size, size, 4), np.uint8)
            rgba[..., 0] = 200
            rgba[..., 3] = 255
            rgba[: size // 2, :, 3] = 0  # top half transparent
            Image.fromarray(rgba, "RGBA").save(root / split / f"r_{i:03d}.png")
            eye = np.array([4.0 * math.cos(i), 4.0 * math.sin(i), 1.0])
            frames.append(
                {
                    "file_path": f"./{split}/r_{i:03d}",
                    "time": i / max(1, n - 1),
                    "transform_matrix": look_at_gl(eye, np.zeros(3)).tolist(),
                }
            )
        (root / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": angle, "frames": frames})
        )
        if masks:
            (root / "masks" / split).mkdir(parents=True, exist_ok=True)
            for i in range(n):
                m = np.zeros((size, size), np.uint8)
                m[5:9, 5:9] = 2
                Image.fromarray(m, "L").save(root / "masks" / split / f"r_{i:03d}.png")
    if masks:
        (root / "masks" / "labels.json").write_text(json.dumps({"0": "background", "2": "ball"}))


def corrupt_blender(root: Path, split: str, fn) -> Path:
    """Apply `fn` to the parsed transforms_<split>.json of a Blender dataset and write it back;
    returns its path."""
    p = root / f"transforms_{split}.json"
    data = json.loads(p.read_text())
    fn(data)
    p.write_text(json.dumps(data))
    return p


#: (width, height) of `write_colmap`'s images.
COLMAP_SIZE = (24, 16)


def write_colmap(
    root: Path,
    n: int = 10,
    model: str = "PINHOLE",
    params: tuple[float, ...] = (20.0, 22.0, 12.5, 7.5),
    text: bool = False,
    sub0: bool = True,
) -> pycolmap.Reconstruction:
    """A tiny COLMAP dataset: `n` images on a circle around the origin and a few 3D points."""
    import pycolmap

    w, h = COLMAP_SIZE
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=w, height=h, params=list(params), camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    (root / "images").mkdir(parents=True, exist_ok=True)
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = np.array([4.0 * math.cos(a), 4.0 * math.sin(a), 1.0 + 0.1 * i])
        pose = pycolmap.Rigid3d(look_at_w2c(eye, np.zeros(3))[:3])
        # Names out of order on purpose: the loader sorts by name.
        name = f"frame_{(i * 7) % n:03d}.png"
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=name, camera_id=1, image_id=i + 1), pose
        )
        Image.fromarray(np.full((h, w, 3), 10 * i, np.uint8)).save(root / "images" / name)
    for xyz, rgb in [((0.1, 0.2, 0.3), (255, 0, 51)), ((-0.5, 0.0, 0.2), (0, 255, 102))]:
        rec.add_point3D(np.array(xyz), pycolmap.Track(), np.array(rgb, np.uint8))
    sparse = root / "sparse" / "0" if sub0 else root / "sparse"
    sparse.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write)(str(sparse))
    return rec


def write_hypernerf(root: Path) -> None:
    """A HyperNeRF (Nerfies) dataset: 4 frames, their cameras, 1x (16x12) and 2x scale
    folders, train ids 000-002 and val id 003, time ids 0, 2, 4, 6."""
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


def write_nerfstudio(root: Path, n: int = 10, split_keys: bool = False) -> dict:
    """A nerfstudio transforms.json with `n` 12x8 frames at times 0, 2, 4, ... (`split_keys`:
    explicit train / test file lists, f3 the test frame). Returns the transforms."""
    (root / "images").mkdir(parents=True, exist_ok=True)
    frames = []
    for i in range(n):
        Image.fromarray(np.full((8, 12, 3), 10 * i, np.uint8)).save(root / f"images/f{i}.png")
        c2w = np.eye(4)
        c2w[:3, 3] = [0.0, 0.0, 3.0]  # OpenGL camera at z = 3 looking down -z at the origin
        frames.append(
            {"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist(), "time": 2.0 * i}
        )
    data = {"fl_x": 10.0, "fl_y": 11.0, "cx": 6.0, "cy": 4.0, "w": 12, "h": 8, "frames": frames}
    if split_keys:
        data["test_filenames"] = ["images/f3.png"]
        data["train_filenames"] = [
            f["file_path"] for f in frames if f["file_path"] != "images/f3.png"
        ]
    (root / "transforms.json").write_text(json.dumps(data))
    return data


def write_panoptic(root: Path, t_count: int = 3, cams: int = 2, w: int = 16, h: int = 12) -> dict:
    """A Dynamic-3DGS Panoptic dataset: `t_count` timesteps of `cams` training cameras (with
    segmentation masks) and test camera 9. Returns the train and test metadata."""
    metas = {}
    for name, cam_ids in (("train_meta.json", list(range(cams))), ("test_meta.json", [9])):
        fns, ks, w2cs = [], [], []
        for t in range(t_count):
            row, krow, wrow = [], [], []
            for c in cam_ids:
                (root / "ims" / str(c)).mkdir(parents=True, exist_ok=True)
                Image.fromarray(np.full((h, w, 3), (40 * c) % 256, np.uint8)).save(
                    root / "ims" / str(c) / f"{t:06d}.jpg"
                )
                if name == "train_meta.json":
                    (root / "seg" / str(c)).mkdir(parents=True, exist_ok=True)
                    m = np.zeros((h, w), bool)
                    m[2:5, 3:7] = True
                    Image.fromarray(m).save(root / "seg" / str(c) / f"{t:06d}.png")
                row.append(f"{c}/{t:06d}.jpg")
                krow.append([[20.0, 0, w / 2], [0, 21.0, h / 2], [0, 0, 1]])
                m4 = np.eye(4)
                m4[:3, 3] = [0.1 * c, 0.0, 5.0]
                wrow.append(m4.tolist())
            fns.append(row)
            ks.append(krow)
            w2cs.append(wrow)
        meta = {"w": w, "h": h, "k": ks, "w2c": w2cs, "fn": fns, "cam_id": [cam_ids] * t_count}
        (root / name).write_text(json.dumps(meta))
        metas[name] = meta
    return metas
