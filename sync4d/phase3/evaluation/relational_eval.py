"""Evaluating relational questions (`sync4d.phase3.relational`) against a question file.

Design notes
------------
A relational question file is our query format's sibling, told apart by ``"kind":
"relational"``::

    {"version": 1, "kind": "relational", "scene": "...", "truth": "how it was derived",
     "questions": [
       {"question": "which ball lands first", "form": "ordinal-objects",
        "object": "red ball", "times": [[0.319, 0.366]]},
       {"question": "how many times does the red ball bounce", "form": "count",
        "object": "red ball", "times": [[...], [...]], "count": 2}]}

`form` is one of `relational.FORMS` and only groups the results; `times` are inclusive ranges
of normalised time (a frame is in the answer when its time lies in one, with 1e-9 slack; an
empty list: the answer holds at no frame); `count` is given for count questions. Each
question is answered by `query.answer` (the default scorer, which reads the plan) and scored
on the field's frames: Acc is whether the top object is the question's object (a refusal, "the
fifth ball to land" of three, names none); tIoU the temporal IoU of the top object's
intervals and the true ones (0 when the object is wrong; 1 when both are empty); for count
questions, whether the count is right; plan accuracy whether the plan has the question's form
(and, for counts, the right count). The rows and the mean
per form go to ``RUN/phase3/eval-<name>-relational.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sync4d.files import write_text_atomic
from sync4d.phase3.evaluation.annotations import AnnotationError
from sync4d.phase3.evaluation.query_metrics import temporal_iou
from sync4d.phase3.query import TextCache, answer
from sync4d.phase3.relational import FORMS
from sync4d.phase3.store import load_field
from sync4d.runs.names import FIELD_DIR

__all__ = ["is_relational", "read_relational", "evaluate_relational"]

_KEYS = {"question", "form", "object", "times", "count"}


def is_relational(path: str | Path) -> bool:
    """Whether `path` is a relational question file (a JSON object with kind "relational")."""
    p = Path(path)
    if not p.is_file() or p.suffix.lower() != ".json":
        return False
    try:
        return json.loads(p.read_text(encoding="utf-8")).get("kind") == "relational"
    except (OSError, ValueError, AttributeError):
        return False


def read_relational(path: str | Path, names: list[str]) -> list[dict]:
    """The questions of `path`, checked: AnnotationError naming the question and the fix."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise AnnotationError(p, f"not a readable JSON file ({e})") from None
    qs = doc.get("questions")
    if not isinstance(qs, list) or not qs:
        raise AnnotationError(p, "no \"questions\" list", "give a non-empty list of questions")
    for i, q in enumerate(qs):
        where = f"question {i + 1}"
        if not isinstance(q, dict) or not isinstance(q.get("question"), str):
            raise AnnotationError(p, f"{where} is not an object with a \"question\" text")
        extra = set(q) - _KEYS
        if extra:
            raise AnnotationError(p, f"{where} has unknown keys {sorted(extra)}",
                                  f"allowed: {sorted(_KEYS)}")  # fmt: skip
        if q.get("form") not in FORMS:
            raise AnnotationError(p, f"{where} has form {q.get('form')!r}",
                                  f"\"form\" must be one of {list(FORMS)}")  # fmt: skip
        if q.get("object") not in names:
            raise AnnotationError(p, f"{where}: \"object\" {q.get('object')!r} is no object "
                                  "of this run", f"use one of {', '.join(names)}")  # fmt: skip
        times = q.get("times")
        if not isinstance(times, list) or any(
                not isinstance(r, list) or len(r) != 2 or r[0] > r[1] for r in times):
            raise AnnotationError(p, f"{where} has bad \"times\"", "give a list of [t0, t1] "
                                  "ranges of normalised time, t0 <= t1")  # fmt: skip
    return qs


def _frames(times: list, frame_times: np.ndarray) -> np.ndarray:
    gt = np.zeros(len(frame_times), bool)
    for t0, t1 in times:
        gt |= (frame_times >= t0 - 1e-9) & (frame_times <= t1 + 1e-9)
    return gt


def evaluate_relational(run_dir: str | Path, path: str | Path, *, encoder=None) -> dict:
    """Answer every question of the file `path` on the run's field; the summary: per form and
    overall, the number of questions, Acc (right object), tIoU and count accuracy; the rows
    are in ``RUN/phase3/eval-<name>-relational.json``."""
    run_dir, path = Path(run_dir), Path(path)
    field = load_field(run_dir)
    qs = read_relational(path, list(field.names))
    cache = TextCache(run_dir, field, encoder)
    rows = []
    for q in qs:
        ans = answer(field, q["question"], cache=cache)
        top = ans["objects"][0]
        pred = np.asarray(ans["active"][top["name"]], bool)
        gt = _frames(q["times"], field.times)
        name = None if ans["refusal"] else top["name"]
        right = name == q["object"]
        row = {"question": q["question"], "form": q["form"], "plan": ans["plan"],
               "fallback": ans["fallback"], "refusal": ans["refusal"], "object": name,
               "gt_object": q["object"], "object_correct": right,
               "read_form": ans["form"], "form_correct": ans["form"] == q["form"],
               "tiou": temporal_iou(pred, gt) if right else 0.0,
               "pred_intervals": [[iv["start"], iv["end"]] for iv in top["intervals"]],
               "gt_times": q["times"]}  # fmt: skip
        if "count" in q:
            row["count"], row["gt_count"] = ans["count"], q["count"]
            row["count_correct"] = ans["count"] == q["count"]
        rows.append(row)

    def mean(rs: list[dict]) -> dict:
        counts = [r["count_correct"] for r in rs if "count_correct" in r]
        return {"n": len(rs), "acc": float(np.mean([r["object_correct"] for r in rs])),
                "tiou": float(np.mean([r["tiou"] for r in rs])),
                "count_acc": float(np.mean(counts)) if counts else None,
                "parsed": float(np.mean([r["plan"] is not None for r in rs])),
                "plan_acc": float(np.mean([r["form_correct"] and r.get("count_correct", True)
                                           for r in rs]))}  # fmt: skip

    forms = {f: mean([r for r in rows if r["form"] == f]) for f in FORMS
             if any(r["form"] == f for r in rows)}  # fmt: skip
    summary = {"questions": path.name, "forms": forms, "all": mean(rows)}
    out = run_dir / FIELD_DIR / f"eval-{path.stem}-relational.json"
    write_text_atomic(out, json.dumps({**summary, "file": str(path), "rows": rows,
                                       "encoder": field.encoder}, indent=1) + "\n")  # fmt: skip
    summary["rows_file"] = str(out)
    return summary
