"""Temporal-query evaluation maths of Phase 3 (Appendix F): Acc, tIoU, vIoU of a query's
activation (`sync4d.phase3.activation`) against its ground truth.

Design notes
------------
* Pure functions over numpy arrays; no torch, no file access except `write_rows`.
* A query is answered with one object k and its per-frame similarities s(f) over the frames
  that are scored (f = 0..T-1, or the query's `evaluated` subset); `activate` turns them into a
  bool activation with a rule of `sync4d.phase3.activation.RULES`.
* Acc = mean_f [active(f) == gt(f)]; tIoU = |P & G| / |P | G| over frame index sets.
* vIoU mirrors 4D LangSplat's `evaluate_video_feature`: over the frames in P | G, a frame where
  both sides are active scores the spatial mask IoU of that frame, a frame where only one side is
  active scores 0, and the scores are averaged over |P | G|. 4D LangSplat scores a query only on
  the frames that carry a GT mask of its object (frames without one never enter its frame list,
  neither for the mean threshold, nor for Acc, nor for vIoU); here `evaluate_query` restricts
  every metric to `Query.evaluated`, and `video_iou` skips frames whose GT mask is None.
  4D LangSplat returns vIoU 0 when P | G is empty; `video_iou` does the same by default
  (`empty_union`), while tIoU of two empty sets is 1.0 (both say "never").
* A query answered with another object than its GT object scores every predicted-active frame
  as wrong (see `evaluate_query`), so "which object" and "when" are both judged.
* `write_rows` writes one row per query plus a mean row as CSV and JSON, each atomically (a
  unique temporary in the target folder, fsync, rename, fsync of the folder: the contract of
  `sync4d.files.write_atomic`, re-implemented here because importing `sync4d.runs` loads
  torch and the compiled extension, and these functions need only numpy).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sync4d.files import write_text_atomic
from sync4d.phase3.activation import DEFAULT_RULE, Interval, Rule, activate, bool_vector, intervals

if TYPE_CHECKING:
    from sync4d.phase3.evaluation.annotations import Query

__all__ = [
    "QueryResult",
    "evaluate_query",
    "frame_accuracy",
    "mask_iou",
    "mean_row",
    "temporal_iou",
    "video_iou",
    "write_rows",
]

def _pair(pred: np.ndarray | Sequence[bool], gt: np.ndarray | Sequence[bool]):
    p, g = bool_vector(pred, "pred"), bool_vector(gt, "gt")
    if p.shape != g.shape:
        raise ValueError(f"pred and gt differ in length: {p.size} and {g.size} frames")
    return p, g


def frame_accuracy(pred: np.ndarray | Sequence[bool], gt: np.ndarray | Sequence[bool]) -> float:
    """Acc: the fraction of frames where `pred` [T] equals `gt` [T] (bool), in [0, 1]."""
    p, g = _pair(pred, gt)
    if p.size == 0:
        raise ValueError("frame_accuracy of zero frames")
    return float(np.mean(p == g))


def temporal_iou(pred: np.ndarray | Sequence[bool], gt: np.ndarray | Sequence[bool]) -> float:
    """tIoU: |P & G| / |P | G| of the active frame sets of `pred` [T] and `gt` [T], in [0, 1].
    Both empty (the query never holds and is never predicted) is agreement: 1.0."""
    p, g = _pair(pred, gt)
    union = int(np.count_nonzero(p | g))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(p & g)) / union


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Spatial IoU |a & b| / |a | b| of two bool masks [H, W], in [0, 1]. Both empty is
    agreement: 1.0 (4D LangSplat's torch division would give NaN there, which never happens on
    its data because a GT mask comes from a polygon)."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"masks differ in shape: {list(a.shape)} and {list(b.shape)}")
    union = int(np.count_nonzero(a | b))
    if union == 0:
        return 1.0
    return int(np.count_nonzero(a & b)) / union


def video_iou(
    pred_active: np.ndarray | Sequence[bool],
    gt_active: np.ndarray | Sequence[bool],
    pred_masks: Sequence[np.ndarray | None],
    gt_masks: Sequence[np.ndarray | None],
    empty_union: float = 0.0,
) -> float | None:
    """vIoU after 4D LangSplat's `evaluate_video_feature`: the mean, over the frames in
    P | G (predicted-active or GT-active), of the spatial `mask_iou(pred_masks[f], gt_masks[f])`
    where both are active and 0 where only one is.

    `pred_active`, `gt_active`: bool [T]; `pred_masks`, `gt_masks`: T entries, each a bool
    [H, W] mask or None. A frame whose GT mask is None is not scored at all (4D LangSplat only
    evaluates frames annotated with the object's mask); a None predicted mask is an empty
    prediction. Returns None when no frame has a GT mask (vIoU is not measurable), and
    `empty_union` (4D LangSplat: 0) when no scored frame is active on either side.
    """
    p, g = _pair(pred_active, gt_active)
    if len(pred_masks) != p.size or len(gt_masks) != p.size:
        raise ValueError(
            f"need one mask (or None) per frame: {p.size} frames, {len(pred_masks)} predicted "
            f"and {len(gt_masks)} GT masks"
        )
    if all(m is None for m in gt_masks):
        return None
    scores: list[float] = []
    for f in range(p.size):
        gm = gt_masks[f]
        if gm is None or not (p[f] or g[f]):
            continue
        if p[f] and g[f]:
            pm = pred_masks[f]
            gm = np.asarray(gm, dtype=bool)
            scores.append(mask_iou(np.zeros_like(gm) if pm is None else pm, gm))
        else:
            scores.append(0.0)
    if not scores:
        return float(empty_union)
    return float(np.mean(scores))


@dataclass(frozen=True)
class QueryResult:
    """One evaluated query: what was asked, what answered it, and the three metrics.

    `acc`, `tiou` in [0, 1]; `viou` in [0, 1] or None (no GT masks, or no predicted masks
    given); intervals are inclusive run-frame ranges of the scored frames (`n_frames` of them);
    `object_correct` is None when the chosen and GT objects cannot be compared."""

    query: str
    object: str
    gt_object: str
    rule: str
    acc: float
    tiou: float
    viou: float | None
    pred_intervals: list[Interval]
    gt_intervals: list[Interval]
    n_frames: int
    object_correct: bool | None

    def as_dict(self) -> dict:
        """The row as JSON-ready values (intervals as lists of [start, end])."""
        return {
            "query": self.query,
            "object": self.object,
            "gt_object": self.gt_object,
            "rule": self.rule,
            "acc": self.acc,
            "viou": self.viou,
            "tiou": self.tiou,
            "pred_intervals": [list(r) for r in self.pred_intervals],
            "gt_intervals": [list(r) for r in self.gt_intervals],
            "n_frames": self.n_frames,
            "object_correct": self.object_correct,
        }


def _object_text(name: str | None, label: int | None) -> str:
    if name is not None and label is not None:
        return f"{name} (#{label})"
    if name is not None:
        return name
    return "" if label is None else f"#{label}"


def evaluate_query(
    query: Query,
    scores: np.ndarray | Sequence[float],
    rule: Rule = DEFAULT_RULE,
    object: str | int | None = None,
    pred_masks: Sequence[np.ndarray | None] | None = None,
    active: np.ndarray | Sequence[bool] | None = None,
) -> QueryResult:
    """Score one query answered by the object `object` (a name or label id; None: the GT one)
    with its per-frame similarities `scores` [T] over all run frames.

    Only the frames in `query.evaluated` are scored, as in 4D LangSplat (frames annotated with
    the object's mask): the activation threshold, Acc, tIoU and vIoU all use them alone.
    `active` [T] (bool) replaces the thresholded scores for a scorer that decides the frames
    itself. `pred_masks` (T entries, bool [H, W] or None) give vIoU; without them, or without
    GT masks, `viou` is None. A chosen object that differs from the GT one (compared by label
    id when both are ints, else by name) turns every predicted-active frame into a wrong frame:
    Acc counts it as a mismatch, tIoU and vIoU see no overlap; the reported predicted intervals
    stay the real activation.
    """
    s = np.asarray(scores, dtype=np.float64)
    n = query.gt_active.size
    if s.shape != (n,):
        raise ValueError(f"scores must cover the run's {n} frames, got shape {list(s.shape)}")
    if pred_masks is not None and len(pred_masks) != n:
        raise ValueError(f"pred_masks must have {n} entries (one per frame), got {len(pred_masks)}")
    ev = np.flatnonzero(query.evaluated)
    if ev.size == 0:
        raise ValueError(f"query {query.text!r} has no frame to score")
    if active is None:
        active = activate(s[ev], rule)
    else:  # a scorer that decides the frames itself (the motion phrases)
        active = bool_vector(active, "active")
        if active.shape != (n,):
            raise ValueError(f"active must cover the run's {n} frames, got {list(active.shape)}")
        active = active[ev]
    gt = query.gt_active[ev]

    correct: bool | None = None
    if isinstance(object, int) and not isinstance(object, bool) and query.label is not None:
        correct = object == query.label
    elif isinstance(object, str) and query.object is not None:
        correct = object == query.object
    scored = active & ~gt if correct is False else active

    viou = None
    if pred_masks is not None and query.gt_masks is not None:
        viou = video_iou(
            scored, gt, [pred_masks[f] for f in ev], [query.gt_masks[f] for f in ev]
        )
    full_pred = np.zeros(n, dtype=bool)
    full_pred[ev] = active
    full_gt = np.zeros(n, dtype=bool)
    full_gt[ev] = gt
    if object is None:
        chosen = _object_text(query.object, query.label)
    elif isinstance(object, str):
        chosen = object
    else:
        chosen = f"#{object}"
    return QueryResult(
        query=query.text,
        object=chosen,
        gt_object=_object_text(query.object, query.label),
        rule=rule,
        acc=frame_accuracy(scored, gt),
        tiou=temporal_iou(scored, gt),
        viou=viou,
        pred_intervals=intervals(full_pred),
        gt_intervals=intervals(full_gt),
        n_frames=int(ev.size),
        object_correct=correct,
    )


def mean_row(rows: Sequence[QueryResult]) -> dict:
    """The mean over `rows` of acc and tiou (all rows) and viou (rows that have one; None if
    none), with the counts `n_queries` and `n_viou`."""
    if not rows:
        raise ValueError("no query results to average")
    vious = [r.viou for r in rows if r.viou is not None]
    return {
        "query": "mean",
        "acc": float(np.mean([r.acc for r in rows])),
        "viou": float(np.mean(vious)) if vious else None,
        "tiou": float(np.mean([r.tiou for r in rows])),
        "n_queries": len(rows),
        "n_viou": len(vious),
    }


CSV_COLUMNS = ("query", "object", "gt_object", "rule", "acc", "viou", "tiou",
               "pred_intervals", "gt_intervals", "n_frames", "object_correct")  # fmt: skip


def _cell(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if math.isnan(v) else repr(v)
    if isinstance(v, list):
        return json.dumps(v)
    return str(v)


def write_rows(
    rows: Sequence[QueryResult], csv_path: str | Path, json_path: str | Path
) -> dict:
    """Write the per-query `rows` and their mean row as CSV (columns `CSV_COLUMNS`, intervals
    as JSON lists, None as an empty cell, the last row's query "mean") and as JSON
    ({"queries": [...], "mean": {...}}), each file atomically. Returns the mean row."""
    mean = mean_row(rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        d = r.as_dict()
        w.writerow([_cell(d[c]) for c in CSV_COLUMNS])
    w.writerow([_cell(mean.get(c)) for c in CSV_COLUMNS])
    write_text_atomic(Path(csv_path), buf.getvalue())
    doc = {"queries": [r.as_dict() for r in rows], "mean": mean}
    write_text_atomic(Path(json_path), json.dumps(doc, indent=2) + "\n")
    return mean
