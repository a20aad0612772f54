"""The run record: what a run folder says about how it was made (``run.json``, and the same
entries in the checkpoint header's "run", which stays consistent with the tensors beside it),
and the checks that continuing a run (`fit --resume`, `fit --phases 2`) makes against it.

The record holds the dataset (its path, whether it is the embedded synthetic scene, and a
fingerprint: frame counts, names, times and poses), the whole resolved config, the command-line
settings it came from, the thread count and the training seconds so far. A continued run takes
its data and settings from the record; a DATA whose fingerprint differs, or a setting that
would change the run, is refused with the difference named. Only the lengths of the phases and
the evaluation / checkpoint cadence may change on `--resume` (they extend a run without changing
what it computes); `--phases 2` may also change every Phase 2 setting (it redoes Phase 2).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shlex
from pathlib import Path
from typing import Any

import numpy as np

from sync4d.config import ConfigError, RunConfig, config_from_dict
from sync4d.data.scene import Scene
from sync4d.runs.checkpoint import read_checkpoint
from sync4d.runs.folder import CHECKPOINT_NAME, RUN_FILE, RunError

__all__ = [
    "CADENCE_KEYS",
    "config_differences",
    "continue_command",
    "dataset_fingerprint",
    "dataset_differences",
    "read_record",
    "recorded_config",
]

#: Settings that never change what a run computes, only how often it reports and saves.
CADENCE_KEYS = ("eval_every", "eval_frames", "checkpoint_every")


def dataset_fingerprint(scene: Scene) -> dict:
    """What identifies `scene`'s data independently of where it lies: its name, train / test
    frame counts, whether it has masks, and a SHA-256 over every frame's name, time and
    world-to-camera pose (rounded to 1e-6)."""
    h = hashlib.sha256()
    for split, frames in (("train", scene.train), ("test", scene.test)):
        for f in frames:
            pose = np.round(np.asarray(f.camera.viewmat, dtype=np.float64), 6) + 0.0
            h.update(f"{split}|{f.name}|{float(f.time):.6f}|".encode())
            h.update(pose.tobytes())
    return {
        "name": scene.name,
        "train": len(scene.train),
        "test": len(scene.test),
        "masks": scene.has_masks,
        "digest": h.hexdigest(),
    }


def dataset_differences(recorded: dict, scene: Scene) -> list[str]:
    """How `scene` differs from the recorded fingerprint, in words (empty: the same data). The
    name (the folder's) is not compared: a dataset moved or renamed is the same dataset."""
    now = dataset_fingerprint(scene)
    out = []
    for key, what in (("train", "train frames"), ("test", "test frames"), ("masks", "masks")):
        if key in recorded and recorded[key] != now[key]:
            out.append(f"{what} {now[key]} against the run's {recorded[key]}")
    if not out and recorded.get("digest") not in (None, now["digest"]):
        out.append("the frames' names, times or camera poses differ")
    return out


def read_record(run_dir: Path) -> dict:
    """The record of the run in `run_dir`: the checkpoint header's "run" entry (written with
    the tensors), else ``run.json``."""
    ckpt = run_dir / CHECKPOINT_NAME
    if ckpt.exists():
        record = read_checkpoint(ckpt)[1].get("run")
        if isinstance(record, dict) and "config" in record:
            return record
    path = run_dir / RUN_FILE
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RunError(f"{run_dir}: the run has no record ({RUN_FILE} is missing)") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise RunError(f"{path}: not a JSON run record ({e})") from None
    if not isinstance(record, dict) or not isinstance(record.get("config"), dict):
        raise RunError(f"{path}: not a run record (no 'config' object)")
    return record


def recorded_config(record: dict, run_dir: Path) -> RunConfig:
    """The run's whole config, rebuilt from its record."""
    try:
        return config_from_dict(record["config"], f"{run_dir / RUN_FILE} config")
    except ConfigError as e:
        raise RunError(f"{e} (was the run written by another sync4d version?)") from None


def _flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(v):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def config_differences(recorded: RunConfig, requested: RunConfig) -> dict[str, tuple]:
    """Every setting whose value differs: dotted key -> (recorded value, requested value)."""
    a, b = _flatten(recorded), _flatten(requested)
    return {k: (a[k], b[k]) for k in a if a[k] != b[k]}


def continue_command(run_dir: Path, record: dict) -> str:
    """The command that continues the run in `run_dir` (its settings come from the record)."""
    data = "" if record.get("embedded") else f" {shlex.quote(str(record['data']))}"
    return f"python -m sync4d fit{data} --out {shlex.quote(str(run_dir))} --resume"
