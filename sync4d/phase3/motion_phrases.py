"""Motion phrases (beyond the paper): queries that name motion, grounded on the kinematics.

The paper's scorer finds states that change an object's *appearance* in its crops; "falling",
"at rest" or "approaching the blue ball" change none. Here a small vocabulary of predicates is
evaluated frame by frame on the field's kinematic features (Appendix B), M_phi's centroids and
the contact gaps, and matched to the query text:

* a predicate matches when one of its phrases occurs in the query (whole words, longest phrase
  first, a span used once), or, failing any literal match, when the text encoder's similarity of
  a query n-gram (1-3 words) to a phrase reaches `phrase_match`;
* relational predicates (approaching, moving away from, touching) take the object named after
  the phrase ("approaching *the blue ball*"): a background word (ground, floor, plate, table,
  background) means the background (label 0); otherwise the object whose name occurs in the
  text, else the one whose name (or static embedding, when objects are unnamed) the text encoder
  finds nearest; no target means any other object or the background;
* motion is read from M_phi's centroids smoothed in time by a Gaussian of `phrase_smooth`
  (normalised time; the paper's per-frame features stay raw): finite differences of a
  reconstruction's per-frame table flip sign from frame to frame (bouncingballs: vertical
  velocity -2.3, -0.5, -1.5 on consecutive frames of one fall);
* speeds are compared with the scene's reference speed s_ref (95th percentile of every object's
  speed), with a floor for static scenes; "up" is the field's up vector; "left"/"right" are
  along the first training camera's image x axis;
* "touching" is a contact, which the run's one state model decides (`sync4d.phase3.states`:
  `states.holds` evaluates a matched predicate, contacts there and every other one here).

Each predicate gives a bool per object and frame; matched predicates are combined with AND; a
state holds over an interval: one-frame gaps are closed and runs shorter than
`phrase_min_frames` dropped.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["BACKGROUND_WORDS", "PREDICATES", "MatchedPredicate", "Predicate", "clean_runs",
           "evaluate", "match_predicates", "smooth_in_time", "smoothed_motion"]  # fmt: skip

#: Words that name the background (label 0) as a relation target.
BACKGROUND_WORDS = ("ground", "floor", "plate", "table", "background", "surface", "scene")


@dataclass(frozen=True)
class Predicate:
    """A motion predicate: its `name`, the `phrases` that name it and whether it takes a
    target object (`relational`)."""

    name: str
    phrases: tuple[str, ...]
    relational: bool = False


PREDICATES: tuple[Predicate, ...] = (
    Predicate("rising", ("rising", "going up", "moving up", "ascending", "flying up",
                         "bouncing up", "jumping", "lifted", "rises")),
    Predicate("falling", ("falling", "dropping", "going down", "moving down", "descending",
                          "coming down", "falls", "drops")),
    Predicate("at rest", ("at rest", "standing still", "not moving", "stationary", "still",
                          "resting", "motionless", "static", "stopped")),
    Predicate("moving left", ("moving left", "going left", "to the left")),
    Predicate("moving right", ("moving right", "going right", "to the right")),
    Predicate("turning", ("turning", "rotating", "spinning")),
    Predicate("fastest", ("the fastest", "fastest", "quickest", "moving the most")),
    Predicate("slowest", ("the slowest", "slowest", "moving the least")),
    Predicate("moving", ("moving", "in motion", "sliding", "travelling", "traveling",
                         "rolling", "slides", "moves")),
    Predicate("approaching", ("approaching", "moving towards", "moving toward",
                              "getting closer to", "coming closer to", "closing in on"),
              relational=True),
    Predicate("moving away", ("moving away from", "receding from", "getting farther from",
                              "leaving"), relational=True),
    Predicate("touching", ("touching", "in contact with", "on the ground", "hitting",
                           "bouncing on", "landing on", "lying on", "resting on", "on"),
              relational=True),
)  # fmt: skip


@dataclass
class MatchedPredicate:
    """A predicate matched in a query: the `phrase` found (or its nearest phrase), the match
    `similarity` (1.0 for a literal match), the `target` text after it and the target label
    (None: any)."""

    predicate: Predicate
    phrase: str
    similarity: float
    target_text: str = ""
    target: int | None = None


def _words(text: str) -> list[str]:
    return re.findall(r"[a-z0-9']+", text.lower())


def _find(words: list[str], phrase: list[str], used: list[bool]) -> int:
    """Start of the first unused occurrence of `phrase` in `words`, -1 if none."""
    n = len(phrase)
    for i in range(len(words) - n + 1):
        if words[i:i + n] == phrase and not any(used[i:i + n]):
            return i
    return -1


def _target_text(words: list[str], start: int, used: list[bool]) -> str:
    """The words after a relational phrase up to the next used word (the target's name)."""
    out = []
    for j in range(start, len(words)):
        if used[j]:
            break
        out.append(words[j])
    return " ".join(out)


def match_predicates(
    query: str, similarity: Callable[[list[str], list[str]], np.ndarray] | None = None,
    threshold: float = 0.8,
) -> tuple[list[MatchedPredicate], str]:  # fmt: skip
    """(matched predicates, the rest of the query) of `query`. Literal phrase matches first
    (longest phrase first); when none matches and `similarity(ngrams, phrases)` (a matrix of
    text-encoder similarities) is given, the best n-gram-phrase pair at or above `threshold`.
    The rest is the query without the matched phrases and their targets (the identity text).
    A bare "on" counts only with a target (it is too common a word otherwise)."""
    words = _words(query)
    used = [False] * len(words)
    found: list[tuple[int, int, MatchedPredicate]] = []
    pairs = sorted(((len(_words(ph)), ph, p) for p in PREDICATES for ph in p.phrases),
                   key=lambda x: -x[0])  # fmt: skip
    for n, ph, p in pairs:
        if any(m.predicate.name == p.name for _, _, m in found):
            continue
        i = _find(words, _words(ph), used)
        if i < 0:
            continue
        if ph == "on" and i + 1 >= len(words):
            continue
        for j in range(i, i + n):
            used[j] = True
        found.append((i, n, MatchedPredicate(p, ph, 1.0, target=0 if ph == "on the ground"
                                             else None)))
    if not found and similarity is not None and words:
        grams = [" ".join(words[i:i + n]) for n in (1, 2, 3) for i in range(len(words) - n + 1)]
        flat = [(ph, p) for p in PREDICATES for ph in p.phrases if ph != "on"]
        sims = np.asarray(similarity(grams, [ph for ph, _ in flat]))
        gi, pi = np.unravel_index(int(np.argmax(sims)), sims.shape)
        if sims[gi, pi] >= threshold:
            gw = grams[gi].split()
            i = _find(words, gw, used)
            for j in range(i, i + len(gw)):
                used[j] = True
            found.append((i, len(gw), MatchedPredicate(flat[pi][1], flat[pi][0],
                                                       float(sims[gi, pi]))))
    for i, n, m in found:
        if m.predicate.relational and m.target is None:
            m.target_text = _target_text(words, i + n, used)
            if m.target_text:
                for j in range(i + n, i + n + len(m.target_text.split())):
                    used[j] = True
    found = [f for f in found if not (f[2].phrase == "on" and not f[2].target_text)]
    rest = " ".join(w for w, u in zip(words, used, strict=True) if not u)
    return [m for _, _, m in sorted(found, key=lambda x: x[0])], rest


def smooth_in_time(x: np.ndarray, times: np.ndarray, sigma: float) -> np.ndarray:
    """`x` [K, T, ...] smoothed along T by a local linear fit with Gaussian weights of `sigma`
    (normalised time) at each frame time: unevenly spaced frames are fine and a linear motion is
    kept exactly (a plain weighted mean would bend it where frames cluster); `sigma` 0 returns
    `x`."""
    if sigma <= 0 or x.shape[1] < 2:
        return x
    d = times[None, :] - times[:, None]  # [t, s]: s's offset from t
    w = np.exp(-0.5 * (d / sigma) ** 2)
    s0, s1, s2 = w.sum(1), (w * d).sum(1), (w * d * d).sum(1)
    det = s0 * s2 - s1 * s1
    flat = det <= 1e-12 * np.maximum(s0 * s2, 1e-300)
    # weights of the fitted intercept: (s2 - s1 d) w / det; the weighted mean where it is flat
    lin = (s2[:, None] - s1[:, None] * d) * w / np.where(flat, 1.0, det)[:, None]
    mean = w / s0[:, None]
    coef = np.where(flat[:, None], mean, lin)
    return np.einsum("ts,ks...->kt...", coef, x)


def clean_runs(active: np.ndarray, min_frames: int) -> np.ndarray:
    """`active` [K, T] with one-frame gaps inside a run closed and then runs shorter than
    `min_frames` dropped: a state holds over an interval, not for a flickering frame."""
    out = active.copy()
    t = out.shape[1]
    for row in out:
        for f in range(1, t - 1):
            if not row[f] and row[f - 1] and row[f + 1]:
                row[f] = True
        f = 0
        while f < t:
            if row[f]:
                g = f
                while g < t and row[g]:
                    g += 1
                if g - f < min_frames:
                    row[f:g] = False
                f = g
            else:
                f += 1
    return out


def evaluate(
    m: MatchedPredicate, features: np.ndarray, centroids: np.ndarray, labels: list[int],
    radius: np.ndarray, up: np.ndarray, right: np.ndarray, times: np.ndarray, cfg,
) -> np.ndarray:  # fmt: skip
    """Truth of predicate `m` per object and frame [K, T] (bool). `features` [K, T, 28],
    `centroids` [K, T, 3] (M_phi's), `labels` [K] the objects' labels, `radius` [K], `up` and
    `right` [3] unit vectors, `times` [T], `cfg` a Phase3Config. Motion is read from the
    centroids smoothed in time (`cfg.phrase_smooth`), and the result keeps only runs of
    `cfg.phrase_min_frames`. Touching is a contact: `sync4d.phase3.states` reads it."""
    raw = _evaluate(m, features, centroids, labels, radius, up, right, times, cfg)
    return clean_runs(raw, cfg.phrase_min_frames)


def smoothed_motion(
    centroids: np.ndarray, times: np.ndarray, radius: np.ndarray, sigma: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """What the predicates read of the motion: the centroids [K, T, 3] smoothed in time by
    `sigma` (`smooth_in_time`), their velocity [K, T, 3] (world units per unit time) and the
    scene's reference speed s_ref (95th percentile of every object's speed, at least 5 % of
    the median object `radius` [K] per unit time, so a still scene has no motion)."""
    t = centroids.shape[1]
    c = smooth_in_time(centroids, times, sigma)
    vel = np.gradient(c, times, axis=1, edge_order=2 if t >= 3 else 1) if t > 1 \
        else np.zeros_like(c)
    speed = np.linalg.norm(vel, axis=-1)
    floor = 0.05 * float(np.median(radius)) if len(radius) else 1e-3
    s_ref = max(float(np.percentile(speed, 95)) if speed.size else 0.0, floor)
    return c, vel, s_ref


def _evaluate(m, features, centroids, labels, radius, up, right, times, cfg):
    k, t = centroids.shape[:2]
    c, vel, s_ref = smoothed_motion(centroids, times, radius, cfg.phrase_smooth)
    speed = np.linalg.norm(vel, axis=-1)
    name = m.predicate.name
    if name == "moving":
        return speed > cfg.moving_speed * s_ref
    if name == "at rest":
        return speed < cfg.rest_speed * s_ref
    if name in ("rising", "falling"):
        vu = vel @ up
        sign = 1.0 if name == "rising" else -1.0
        return sign * vu > cfg.vertical_speed * s_ref
    if name in ("moving left", "moving right"):
        vr = vel @ right
        sign = 1.0 if name == "moving right" else -1.0
        return sign * vr > cfg.moving_speed * s_ref
    if name == "turning":
        return smooth_in_time(features[..., 2], times, cfg.phrase_smooth) > 0.5
    if name in ("fastest", "slowest"):
        pick = speed.max(0) if name == "fastest" else speed.min(0)
        moving = speed > cfg.moving_speed * s_ref
        return (speed >= pick[None]) & (moving if name == "fastest" else True)
    if name in ("approaching", "moving away"):
        if m.target is None or m.target == 0 or m.target not in labels:
            if m.target not in (None, 0):
                return np.zeros((k, t), bool)
            d = np.linalg.norm(c[:, None] - c[None, :], axis=-1)
            d[np.arange(k), np.arange(k)] = np.inf
            d = d.min(1) if k > 1 else np.zeros((k, t))
            tgt = None
        else:
            tgt = labels.index(m.target)
            d = np.linalg.norm(c - c[tgt][None], axis=-1)
        closing = np.gradient(d, times, axis=1) if t > 1 and np.isfinite(d).all() \
            else np.zeros((k, t))
        sign = -1.0 if name == "approaching" else 1.0
        out = sign * closing > cfg.closing_speed * s_ref
        if tgt is not None:
            out[tgt] = False
        return out
    if name == "touching":
        raise ValueError("touching is a contact: sync4d.phase3.states.contact reads it")
    raise ValueError(f"unknown predicate {name!r}")
