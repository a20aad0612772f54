"""Building the language field of a Phase 2 run and keeping it in the run folder.

`build_field(run, cfg, encoder)` runs Appendix A's Phase 3 steps on the frozen run: observe
(crops, visibility, residuals: `observe`), encode the crops (`Encoder.encode_images`), the static
anchors, the 28-D kinematics (`kinematics`), per-object standardisation and ridge, prediction,
blend and temporal EMA (`field`). The result is a `Field`, saved as ``RUN/phase3/field.safetensors``
(arrays) and ``RUN/phase3/field.json`` (labels, names, times, crop views, the encoder, the
settings, timings), both written atomically. `load_field(RUN)` reads it back and checks it.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file, save_file

from sync4d.config import Phase3Config
from sync4d.phase3 import field as fm
from sync4d.phase3.encoder import Encoder
from sync4d.phase3.kinematics import Tracks, kinematic_features
from sync4d.phase3.observe import Observations, observe
from sync4d.runs import Run, RunError
from sync4d.runs.files import write_atomic, write_text_atomic

__all__ = [
    "FIELD_DIR",
    "FIELD_FILE",
    "FIELD_META",
    "Field",
    "FieldError",
    "build_field",
    "load_field",
    "up_vector",
]

#: The field's folder inside the run folder.
FIELD_DIR = "phase3"
FIELD_FILE = "field.safetensors"
FIELD_META = "field.json"
_VERSION = 1
_ARRAYS = (
    "obs", "observed", "static", "features", "standardised", "ridge", "pred", "sync",
    "visible", "boxes", "gaps", "radius", "centroids",
)  # fmt: skip


class FieldError(RunError):
    """A language field that is missing or cannot be used; the message names the file."""


@dataclass
class Field:
    """The language field of a run: K foreground objects (`labels`, `names`), T frames
    (`times`), embeddings of D dimensions.

    Arrays: `obs` [K, T, D] e_obs (zero where unobserved), `observed` [K, T] bool, `static`
    [K, D], `features` [K, T, 28] (Appendix B), `standardised` [K, T, 29], `ridge` [K, 29, D]
    W_k, `pred` [K, T, D] e_hat, `sync` [K, T, D] the blended and smoothed embeddings,
    `visible` [K, T], `boxes` [K, T, 4] crop boxes, `gaps` [K, L, T] robust distances to each
    of `gap_labels`, `radius` [K], `centroids` [K, T, 3] (M_phi's). `meta`: everything else.
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
        }  # fmt: skip
        write_text_atomic(out / FIELD_META, json.dumps(meta, indent=1) + "\n")
        return out


def up_vector(run: Run, scene_cameras: list, spec: str = "auto") -> np.ndarray:
    """World up [3] (unit): an axis spec "+z" ..., or "auto": the normalised mean of the
    cameras' up directions (OpenCV camera axes: up is -y), which holds for captures whose
    cameras stand upright around the scene."""
    if spec != "auto":
        v = np.zeros(3)
        v["xyz".index(spec[1])] = 1.0 if spec[0] == "+" else -1.0
        return v
    ups = [-np.asarray(c.viewmat)[1, :3] for c in scene_cameras]
    m = np.mean(ups, axis=0) if ups else np.array([0.0, 0.0, 1.0])
    n = float(np.linalg.norm(m))
    return m / n if n > 1e-6 else np.array([0.0, 0.0, 1.0])


def _tracks(run: Run, obs: Observations, hand: int | None) -> Tracks:
    """M_phi's transforms of the foreground objects with the observed statistics."""
    a, b = run.motion.trajectory()
    sel = obs.labels
    return Tracks(
        times=obs.times, linear=a[sel], offsets=b[sel],
        canonical_centroids=obs.canonical_centroids, residual_mean=obs.residual_mean,
        residual_std=obs.residual_std, rigid_share=obs.rigid_share, visible=obs.visible,
        rigid=bool(run.motion.rigid), hand=hand,
    )  # fmt: skip


def build_field(
    run: Run, cfg: Phase3Config, encoder: Encoder, *, data: str | Path | None = None,
    threads: int | None = None, progress: bool = True,
) -> Field:  # fmt: skip
    """The language field of the Phase 2 run `run` (its dataset from `data` or the folder it
    recorded) with `encoder` and the settings `cfg`."""
    if run.kind != "sync4d.phase2" or run.motion is None:
        raise FieldError(
            f"{run.checkpoint}: Phase 3 needs a Phase 2 run (this checkpoint is {run.kind}); "
            "run `fit RUN --phases 2` first"
        )
    scene = run.scene(data)
    if scene is None:
        raise FieldError(
            f"{run.path}: the dataset it recorded ({run.settings.get('data')}) is gone; "
            "give it with --data DIR"
        )
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    share_eps = float(run.settings.get("config", {}).get("phase2", {}).get("share_eps", 1e-6))
    cams = [fr.camera for fr in scene.train]
    up = up_vector(run, cams, cfg.up)
    obs = observe(
        run, scene, min_visible=cfg.min_visible, min_box=cfg.min_box, margin=cfg.crop_margin,
        percentiles=(cfg.crop_low, cfg.crop_high), share_eps=share_eps, up=up, threads=threads,
        progress=progress,
    )  # fmt: skip
    if not obs.labels:
        raise FieldError(f"{run.checkpoint}: the run has no foreground object (every Gaussian "
                         "is background); Phase 3 needs objects from masks or clustering")
    timings["observe_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    k, t = obs.observed.shape
    d = encoder.dim
    e_obs = np.zeros((k, t, d), dtype=np.float64)
    if obs.crops:
        emb = encoder.encode_images(obs.crops)
        for (a, f), e in zip(obs.crop_index, emb, strict=True):
            e_obs[a, f] = e
    timings["encode_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    names = [run.names.get(j, f"object {j}") for j in obs.labels]
    hand = names.index(cfg.hand_object) if cfg.hand_object in names else None
    tracks = _tracks(run, obs, hand)
    feats = kinematic_features(tracks)
    static = fm.static_embeddings(e_obs, obs.observed)
    std = fm.standardise(feats, obs.observed)
    pred, w = fm.predict_embeddings(std, e_obs, obs.observed, static, cfg.ridge_lambda)
    mixed = fm.blend(pred, e_obs, obs.observed, cfg.beta, cfg.beta_on)
    sync = fm.temporal_ema(mixed, cfg.ema_gamma)
    timings["field_s"] = time.perf_counter() - t2
    timings["total_s"] = time.perf_counter() - t0
    timings["crops"] = len(obs.crops)
    return Field(
        labels=obs.labels, names=names, times=obs.times, obs=e_obs.astype(np.float32),
        observed=obs.observed, static=static.astype(np.float32), features=feats,
        standardised=std, ridge=w, pred=pred.astype(np.float32), sync=sync.astype(np.float32),
        visible=obs.visible, boxes=obs.boxes, gaps=obs.gaps, radius=obs.radius,
        centroids=tracks.centroids, gap_labels=obs.gap_labels, views=obs.views,
        up=up, right=np.asarray(cams[0].viewmat[0, :3], float),
        encoder=encoder.describe(),
        config=dataclasses.asdict(cfg), timings=timings,
    )  # fmt: skip


def load_field(run_dir: str | Path) -> Field:
    """The field saved in ``run_dir/phase3``; FieldError naming the file when it is missing,
    unreadable or inconsistent."""
    folder = Path(run_dir) / FIELD_DIR
    meta_path, arr_path = folder / FIELD_META, folder / FIELD_FILE
    if not meta_path.is_file() or not arr_path.is_file():
        raise FieldError(
            f"{folder}: no language field in this run; build it with "
            f"`python -m sync4d fit {run_dir} --phases 3`"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise FieldError(f"{meta_path}: not a readable field header ({e}); rebuild with "
                         f"`fit {run_dir} --phases 3`") from None  # fmt: skip
    try:
        arrays = load_file(str(arr_path))
    except Exception as e:  # noqa: BLE001 - safetensors raises several kinds
        raise FieldError(f"{arr_path}: not a readable safetensors file ({e})") from None
    missing = [n for n in (*_ARRAYS, "times") if n not in arrays]
    if missing or meta.get("version") != _VERSION:
        raise FieldError(f"{arr_path}: field of another version or missing {missing}; "
                         f"rebuild with `fit {run_dir} --phases 3`")  # fmt: skip
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
        encoder=meta["encoder"], config=meta["config"], timings=meta.get("timings", {}), **kw,
    )  # fmt: skip

