"""What the operators read: per object and frame, the height, the speed and each atom's
activation (`Timeline`), the clause's frames (`clause_active`), the relation between two
clauses (`relate`), and the episodes and peaks the forms select from. The field's own
timeline (M_phi's motion, the states and contacts of `sync4d.phase3.states`) is
`field_timeline`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3 import states
from sync4d.phase3.activation import intervals
from sync4d.phase3.relational.words import FLAT

if TYPE_CHECKING:
    from sync4d.phase3.relational.plan import Atom, Clause
    from sync4d.phase3.store import Field

__all__ = ["Timeline", "clause_active", "episodes", "field_timeline", "nth_episode", "peak_run",
           "relate", "span"]


@dataclass
class Timeline:
    """What the operators read, per object k and frame f: `times` [T], `height` and `speed`
    [K, T], and `activation(atom, k)` -> bool [T] of an atom (set by the caller: the field's
    predicates, or the true states of an evaluation set)."""

    times: np.ndarray
    height: np.ndarray
    speed: np.ndarray
    activation: object  # Callable[[Atom], np.ndarray [K, T]]
    #: Gaps shorter than this many frames inside a clause's episodes are closed (an episode
    #: is not two because a slow motion dips under a threshold for a frame or two).
    merge: int = 0

    def onset_frames(self) -> int:
        """The first frame an onset can be at: a state needs to be absent for `merge`
        frames (the shortest state) before it begins, so an episode that starts earlier was
        under way when the clip began (at least 1: frame 0 is never an onset)."""
        return max(1, self.merge)


def episodes(row: np.ndarray) -> list[tuple[int, int]]:
    """The runs of true frames of `row` [T], inclusive (start, end)."""
    return intervals(np.asarray(row, bool))


def clause_active(c: Clause, tl: Timeline) -> np.ndarray:
    """Frames [K, T] where clause `c` holds: its atoms (AND), negated when it says so, gaps
    shorter than `tl.merge` closed."""
    k, t = tl.height.shape
    act = np.ones((k, t), bool)
    for a in c.atoms:
        act &= np.asarray(tl.activation(a), bool)
    act = ~act if c.negated else act
    for row in act:
        eps = episodes(row)
        for (_, e), (s, _) in zip(eps, eps[1:], strict=False):
            if s - e - 1 < tl.merge:
                row[e:s] = True
    return act


def relate(a: np.ndarray, b: np.ndarray, word: str, lead: int = 1) -> np.ndarray:
    """Frames [T] of `a` [T] in relation `word` to `b` [T]: while / during: both; before /
    until: before the first onset of `b` (an episode that starts at frame `lead` or later);
    after: from that onset on (after the end of `b`'s first episode when it has no onset)."""
    if word in ("while", "during"):
        return a & b
    iv = intervals(b)
    t = len(a)
    idx = np.arange(t)
    onsets = [s for s, _ in iv if s >= lead]
    if word in ("before", "until"):
        return a & (idx < onsets[0]) if onsets else np.zeros(t, bool)
    if word == "after":
        if onsets:
            return a & (idx >= onsets[0])
        return a & (idx > iv[0][1]) if iv else np.zeros(t, bool)
    raise ValueError(f"unknown relation {word!r}")


def nth_episode(row: np.ndarray, n: int | None, after: int = -1) -> tuple[int, int] | None:
    """Episode `n` of `row` [T] (1-based, -1 the last; None: the first that starts after
    frame `after`), None when there is no such episode."""
    eps = episodes(row)
    if n is None:
        return next((ep for ep in eps if ep[0] > after), None)
    if n == -1:
        return eps[-1] if eps else None
    return eps[n - 1] if 0 < n <= len(eps) else None


def span(x: np.ndarray, y: np.ndarray | None, word: str, nx: int | None = None,
         ny: int | None = None) -> np.ndarray:
    """Frames [T] of "between X and Y" (after X's episode ends, before Y's begins) or "from X
    to Y" (from X's start to Y's end) for the activations `x`, `y` [T]: X's episode `nx`
    (default its first), Y's episode `ny` (default its first one after X's). Without `y`,
    "between" is every gap between two consecutive episodes of `x` ("between bounces")."""
    t = len(x)
    out = np.zeros(t, bool)
    if y is None:
        eps = episodes(x)
        for (_, e), (s, _) in zip(eps, eps[1:], strict=False):
            out[e + 1:s] = True
        return out
    first = nth_episode(x, nx)
    if first is None:
        return out
    second = nth_episode(y, ny, first[1] if word == "between" else first[0] - 1)
    if second is None:
        return out
    if word == "between":
        out[first[1] + 1:second[0]] = True
    else:
        out[first[0]:second[1] + 1] = True
    return out


def peak_run(q: np.ndarray, direction: str, scale: float = 0.0) -> tuple[float, tuple[int, int]]:
    """(extreme value, the run around it on its side of the mid-range) of `q` [T]; the whole
    clip when `q` varies by at most `FLAT` of `scale` (the largest range among the compared
    objects): a still object's speed or height has no peak but its noise."""
    f = int(np.argmax(q) if direction == "max" else np.argmin(q))
    lo, hi = float(q.min()), float(q.max())
    side = q >= lo + 0.5 * (hi - lo) if direction == "max" else q <= lo + 0.5 * (hi - lo)
    if hi - lo <= FLAT * scale or hi == lo:
        side = np.ones_like(q, bool)
    for s, e in episodes(side):
        if s <= f <= e:
            return float(q[f]), (s, e)
    return float(q[f]), (f, f)


# --- the field's timeline --------------------------------------------------------------------


#: Approaching / moving away from the background is falling / rising (the scene
#: description's approach and separation events with the background: the height changes).
_TOWARDS_GROUND = {"approaching": "falling", "moving away": "rising"}


def field_timeline(field: Field, cfg) -> Timeline:
    """The timeline of `field`: M_phi's smoothed centroid height and speed, and the atoms
    read from the run's one state model (`sync4d.phase3.states`: motion states, contacts)."""
    c, vel, _ = mp.smoothed_motion(field.centroids, field.times, field.radius,
                                   cfg.phrase_smooth)  # fmt: skip
    memo: dict[tuple[str, int | None], np.ndarray] = {}

    def activation(a: Atom) -> np.ndarray:
        key = (a.name, a.target)
        if key not in memo:
            if a.name == "contact":
                memo[key] = states.contact(field, cfg, a.target)
            else:
                name = a.name
                if a.target == 0 and name in _TOWARDS_GROUND:
                    name = _TOWARDS_GROUND[name]
                memo[key] = states.motion_state(field, cfg, name, a.target)
        return memo[key]

    return Timeline(np.asarray(field.times), c @ field.up, np.linalg.norm(vel, axis=-1),
                    activation, int(cfg.phrase_min_frames))  # fmt: skip
