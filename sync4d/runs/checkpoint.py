"""Checkpoints: one safetensors file holding every tensor a trainer's `state()` gives (canonical
Gaussians, D_theta weights, Adam moments, densification statistics; in Phase 2 also M_phi, its
Adam moments, the object labels, the residual EMA and the motion export) and a JSON header
(format version, the trainer's settings with its kind "sync4d.phase1" or "sync4d.phase2", and
the run's settings and cameras under "run"). The file format is all this module knows: each
phase gives its own state and rebuilds from it (`Phase1Trainer.from_state`,
`DeformableGaussians.from_state`).

Written atomically (temporary file, then rename), so an interrupted write never replaces the
last good checkpoint. The standalone Rust renderer reads the same file (docs/run-folder.md).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from sync4d.data.scene import Scene
from sync4d.phase1.gaussians import DeformableGaussians

__all__ = [
    "CheckpointError",
    "FORMAT_VERSION",
    "camera_records",
    "checkpoint_kind",
    "load_model",
    "read_checkpoint",
    "save_checkpoint",
    "state_errors",
    "write_checkpoint",
]

FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """An unreadable, truncated or inconsistent checkpoint; the message names the file."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")


class HasState(Protocol):
    """What `save_checkpoint` needs of a trainer."""

    def state(self) -> tuple[dict[str, torch.Tensor], dict]: ...


def camera_records(scene: Scene) -> list[dict]:
    """Every train and test camera of `scene` as JSON-ready records (viewmat row-major 4x4
    world-to-camera, OpenCV axes; intrinsics in pixels; frame time), for renderers that read a
    checkpoint without the dataset."""
    out = []
    for split, frames in (("train", scene.train), ("test", scene.test)):
        for f in frames:
            c = f.camera
            out.append(
                {
                    "split": split,
                    "name": f.name,
                    "time": float(f.time),
                    "viewmat": [float(v) for v in c.viewmat.reshape(-1)],
                    "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                    "width": c.width, "height": c.height,
                }  # fmt: skip
            )
    return out


def write_checkpoint(
    path: str | Path, tensors: dict[str, torch.Tensor], meta: dict, extra: dict | None = None
) -> Path:
    """Write `tensors` and the JSON header `meta` (with the format version, and `extra` under
    "run") to `path` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"format_version": FORMAT_VERSION, **meta}
    if extra:
        header["run"] = extra
    tmp = path.with_name(path.name + ".tmp")
    save_file(
        {k: v.contiguous() for k, v in tensors.items()},
        str(tmp),
        metadata={"sync4d": json.dumps(header)},
    )
    os.replace(tmp, path)
    return path


def save_checkpoint(trainer: HasState, path: str | Path, extra: dict | None = None) -> Path:
    """Write `trainer.state()` to `path` atomically; `extra` (JSON-serialisable: run settings,
    cameras) is stored in the header under "run"."""
    tensors, meta = trainer.state()
    return write_checkpoint(path, tensors, meta, extra)


def read_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict]:
    """Every tensor and the header of the checkpoint at `path`, checked: a readable sync4d
    file of this format version whose floating-point tensors are all finite."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(path, "checkpoint file is missing")
    try:
        tensors = load_file(str(path))
        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError) as e:
        raise CheckpointError(path, f"not a readable safetensors checkpoint ({e})") from None
    if "sync4d" not in header:
        raise CheckpointError(path, "no sync4d metadata in the header (not a sync4d checkpoint)")
    meta = json.loads(header["sync4d"])
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(path, f"unsupported format version {meta.get('format_version')}")
    for name, t in tensors.items():
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise CheckpointError(path, f"tensor '{name}' contains NaN or inf")
    return tensors, meta


def checkpoint_kind(path: Path) -> str | None:
    """"sync4d.phase1" or "sync4d.phase2" for an existing checkpoint, None when absent."""
    if not path.exists():
        return None
    return read_checkpoint(path)[1].get("kind", "sync4d.phase1")


@contextmanager
def state_errors(path: Path) -> Iterator[None]:
    """Turn the KeyError (a missing tensor or field) and ValueError (one that does not fit) of
    rebuilding something from the checkpoint at `path` into a `CheckpointError` naming it."""
    try:
        yield
    except CheckpointError:
        raise
    except KeyError as e:
        raise CheckpointError(path, f"missing tensor or field {e}") from None
    except ValueError as e:
        raise CheckpointError(path, str(e)) from None


def load_model(path: str | Path, near: float | None = None) -> tuple[DeformableGaussians, dict]:
    """The Phase 1 model stored in a checkpoint (`near` replaces its near plane), and the
    checkpoint's header."""
    path = Path(path)
    tensors, meta = read_checkpoint(path)
    with state_errors(path):
        return DeformableGaussians.from_state(tensors, meta, near), meta
