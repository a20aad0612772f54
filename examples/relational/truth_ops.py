"""The answers of the question sets, computed from true states by code of their own.

`make_truth.py` writes each question's meaning by hand (`Q`: the form, the subject, the state
or event, the relation); this module evaluates that meaning on the true states with its own
operators, so the evaluation can find a wrong operator of `sync4d.phase3.relational` rather
than share it. Nothing here imports the method.

The meanings (the same ones docs/phase3-queries.md states for the grammar):

* states per object and frame: rising / falling while the true vertical speed exceeds 0.15 of
  the scene's reference speed (the 95th percentile of every object's true speed), moving above
  0.15 of it, at rest below 0.08; a state holds over runs of at least 3 frames (one-frame gaps
  closed); contact and turning are given by the scene's truth;
* an episode's onset is its first frame, when that is frame 3 or later (one under way from the
  clip's start has none);
* ordinal over objects: the objects ordered by the onset of their first episode, the nth, its
  first episode with an onset; within one object: its nth episode; counts: its episodes;
* relations: while / during, both; before / until, the frames before the other's first onset;
  after, from it on; the other clause's nth episode when it names one;
* extremes: height or speed, the object with the extreme value, answered with the run around
  its extreme on its side of the mid-range (for rising / falling episodes: the height gained or
  lost, the episode); duration, the longest / shortest episode;
* never: the object whose frames never hold the clause, the whole clip.
"""

from __future__ import annotations

import numpy as np

LEAD = 3
MIN_FRAMES = 3


def runs(row: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive runs of true frames of `row` [T]."""
    out, start = [], None
    for f, v in enumerate(row):
        if v and start is None:
            start = f
        elif not v and start is not None:
            out.append((start, f - 1))
            start = None
    if start is not None:
        out.append((start, len(row) - 1))
    return out


def held(row: np.ndarray) -> np.ndarray:
    """`row` with one-frame gaps closed and runs shorter than `MIN_FRAMES` dropped."""
    r = np.asarray(row, bool).copy()
    for f in range(1, len(r) - 1):
        if r[f - 1] and r[f + 1]:
            r[f] = True
    out = np.zeros_like(r)
    for s, e in runs(r):
        if e - s + 1 >= MIN_FRAMES:
            out[s:e + 1] = True
    return out


def true_states(times, centres, radius, contact, turning=None) -> dict[str, np.ndarray]:
    """The states [K, T] of objects with true centres [K, T, 3] (z up) and radii [K]."""
    vel = np.gradient(centres, times, axis=1)
    speed = np.linalg.norm(vel, axis=-1)
    s_ref = max(float(np.percentile(speed, 95)), 0.05 * float(np.median(radius)))
    vz = vel[..., 2]
    raw = {"rising": vz > 0.15 * s_ref, "falling": -vz > 0.15 * s_ref,
           "moving": speed > 0.15 * s_ref, "at rest": speed < 0.08 * s_ref,
           "turning": np.zeros(speed.shape, bool) if turning is None else turning > 0.5}
    out = {k: np.stack([held(r) for r in v]) for k, v in raw.items()}
    out["contact"] = np.asarray(contact, bool)
    return out


def clause(states, atoms, negated, k, t) -> np.ndarray:
    """Object k's frames [T] of a clause: its atoms all hold (negated when it says so)."""
    row = np.ones(t, bool)
    for a in atoms:
        row &= states[a][k]
    return ~row if negated else row


def nth(eps, n):
    if not eps or (n != -1 and n > len(eps)):
        return None
    return eps[-1] if n == -1 else eps[n - 1]


def relate(row, other, word):
    """Frames of `row` in relation `word` to the frames `other` [T]."""
    idx = np.arange(len(row))
    if word in ("while", "during"):
        return row & other
    onsets = [s for s, _ in runs(other) if s >= LEAD]
    if word in ("before", "until"):
        return row & (idx < onsets[0]) if onsets else np.zeros_like(row)
    if onsets:
        return row & (idx >= onsets[0])
    eps = runs(other)
    return row & (idx > eps[0][1]) if eps else np.zeros_like(row)


def around(q, f, direction):
    """The run around frame `f` of `q` [T] on its side of the mid-range."""
    mid = 0.5 * (q.min() + q.max())
    side = q >= mid if direction == "max" else q <= mid
    return next(((s, e) for s, e in runs(side) if s <= f <= e), (f, f))


def answer(spec: dict, names: list[str], states, height, speed) -> tuple[int, list, int | None]:
    """(object index, its spans, the count) of question `spec` (a `make_truth.Q`)."""
    k_all, t = height.shape
    subj = list(range(k_all)) if spec["subject"] is None else [names.index(spec["subject"])]
    rel = spec["relation"]
    if rel:
        word, other, atoms, neg, *rank = rel
        if other is not None and spec["subject"] is None:
            subj = [k for k in subj if k != names.index(other)]
    frames = {}
    for k in subj:
        row = clause(states, spec["atoms"], spec["negated"], k, t)
        if rel:
            who = k if other is None else names.index(other)
            o = clause(states, atoms, neg, who, t)
            if rank:
                ep = nth(runs(o), rank[0])
                o = np.zeros(t, bool)
                if ep:
                    o[ep[0]:ep[1] + 1] = True
            row = relate(row, o, word)
        frames[k] = row
    eps = {k: runs(frames[k]) for k in subj}
    form, n = spec["form"], spec["n"]
    if form == "ordinal-objects":
        first = {k: next((s for s, _ in eps[k] if s >= LEAD), None) for k in subj}
        order = sorted([k for k in subj if first[k] is not None], key=lambda k: first[k])
        k = order[-1] if n == -1 else order[n - 1]
        return k, [next(e for e in eps[k] if e[0] >= LEAD)], None
    if form == "ordinal-episodes":
        k = subj[0]
        ep = nth(eps[k], n)
        return k, [ep] if ep else [], None
    if form == "count":
        k = subj[0]
        return k, eps[k], len(eps[k])
    if form == "count-select":
        cnt = {k: len(eps[k]) for k in subj}
        if spec["quantity"] == "count":
            pick = max if spec["direction"] == "max" else min
            k = pick(subj, key=lambda j: cnt[j])
        else:
            k = next(j for j in subj if cnt[j] == n)
        return k, eps[k], cnt[k]
    if form == "negation":
        k = next(j for j in subj if not frames[j].any())
        return k, [(0, t - 1)], None
    if form == "relation":
        k = subj[0]
        return k, eps[k], None
    # extremes
    sign = 1.0 if spec["direction"] == "max" else -1.0
    best = {}
    for k in subj:
        if spec["quantity"] == "duration":
            c = [((e - s + 1) * sign, (s, e)) for s, e in eps[k]]
        elif spec["atoms"]:
            q = height[k] if spec["quantity"] == "height" else speed[k]
            vertical = spec["quantity"] == "height" and set(spec["atoms"]) <= {"rising",
                                                                                 "falling"}
            c = [((abs(q[e] - q[s]) if vertical else
                   (q[s:e + 1].max() if sign > 0 else q[s:e + 1].min())) * sign, (s, e))
                 for s, e in eps[k]]  # fmt: skip
        else:
            q = height[k] if spec["quantity"] == "height" else speed[k]
            f = int(np.argmax(q) if sign > 0 else np.argmin(q))
            c = [(float(q[f]) * sign, around(q, f, spec["direction"]))]
        best[k] = max(c) if c else (-np.inf, None)
    k = max(subj, key=lambda j: best[j][0])
    return k, [best[k][1]] if best[k][1] else [], None
