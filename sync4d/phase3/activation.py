"""Phase 3's temporal activation rules: when a query holds, from one object's per-frame
similarities (Appendix F), and the frame ranges an activation is reported as.

* `activate` turns an object's similarities s(f) over the scored frames into a bool activation
  with a rule of `RULES`, the one registry of activation rules (the config's
  `phase3.activation` and the command line's ``--rule`` take their names from it): the paper's
  ("half-peak": s > 0.5 * max s) or 4D LangSplat's ("mean": s >= mean s, `eval/eval.py:
  evaluate_video_feature` with `video_thresh` / `clip_thresh` = the mean similarity over the
  evaluated frames).
* `intervals` / `from_intervals` convert between bool [T] and inclusive (start, end) ranges,
  the form 4D LangSplat's `video_annotations.json`, our query files, the answers of a query
  and the scene description use.

Pure functions over numpy arrays (no torch): the query path, the config, the command line's
help and the evaluation (`sync4d.phase3.evaluation`) all read them from here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "DEFAULT_RULE",
    "RULES",
    "ActivationRule",
    "Interval",
    "Rule",
    "activate",
    "bool_vector",
    "from_intervals",
    "intervals",
]

#: An activation rule's name: a key of `RULES`.
Rule = str

#: An inclusive (start, end) range of frame indices.
Interval = tuple[int, int]


def bool_vector(x: np.ndarray | Sequence[bool], name: str) -> np.ndarray:
    """`x` as a bool [T] array over frames (0/1 taken); ValueError for another shape or
    value."""
    a = np.asarray(x)
    if a.ndim != 1:
        raise ValueError(f"{name} must be a 1-D array over frames, got shape {list(a.shape)}")
    if a.dtype != bool:
        if not np.isin(a, (0, 1)).all():
            raise ValueError(f"{name} must be bool (or 0/1), got dtype {a.dtype}")
        a = a.astype(bool)
    return a


@dataclass(frozen=True)
class ActivationRule:
    """A temporal activation rule: its `name` (``--rule NAME``, ``phase3.activation``), a
    one-line `summary` (the command line's help) and `active(s)`: the bool [T] activation of
    finite, non-constant scores s [T] (`activate` handles the rest)."""

    name: str
    summary: str
    active: Callable[[np.ndarray], np.ndarray]


def _half_peak(s: np.ndarray) -> np.ndarray:
    """The paper's rule (Appendix F): s(f) > 0.5 * max s; with a peak <= 0, above the midpoint
    of the score range (see `activate`)."""
    lo, hi = float(s.min()), float(s.max())
    if hi > 0.0:
        return s > 0.5 * hi
    return (s - lo) > 0.5 * (hi - lo)


def _mean(s: np.ndarray) -> np.ndarray:
    """4D LangSplat's rule (`evaluate_video_feature`): s(f) >= mean s."""
    return s >= s.mean()


#: The activation rules by name, the default first.
RULES: dict[str, ActivationRule] = {r.name: r for r in (
    ActivationRule("half-peak", "above half the peak (Appendix F)", _half_peak),
    ActivationRule("mean", "at least the mean (4D LangSplat)", _mean),
)}  # fmt: skip
DEFAULT_RULE: Rule = next(iter(RULES))


def activate(scores: np.ndarray | Sequence[float], rule: Rule = DEFAULT_RULE) -> np.ndarray:
    """Per-frame activation, bool [T], of one object's query similarities `scores` [T] by
    `rule`, a name in `RULES`.

    ``"half-peak"`` (the paper, Appendix F): active(f) = s(f) > 0.5 * max_f' s(f').
    ``"mean"`` (4D LangSplat's `evaluate_video_feature`): active(f) = s(f) >= mean_f' s(f').

    Decisions:

    * Peak <= 0 under "half-peak": the literal rule would activate nothing (0.5 * peak >= peak
      when peak <= 0), although cosine similarities are often all negative and their shape over
      time still says when the query holds. Then the rule is applied to the scores shifted by
      their minimum: active(f) = s(f) - min s > 0.5 * (max s - min s), i.e. above the midpoint
      of the score range. With a positive peak the literal rule is kept (so results match the
      paper wherever the paper's rule is meaningful); the two branches meet discontinuously at
      peak = 0, which is the price of keeping the literal rule.
    * Constant scores (max == min, exactly): every frame is active under every rule. Nothing
      tells the frames apart and the object was chosen as the answer, so it is answered for the
      whole run; this is what the mean rule (s >= mean) and the literal half-peak rule with a
      positive constant give anyway, and it makes the negative constant agree with them.

    Raises ValueError for an empty or non-1-D array, NaN / inf, or an unknown rule.
    """
    if rule not in RULES:
        raise ValueError(f"unknown activation rule {rule!r}; use one of {list(RULES)}")
    s = np.asarray(scores, dtype=np.float64)
    if s.ndim != 1 or s.size == 0:
        raise ValueError(f"scores must be a non-empty 1-D array, got shape {list(s.shape)}")
    if not np.isfinite(s).all():
        raise ValueError("scores contain NaN or inf")
    if float(s.max()) == float(s.min()):
        return np.ones(s.size, dtype=bool)
    return RULES[rule].active(s)


def intervals(active: np.ndarray | Sequence[bool]) -> list[Interval]:
    """The maximal runs of True in `active` [T] as inclusive (start, end) frame indices."""
    a = bool_vector(active, "active")
    edges = np.diff(np.concatenate([[0], a.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    return [(int(s), int(e)) for s, e in zip(starts, ends, strict=True)]


def from_intervals(ranges: Sequence[Sequence[int]], n_frames: int) -> np.ndarray:
    """bool [n_frames], True on every frame of the inclusive (start, end) `ranges` (overlaps
    allowed). Raises ValueError for a reversed range or one outside 0..n_frames-1."""
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    out = np.zeros(n_frames, dtype=bool)
    for r in ranges:
        if len(r) != 2:
            raise ValueError(f"a frame range is [start, end], got {list(r)}")
        s, e = int(r[0]), int(r[1])
        if s > e:
            raise ValueError(f"frame range [{s}, {e}] is reversed")
        if s < 0 or e >= n_frames:
            raise ValueError(f"frame range [{s}, {e}] lies outside frames 0..{n_frames - 1}")
        out[s : e + 1] = True
    return out
