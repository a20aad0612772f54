"""Checkpoints: one safetensors file holding every tensor a trainer's `state()` gives (canonical
Gaussians, D_theta weights, Adam moments, densification statistics; in Phase 2 also M_phi, its
Adam moments, the object labels, the residual EMA and the motion export) and a JSON header
(format version, the trainer's settings with its kind "sync4d.phase1" or "sync4d.phase2", and
the run's settings and cameras under "run"). The file format is all this module knows: each
phase gives its own state and rebuilds from it (`Phase1Trainer.from_state`,
`DeformableGaussians.from_state`).

Written atomically (a unique temporary file, fsync, rename, fsync of the folder), so an
interrupted or failed write never replaces the last good checkpoint. The standalone Rust
renderer reads the same file (docs/run-folder.md).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import load_file, save_file

from sync4d.data.scene import Scene
from sync4d.errors import Sync4dError
from sync4d.files import write_atomic
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase1.plugin import CheckpointKind

__all__ = [
    "CheckpointError",
    "CheckpointKind",
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


class CheckpointError(Sync4dError, ValueError):
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
    "run") to `path` atomically (`sync4d.files.write_atomic`: a failed write raises
    `WriteFailed` and leaves the previous checkpoint in place)."""
    path = Path(path)
    header = {"format_version": FORMAT_VERSION, **meta}
    if extra:
        header["run"] = extra
    tensors = {k: v.contiguous() for k, v in tensors.items()}
    metadata = {"sync4d": json.dumps(header)}
    write_atomic(path, lambda tmp: save_file(tensors, str(tmp), metadata=metadata))
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
    try:
        meta = json.loads(header["sync4d"])
    except ValueError as e:
        raise CheckpointError(path, f"the header's sync4d metadata is not JSON ({e})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(path, "the header's sync4d metadata is not a JSON object")
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(path, f"unsupported format version {meta.get('format_version')}")
    _check_header(path, meta)
    for name, t in tensors.items():
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise CheckpointError(path, f"tensor '{name}' contains NaN or inf")
    return tensors, meta


#: The trainers whose checkpoints this format holds.
KINDS = tuple(k.value for k in CheckpointKind)


def _check_header(path: Path, meta: dict) -> None:
    """The header's kind and iteration counters are what a trainer can continue from."""
    kind = meta.get("kind", "sync4d.phase1")
    if kind not in KINDS:
        raise CheckpointError(path, f"unknown checkpoint kind {kind!r} (expected {KINDS})")
    for key, low in (("iteration", 0), ("total_iterations", 1)):
        v = meta.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < low):
            raise CheckpointError(path, f"header field '{key}' must be an integer >= {low}, "
                                  f"got {v!r}")  # fmt: skip
    run = meta.get("run", {})
    if not isinstance(run, dict):
        raise CheckpointError(path, "header field 'run' must be a JSON object")
    seconds = run.get("train_seconds", 0.0)
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not seconds >= 0:
        raise CheckpointError(path, f"header field 'run.train_seconds' must be a number >= 0, "
                              f"got {seconds!r}")  # fmt: skip


def checkpoint_kind(path: Path) -> CheckpointKind | None:
    """The kind of an existing checkpoint, None when absent."""
    if not path.exists():
        return None
    return CheckpointKind(read_checkpoint(path)[1].get("kind", CheckpointKind.PHASE1))


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
