"""Building the language field of a Phase 2 run and keeping it in the run folder.

`build_field(run, cfg, encoder)` runs Appendix A's Phase 3 steps on the frozen run: observe
(crops, visibility, residuals: `observe`), encode the crops (`Encoder.encode_images`), the static
anchors, the 28-D kinematics (`kinematics`), per-object standardisation and ridge, prediction,
blend and temporal EMA (`field`). The result is a `Field`, saved as ``RUN/phase3/field.safetensors``
(arrays) and ``RUN/phase3/field.json`` (labels, names, times, crop views, the encoder, the
settings, timings, counts, and the SHA-256 of the checkpoint it was built from), both written
atomically. `load_field(RUN)` reads it back and checks it, and refuses a field whose checkpoint
has changed since (a refit run), naming the command that rebuilds it.

What the build skips (issue 40) is counted in `Field.counts`, which the pipeline emits as a
`Skipped("phase3", ...)` event and the command line says in one line: only observed
object-frames are cropped and encoded, all in one `encode_images` call
(`Phase3Config.skip_unobserved`; off, the unobserved crops that have a box are encoded too, in a
second call, and discarded); the relational kinematic dims are computed at every frame, see
`sync4d.phase3.kinematics`.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from sync4d import watchdog
from sync4d.events import FieldSummary, FieldTimings, Phase3Skips, PhaseDone, emit
from sync4d.phase3 import field as fm
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import Encoder
from sync4d.phase3.kinematics import Tracks, kinematic_features, relational_counts
from sync4d.phase3.observe import Observations, observe
from sync4d.phase3.store import Field, FieldError, checkpoint_record, load_field
from sync4d.runs import CheckpointKind, Run

__all__ = ["Field", "FieldError", "build_field", "load_field", "up_vector"]


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
    threads: int | None = None,
) -> Field:  # fmt: skip
    """The language field of the Phase 2 run `run` (its dataset from `data` or the folder it
    recorded) with `encoder` and the settings `cfg`; reports its progress and then
    `PhaseDone("phase3")` as `sync4d.events`."""
    if run.kind != CheckpointKind.PHASE2 or run.motion is None:
        raise FieldError(
            f"{run.checkpoint}: Phase 3 needs a Phase 2 run (this checkpoint is {run.kind}); "
            "run `fit --out RUN --phases 2` first"
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
        skip_unobserved=cfg.skip_unobserved,
    )  # fmt: skip
    if not obs.labels:
        raise FieldError(
            f"{run.checkpoint}: the run has no foreground object (every Gaussian "
            "is background); Phase 3 needs objects from masks or clustering"
        )
    timings["observe_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    k, t = obs.observed.shape
    d = encoder.dim
    e_obs = np.zeros((k, t, d), dtype=np.float64)
    calls = 0
    if obs.crops:  # one call: the encoder batches
        emb = encoder.encode_images(obs.crops)
        calls += 1
        for (a, f), e in zip(obs.crop_index, emb, strict=True):
            e_obs[a, f] = e
    if obs.extra_crops:  # skip_unobserved off: encoded apart (the batches above unchanged), unused
        encoder.encode_images(obs.extra_crops)
        calls += 1
    timings["encode_s"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    names = [run.names.get(j, f"object {j}") for j in obs.labels]
    hand = names.index(cfg.hand_object) if cfg.hand_object in names else None
    tracks = _tracks(run, obs, hand)
    feats = kinematic_features(tracks)
    static = fm.static_embeddings(e_obs, obs.observed)
    std = fm.standardise(feats, obs.observed, cfg.clip_unobserved)
    pred, w = fm.predict_embeddings(std, e_obs, obs.observed, static, cfg.ridge_lambda,
                                    cfg.kinematics)  # fmt: skip
    mixed = fm.blend(pred, e_obs, obs.observed, cfg.beta, cfg.beta_on)
    sync = fm.temporal_ema(mixed, cfg.ema_gamma)
    for name, arr in (("the kinematic features", feats), ("the standardised features", std),
                      ("the ridge map W_k", w), ("the predicted embeddings", pred),
                      ("the synchronised embeddings", sync)):  # fmt: skip
        watchdog.check_array("Phase 3", name, arr)
    timings["field_s"] = time.perf_counter() - t2
    timings["total_s"] = time.perf_counter() - t0
    timings["crops"] = len(obs.crops)
    counts = {**obs.counts, "crops_encoded": len(obs.crops) + len(obs.extra_crops),
              "encoder_calls": calls, **relational_counts(obs.observed)}  # fmt: skip
    built = Field(
        labels=obs.labels, names=names, times=obs.times, obs=e_obs.astype(np.float32),
        observed=obs.observed, static=static.astype(np.float32), features=feats,
        standardised=std, ridge=w, pred=pred.astype(np.float32), sync=sync.astype(np.float32),
        visible=obs.visible, boxes=obs.boxes, gaps=obs.gaps, radius=obs.radius,
        centroids=tracks.centroids, gap_labels=obs.gap_labels, views=obs.views,
        up=up, right=np.asarray(cams[0].viewmat[0, :3], float),
        encoder=encoder.describe(),
        config=dataclasses.asdict(cfg), timings=timings, counts=counts,
        checkpoint=checkpoint_record(run.checkpoint),
    )  # fmt: skip
    emit(PhaseDone("phase3", FieldSummary(len(obs.labels), len(obs.times), FieldTimings(**timings),
                                          Phase3Skips(**counts))))  # fmt: skip
    return built
