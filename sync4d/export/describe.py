"""The scene description of a run with a language field (docs/export.md).

`describe(run, field, ...)` reads what Phases 2 and 3 already hold and arranges it for a reader
that is not sync4d (a person, a script, a multimodal LLM), as the typed model of
`sync4d.export.model` (`Scene`, numbers rounded to `SceneSettings.decimals`):

* **objects**: each foreground object of the field (its Phase 2 label, which is the mask label
  when masks drove the assignment, and name), its Gaussian count, its extent (2nd-98th
  percentile box of its Gaussians, canonical and over time), its mean rigid share, and the
  vocabulary entries nearest its static embedding (cosine, the field's encoder);
* **tracks**, per object and stored frame: M_phi's centroid, rotation (the rotation of the
  polar decomposition in affine mode; unit quaternion w-x-y-z, sign kept continuous in time)
  and translation, velocity and acceleration (Appendix B dims 6-11), visibility, and all 28
  kinematic dims under their names (`sync4d.phase3.kinematics.FEATURE_NAMES`);
* **segments**: per object, the intervals where each motion state holds ("at rest", "moving",
  "rising", "falling", "turning"), evaluated by the very predicates `query` uses for motion
  phrases (`sync4d.phase3.motion_phrases`) with the thresholds the field was built with, so
  the description and the query answers agree;
* **events** between two objects, or an object and the background (id 0): ``approach`` and
  ``separation`` (the centroid distance, or for the background the object's height above the
  surface under it, falls or grows faster than ``closing_speed`` times the scene's reference
  speed) and ``contact``: the run's contacts as `sync4d.phase3.states` finds them (the one
  model every query, the prompt and the MCP tools read; evidence "gap" or "rebound", onset and
  offset from the object's geometry against the surface); runs shorter than
  ``phrase_min_frames`` are dropped, one-frame gaps closed;
* **language slots**: for each query, the object the default scorer ranks first and the frames
  where it is active (Appendix F's rule of the field); for each vocabulary entry the same, but
  only when that object's appearance, the cosine of its static embedding to the entry, beats
  every other object's by at least `SceneSettings.slot_margin` (an entry no object separates
  is attached to none: the prompt lists it as unattached); an object's nearest vocabulary
  entries (`vocabulary`) by the same rule;
* **embeddings** (static [K, D], e_sync [K, T, D], the texts' [V, D]) go to a safetensors side
  file, referenced from the description by name and SHA-256, never inline.

Intervals are inclusive frame ranges [start, end] of the stored frames, with their times t0, t1
(normalised time in [0, 1]). Everything is in the dataset's world units and axes. The records
are arranged as dicts in the file's key order, rounded (`rounded`: fixed decimals, -0 as 0,
not finite as null, numpy values as Python numbers) and checked into the model, so the same
run gives the same `Scene` and the same bytes wherever it is written or served.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import ValidationError

from sync4d import __version__
from sync4d.export.model import EVENT_KINDS, FORMAT, SEGMENT_STATES, VERSION, Scene, where
from sync4d.export.schema import SceneError
from sync4d.files import file_sha256
from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3 import states
from sync4d.phase3.activation import intervals
from sync4d.phase3.kinematics import FEATURE_NAMES
from sync4d.phase3.query import TextCache, answer, field_settings
from sync4d.phase3.store import Field
from sync4d.runs import Run

__all__ = ["EVENT_KINDS", "FORMAT", "SEGMENT_STATES", "THRESHOLD_KEYS", "VERSION",
           "SceneSettings", "describe", "motion_segments", "pairwise_events", "rounded"]

#: The Phase 3 settings the segments and events read (recorded under `metadata.thresholds`).
THRESHOLD_KEYS = ("moving_speed", "rest_speed", "vertical_speed", "closing_speed",
                  "contact_gap", "phrase_smooth", "phrase_min_frames", "activation")  # fmt: skip


@dataclass(frozen=True)
class SceneSettings:
    """What the description keeps: number precision and how many vocabulary matches."""

    #: Decimal places of every number in the JSON (fixed precision: same run, same bytes).
    decimals: int = 6
    #: Vocabulary entries listed per object (nearest first).
    vocab_top: int = 3
    #: Percentiles of an object's Gaussian positions that bound its extent (floaters aside).
    extent_percentiles: tuple[float, float] = (2.0, 98.0)
    #: A vocabulary entry is attached to an object (a slot, a `vocabulary` match) only when the
    #: cosine of the object's static embedding to it beats every other object's by at least
    #: this much (measured, docs/results/phase3.md "Slots": with the offline encoder on
    #: bouncingballs and two embedded-scene runs, the objects' own colours separate by
    #: 0.22-0.54, entries no object matches by 0.12 at most; 0.17 is the middle of the gap).
    slot_margin: float = 0.17


def rounded(x: Any, decimals: int) -> Any:
    """`x` with every float rounded to `decimals` places (-0.0 -> 0.0, non-finite -> None),
    numpy scalars and arrays as Python numbers and lists, tuples as lists."""
    if isinstance(x, dict):
        return {k: rounded(v, decimals) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [rounded(v, decimals) for v in x]
    if isinstance(x, np.ndarray):
        return rounded(x.tolist(), decimals)
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        if not math.isfinite(x):
            return None
        r = round(float(x), decimals)
        return 0.0 if r == 0 else r
    return x


def _span(a: int, b: int, times: np.ndarray) -> dict:
    return {"start": a, "end": b, "t0": float(times[a]), "t1": float(times[b])}


def _quaternions(r: np.ndarray) -> np.ndarray:
    """Unit quaternions w-x-y-z [T, 4] of rotations `r` [T, 3, 3], w >= 0 at the first frame
    and the sign kept continuous (q and -q are one rotation)."""
    out = np.zeros((len(r), 4))
    for i, m in enumerate(r):
        tr = np.trace(m)
        # Shepperd: from the largest of w^2, x^2, y^2, z^2 (4 * each, minus 1)
        d = np.array([tr, m[0, 0] - m[1, 1] - m[2, 2], m[1, 1] - m[0, 0] - m[2, 2],
                      m[2, 2] - m[0, 0] - m[1, 1]])  # fmt: skip
        j = int(np.argmax(d))
        s = 2.0 * math.sqrt(max(1.0 + d[j], 1e-300))
        if j == 0:
            q = [s / 4, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif j == 1:
            q = [(m[2, 1] - m[1, 2]) / s, s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif j == 2:
            q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s]
        else:
            q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4]
        q = np.asarray(q) / np.linalg.norm(q)
        prev = out[i - 1] if i else np.array([1.0, 0.0, 0.0, 0.0])
        out[i] = -q if q @ prev < 0 else q
    return out


def _rotations(linear: np.ndarray, rigid: bool) -> np.ndarray:
    """M_phi's rotation [T, 3, 3]: the linear part itself (SE(3)) or its polar rotation."""
    if rigid:
        return linear
    u, _, vt = np.linalg.svd(linear)
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    return u @ vt


def _positions(run: Run, times: np.ndarray) -> list[np.ndarray]:
    """Every Gaussian's position [N, 3] at each of `times` (D_theta, what renders)."""
    with torch.no_grad():
        return [run.model.at_time(float(t))[0].double().numpy() for t in times]


def _box(x: np.ndarray, pct: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    if len(x) == 0:
        return np.zeros(3), np.zeros(3)
    return np.percentile(x, pct[0], axis=0), np.percentile(x, pct[1], axis=0)


def _runs(active: np.ndarray, min_frames: int) -> list[tuple[int, int]]:
    """Intervals of `active` [T] after closing one-frame gaps and dropping short runs."""
    return intervals(mp.clean_runs(np.asarray(active, bool)[None], min_frames)[0])


def motion_segments(field: Field, cfg) -> list[list[dict]]:
    """Per object, the intervals of each state of `SEGMENT_STATES` (`states.motion_state`),
    in time order."""
    out: list[list[dict]] = [[] for _ in field.labels]
    for state in SEGMENT_STATES:
        act = states.motion_state(field, cfg, state)
        for k in range(len(field.labels)):
            out[k] += [{"state": state, **_span(a, b, field.times)} for a, b in intervals(act[k])]
    for segs in out:
        segs.sort(key=lambda s: (s["start"], SEGMENT_STATES.index(s["state"])))
    return out


def pairwise_events(field: Field, cfg) -> list[dict]:
    """Approach, contact and separation intervals of every pair of objects and of every object
    with the background, sorted by start frame; the contacts are `states.contacts`."""
    times, labels, radius = field.times, field.labels, field.radius
    c, _, s_ref = mp.smoothed_motion(field.centroids, times, radius, cfg.phrase_smooth)
    closing_tol = cfg.closing_speed * s_ref
    minf = int(cfg.phrase_min_frames)
    t = len(times)
    events: list[dict] = []

    def rate(d: np.ndarray) -> np.ndarray:
        return np.gradient(d, times) if t > 1 else np.zeros(t)

    def add(kind: str, a: int, b: int, runs: list[tuple[int, int]], dist: np.ndarray,
            evidence: list[str] | None = None) -> None:  # fmt: skip
        for i, (s, e) in enumerate(runs):
            ev = {"kind": kind, "objects": [a, b], **_span(s, e, times),
                  "distance": [float(dist[s]), float(dist[e])]}  # fmt: skip
            if evidence is not None:
                ev["evidence"] = evidence[i]
            events.append(ev)

    found = states.contacts(field, cfg)
    for k, a in enumerate(labels):
        g = states.support_gap(field, k)
        if g is not None:
            gs = mp.smooth_in_time(g[None], times, cfg.phrase_smooth)[0]
            add("approach", a, 0, _runs(-rate(gs) > closing_tol, minf), g)
            mine = [x for x in found if x.label == a and x.other == 0]
            add("contact", a, 0, [(x.start, x.end) for x in mine], g,
                [x.evidence for x in mine])  # fmt: skip
            add("separation", a, 0, _runs(rate(gs) > closing_tol, minf), g)
        for j in range(k + 1, len(labels)):
            b = labels[j]
            d = np.linalg.norm(c[k] - c[j], axis=-1)
            add("approach", a, b, _runs(-rate(d) > closing_tol, minf), d)
            both = [x for x in found if {x.label, x.other} == {a, b}]
            add("contact", a, b, [(x.start, x.end) for x in both], d,
                [x.evidence for x in both])  # fmt: skip
            add("separation", a, b, _runs(rate(d) > closing_tol, minf), d)
    events.sort(key=lambda e: (e["start"], EVENT_KINDS.index(e["kind"]), e["objects"]))
    return events


def _margin(scores: np.ndarray, k: int) -> float:
    """How far `scores` [K] of object `k` beats the best other object's (inf when alone)."""
    others = np.delete(np.asarray(scores, np.float64), k)
    return float(scores[k] - others.max()) if len(others) else math.inf


def _cameras(run: Run) -> list[dict]:
    out = []
    for c in run.cameras:
        out.append({
            "name": c["name"], "split": c["split"], "time": c["time"],
            "world_to_camera": np.asarray(c["viewmat"], np.float64).reshape(4, 4).tolist(),
            "fx": c["fx"], "fy": c["fy"], "cx": c["cx"], "cy": c["cy"],
            "width": c["width"], "height": c["height"],
        })  # fmt: skip
    return out


def describe(
    run: Run, field: Field, *, cache: TextCache | None = None, vocab: Sequence[str] = (),
    queries: Sequence[str] = (), settings: SceneSettings = SceneSettings(),
) -> tuple[Scene, dict[str, np.ndarray]]:  # fmt: skip
    """The description of `run` (a Phase 2 run) and its language `field` (its numbers rounded
    to `settings.decimals`; no `embeddings` record until `sync4d.export.scene.write_scene`
    writes the side file), and the embeddings for the side file: ``static`` [K, D], ``sync``
    [K, T, D] and ``texts`` [V, D] (the `vocab` entries, then the `queries`). `cache` encodes
    the texts (needed when `vocab` or `queries` are given). `SceneError` for a run that has
    none, or a value the description cannot hold (a track that is not finite)."""
    if run.motion is None or run.labels is None:
        raise SceneError(f"{run.checkpoint}: a scene description needs a Phase 2 run; "
                         f"run `fit --out {run.path} --phases 2` first")  # fmt: skip
    times = np.asarray(field.times, np.float64)
    if run.times is not None and len(run.times) != len(times):
        raise SceneError(f"{run.path}: the field has {len(times)} frames and M_phi "
                         f"{len(run.times)}; rebuild the field with `fit --out {run.path} "
                         "--phases 3`")  # fmt: skip
    texts = [*vocab, *queries]
    if texts and cache is None:
        raise SceneError("describe: vocabulary entries and queries need a text cache")
    cfg = field_settings(field)
    linear, offsets = run.motion.trajectory()
    positions = _positions(run, times)
    canonical = run.model.means.detach().double().numpy()
    feats = field.features
    pct = settings.extent_percentiles
    text_emb = cache.get(texts) if texts else np.zeros((0, field.dim), np.float32)
    vsims = field.static @ text_emb[: len(vocab)].T if len(vocab) else None
    slots: list[list[dict]] = [[] for _ in field.labels]
    for i, text in enumerate(texts):
        ans = answer(field, text, cache=cache)
        top = ans["objects"][0]
        k = field.labels.index(top["label"])
        slot = {"text": text, "source": "vocab" if i < len(vocab) else "query",
                "score": top["score"], "intervals": top["intervals"]}  # fmt: skip
        if i < len(vocab):
            margin = _margin(vsims[:, i], k)
            if margin < settings.slot_margin:
                continue  # no object separates: attached to none
            if math.isfinite(margin):  # (a scene of one object: nothing to separate from)
                slot["margin"] = margin
        slots[k].append(slot)
    objects, tracks = [], []
    for k, label in enumerate(field.labels):
        sel = run.labels == label
        boxes = [_box(x[sel], pct) for x in positions]
        lo0, hi0 = _box(canonical[sel], pct)
        rot = _rotations(linear[label].astype(np.float64), bool(run.motion.rigid))
        matches = []
        if vsims is not None:
            order = [v for v in np.argsort(-vsims[k], kind="stable")
                     if _margin(vsims[:, v], k) >= settings.slot_margin][: settings.vocab_top]
            matches = [{"text": vocab[v], "similarity": float(vsims[k, v])} for v in order]
        objects.append({
            "id": int(label), "label": int(label), "name": field.names[k],
            "gaussians": int(sel.sum()),
            "extent": {"canonical": {"min": lo0.tolist(), "max": hi0.tolist()},
                       "size_max": np.max([hi - lo for lo, hi in boxes], axis=0).tolist()},
            "radius": float(field.radius[k]),
            "rigid_share": float(np.mean(feats[k, :, 4])),
            "observed_frames": int(field.observed[k].sum()),
            "vocabulary": matches,
            "slots": slots[k],
        })  # fmt: skip
        tracks.append({
            "id": int(label),
            "centroid": field.centroids[k].tolist(),
            "rotation": _quaternions(rot).tolist(),
            "translation": offsets[label].astype(np.float64).tolist(),
            "velocity": feats[k, :, 6:9].tolist(),
            "acceleration": feats[k, :, 9:12].tolist(),
            "visible": field.visible[k].tolist(),
            "observed": [bool(x) for x in field.observed[k]],
            "box_min": [lo.tolist() for lo, _ in boxes],
            "box_max": [hi.tolist() for _, hi in boxes],
            "kinematics": {name: feats[k, :, d].tolist() for d, name in enumerate(FEATURE_NAMES)},
        })  # fmt: skip
    segments = motion_segments(field, cfg)
    for obj, segs in zip(objects, segments, strict=True):
        obj["segments"] = segs
    all_pos = canonical[run.labels > 0] if (run.labels > 0).any() else canonical
    lo, hi = _box(all_pos, (1.0, 99.0))
    ckpt = Path(run.checkpoint)
    metadata = {
        "format": FORMAT, "version": VERSION, "sync4d": __version__,
        "run": {"name": Path(run.path).name, "kind": run.kind, "iteration": run.iteration,
                "dataset": Path(str(run.settings.get("data") or "")).name},
        "checkpoint": {"file": ckpt.name,
                       "sha256": file_sha256(ckpt) if ckpt.is_file() else None},
        "encoder": {"kind": field.encoder.get("kind"),
                    "fingerprint": field.encoder.get("fingerprint"), "dim": field.dim,
                    "closed_vocabulary": bool(field.encoder.get("closed_vocabulary", False))},
        "units": {"length": "world units of the dataset", "time": "normalised, 0 to 1",
                  "angle": "radians", "velocity": "length per unit of normalised time",
                  "acceleration": "length per unit of normalised time squared"},
        "axes": {"up": field.up.tolist(), "right": field.right.tolist(),
                 "cameras": "world_to_camera is row-major 4x4 with OpenCV axes (x right, "
                            "y down, z forward); intrinsics in pixels"},
        "scale": {"bounds": [lo.tolist(), hi.tolist()],
                  "extent": float(np.linalg.norm(hi - lo))},
        "frames": {"count": len(times), "times": times.tolist()},
        "cameras": _cameras(run),
        "thresholds": {**{k: getattr(cfg, k) for k in THRESHOLD_KEYS},
                       **states.settings(cfg), "slot_margin": settings.slot_margin},
    }  # fmt: skip
    doc = {"metadata": metadata, "objects": objects, "tracks": tracks,
           "events": pairwise_events(field, cfg), "texts": texts}  # fmt: skip
    try:
        scene = Scene.model_validate(rounded(doc, settings.decimals))
    except ValidationError as e:
        raise SceneError(f"{run.path}: its scene description would not be valid, {where(e)} "
                         "(null: a value that is not finite)") from None
    embeddings = {
        "static": np.ascontiguousarray(field.static, np.float32),
        "sync": np.ascontiguousarray(field.sync, np.float32),
        "texts": np.ascontiguousarray(text_emb, np.float32).reshape(len(texts), field.dim),
    }
    return scene, embeddings
