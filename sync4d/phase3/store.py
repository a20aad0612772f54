"""The language field as the run folder keeps it: `Field` (arrays and header), its atomic
save into ``RUN/phase3`` and `load_field`, which checks it. numpy and safetensors only, so a
query loads a field without torch (`python -m sync4d query` starts in well under a second).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file, save_file

from sync4d.errors import Sync4dError
from sync4d.files import file_sha256, write_atomic, write_text_atomic
from sync4d.runs.names import CHECKPOINT_NAME, FIELD_DIR, FIELD_FILE, FIELD_META

__all__ = ["Field", "FieldError", "checkpoint_record", "load_field"]

_VERSION = 1
_ARRAYS = (
    "obs", "observed", "static", "features", "standardised", "ridge", "pred", "sync",
    "visible", "boxes", "gaps", "radius", "centroids",
)  # fmt: skip


class FieldError(Sync4dError, ValueError):
    """A language field that is missing or cannot be used; the message names the file."""


@dataclass
class Field:
    """The language field of a run: K foreground objects (`labels`, `names`), T frames
    (`times`), embeddings of D dimensions.

    Arrays: `obs` [K, T, D] e_obs (zero where unobserved), `observed` [K, T] bool, `static`
    [K, D], `features` [K, T, 28] (Appendix B), `standardised` [K, T, 29], `ridge` [K, 29, D]
    W_k, `pred` [K, T, D] e_hat, `sync` [K, T, D] the blended and smoothed embeddings,
    `visible` [K, T], `boxes` [K, T, 4] crop boxes, `gaps` [K, L, T] robust distances to each
    of `gap_labels`, `radius` [K], `centroids` [K, T, 3] (M_phi's). `meta`: everything else;
    `counts` what the build encoded and skipped (the `Skipped("phase3", ...)` event; empty in a
    field built before the counters); `checkpoint` the run checkpoint it was built from
    (`checkpoint_record`), which `load_field` checks.
    """

    labels: list[int]
    names: list[str]
    times: np.ndarray
    obs: np.ndarray
    observed: np.ndarray
    static: np.ndarray
    features: np.ndarray
    standardised: np.ndarray
    ridge: np.ndarray
    pred: np.ndarray
    sync: np.ndarray
    visible: np.ndarray
    boxes: np.ndarray
    gaps: np.ndarray
    radius: np.ndarray
    centroids: np.ndarray
    gap_labels: list[int]
    views: list[list[str]]
    up: np.ndarray
    right: np.ndarray
    encoder: dict
    config: dict
    timings: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    checkpoint: dict = field(default_factory=dict)

    @property
    def dim(self) -> int:
        """Embedding dimension D."""
        return int(self.static.shape[-1])

    def temporal(self, static_only: bool = False) -> np.ndarray:
        """The per-frame embeddings the query scores [K, T, D]: e_sync, or e_static at every
        frame for the static-only ablation."""
        if static_only:
            return np.repeat(self.static[:, None], len(self.times), axis=1)
        return self.sync

    def unconditioned(self) -> np.ndarray:
        """The per-frame embeddings [K, T, D] of the W = 0 ablation of this field (every
        W_k = 0, observations blended and smoothed with the field's own beta and gamma;
        `sync4d.phase3.field.unconditioned_sync`): e_sync without the kinematic term."""
        from sync4d.phase3.field import unconditioned_sync

        c = self.config
        return unconditioned_sync(self.static, self.obs, self.observed, c.get("beta", 0.65),
                                  c.get("beta_on", "prediction"), c.get("ema_gamma", 0.15))

    def save(self, run_dir: str | Path) -> Path:
        """Write the field into ``run_dir/phase3`` atomically; returns the folder."""
        out = Path(run_dir) / FIELD_DIR
        out.mkdir(parents=True, exist_ok=True)
        arrays = {}
        for name in _ARRAYS:
            a = np.ascontiguousarray(getattr(self, name))
            arrays[name] = a.astype(np.uint8) if a.dtype == bool else a
        arrays["times"] = np.asarray(self.times, dtype=np.float64)
        write_atomic(out / FIELD_FILE, lambda p: save_file(arrays, str(p)))
        meta = {
            "version": _VERSION, "labels": self.labels, "names": self.names,
            "gap_labels": self.gap_labels, "views": self.views, "up": self.up.tolist(),
            "right": self.right.tolist(),
            "encoder": self.encoder, "config": self.config, "timings": self.timings,
            "counts": self.counts, "checkpoint": self.checkpoint,
        }  # fmt: skip
        write_text_atomic(out / FIELD_META, json.dumps(meta, indent=1) + "\n")
        return out


def checkpoint_record(path: str | Path) -> dict:
    """What a field records of the checkpoint at `path` it is built from: its file name and
    SHA-256 (None when there is no such file: a field of a run held in memory)."""
    path = Path(path)
    return {"file": path.name, "sha256": file_sha256(path) if path.is_file() else None}


def _check_checkpoint(run_dir: Path, meta_path: Path, meta: dict) -> None:
    """FieldError unless the field in `meta` was built from the run's current checkpoint."""
    rebuild = f"rebuild it with `python -m sync4d fit --out {run_dir} --phases 3`"
    built = meta.get("checkpoint")
    if not isinstance(built, dict) or "sha256" not in built:
        raise FieldError(f"{meta_path}: this field does not record the checkpoint it was built "
                         f"from (a field of an older sync4d); {rebuild}")  # fmt: skip
    now = checkpoint_record(run_dir / str(built.get("file") or CHECKPOINT_NAME))
    if now["sha256"] != built["sha256"]:
        was, is_ = (str(d)[:12] if d else "none" for d in (built["sha256"], now["sha256"]))
        raise FieldError(
            f"{meta_path}: the field was built from another model (checkpoint sha256 {was}, "
            f"the run's {now['file']} is now {is_}: the run was refit since); {rebuild}"
        )


def load_field(run_dir: str | Path) -> Field:
    """The field saved in ``run_dir/phase3``; FieldError naming the file when it is missing,
    unreadable, inconsistent, or built from another checkpoint than the run's current one."""
    folder = Path(run_dir) / FIELD_DIR
    meta_path, arr_path = folder / FIELD_META, folder / FIELD_FILE
    if not meta_path.is_file() or not arr_path.is_file():
        raise FieldError(
            f"{folder}: no language field in this run; build it with "
            f"`python -m sync4d fit --out {run_dir} --phases 3`"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise FieldError(f"{meta_path}: not a readable field header ({e}); rebuild with "
                         f"`fit --out {run_dir} --phases 3`") from None  # fmt: skip
    try:
        arrays = load_file(str(arr_path))
    except Exception as e:  # noqa: BLE001 - safetensors raises several kinds
        raise FieldError(f"{arr_path}: not a readable safetensors file ({e})") from None
    _check_checkpoint(Path(run_dir), meta_path, meta)
    missing = [n for n in (*_ARRAYS, "times") if n not in arrays]
    if missing or meta.get("version") != _VERSION:
        raise FieldError(f"{arr_path}: field of another version or missing {missing}; "
                         f"rebuild with `fit --out {run_dir} --phases 3`")  # fmt: skip
    k = len(meta["labels"])
    for n in _ARRAYS:
        a = arrays[n]
        if a.shape[:1] != (k,) or (a.dtype.kind == "f" and not np.isfinite(a).all()
                                   and n != "gaps"):  # fmt: skip
            raise FieldError(f"{arr_path}: '{n}' has shape {list(a.shape)} or non-finite "
                             f"values (expected {k} objects)")  # fmt: skip
    kw = {n: arrays[n] for n in _ARRAYS}
    kw["observed"] = kw["observed"].astype(bool)
    return Field(
        labels=[int(x) for x in meta["labels"]], names=list(meta["names"]),
        times=arrays["times"], gap_labels=[int(x) for x in meta["gap_labels"]],
        views=meta["views"], up=np.asarray(meta["up"], dtype=np.float64),
        right=np.asarray(meta["right"], dtype=np.float64),
        encoder=meta["encoder"], config=meta["config"], timings=meta.get("timings", {}),
        counts=meta.get("counts", {}), checkpoint=meta["checkpoint"], **kw,
    )  # fmt: skip
