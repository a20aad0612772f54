"""One model of what happens in a run: every object's motion states and contacts, per frame.

Every reader of *when* something happens reads this module: `query`'s motion phrases (the full
scorer), the relational grammar's atoms (`sync4d.phase3.relational`), the scene description's
segments and events (`sync4d.export.describe`, and through it the prompt and the MCP tools)
and the viewer (through `query`). So "the green ball touching the plate", "the green ball while
it touches the plate" and the description's contact event give one interval.

Design notes
------------
* **Motion states** (per object and frame, bool [K, T]): at rest, moving, rising, falling,
  turning, moving left / right, approaching, moving away, fastest, slowest; the predicates of
  `motion_phrases` on M_phi's centroids smoothed in time, with the field's thresholds
  (fractions of the scene's reference speed; runs shorter than `phrase_min_frames` dropped).
* **Contact with the background** (label 0) is decided and timed from the object's geometry
  against the surface under it: `gaps[:, 0]` is the height of the object's lowest points (the
  5th percentile of its Gaussians' heights) above the median height of the background under
  it (`observe._support_gap`), smoothed in time like the motion.
  - *Whether*: the gap closes below `contact_gap` object radii while the object is near its
    lowest height over the clip (resting, rolling, sliding: evidence "gap"), or the object
    comes down and goes back up (a fall, then a rise) at a turn near its lowest height
    (within max(`contact_gap` radii, `rebound_height` of its height range)) where the gap is
    at most `rebound_gap` radii (evidence "rebound": a reconstruction leaves a small ball's
    lowest Gaussians above the plate's surface Gaussians at the bounce, so the measured gap
    stays open by a fraction of a radius; a pendulum's or a jump's turn in mid-air is no
    contact).
  - *How long*: from the frame the gap (and the centroid's height: plate Gaussians that cling
    to a ball keep its gap closed in the air) comes within `contact_band` radii of its value
    at the turn (onset) to the frame it leaves that band (offset), so a slow bounce or a roll
    lasts longer than a quick bounce, and a ball that comes to rest stays in contact; a run of
    closed gap around a turn is no contact of its own (the ball passing near the surface).
  Every threshold is in world units: a multiple of the object's own radius (`Field.radius`,
  the median distance of its canonical Gaussians from their centroid).
* **Contact between two objects**: the robust surface-to-surface gap (`observe._robust_gap`,
  either way round, the smaller) below `contact_gap` radii of the object it is measured from.
* **Contacts** (`Contact`) are the runs of contact with their onset, offset and duration; the
  scene description's contact events are these runs.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3.activation import intervals
from sync4d.phase3.config import Phase3Config

if TYPE_CHECKING:
    from sync4d.phase3.store import Field

__all__ = ["CONTACT_DEFAULTS", "MOTION_STATES", "Contact", "contact", "contacts", "holds",
           "motion_state", "settings", "support_gap"]  # fmt: skip

#: The motion states a description lists per object, in its order.
MOTION_STATES = ("at rest", "moving", "rising", "falling", "turning")

#: The contact settings beside `contact_gap` (`Phase3Config`), with their defaults, which a
#: field built before they were settings of its own is read with.
CONTACT_DEFAULTS = {k: getattr(Phase3Config, k) for k in ("contact_band", "rebound_gap",
                                                          "rebound_height")}


@dataclass(frozen=True)
class Contact:
    """A contact of object `label` with `other` (0: the background) over the inclusive frames
    [`start`, `end`] (times `t0`, `t1`, normalised); `evidence` "gap" (the gap closed) or
    "rebound" (a fall turned into a rise at the surface, the gap left open); `turn` the frame
    of a bounce's lowest point (-1 for a contact without one)."""

    label: int
    other: int
    start: int
    end: int
    t0: float
    t1: float
    evidence: str
    turn: int = -1

    @property
    def frames(self) -> int:
        """How many stored frames the contact spans."""
        return self.end - self.start + 1


def settings(cfg) -> dict[str, float]:
    """The contact settings of `cfg` (a Phase3Config or a field's settings), with the defaults
    for a field built before they existed."""
    return {k: float(getattr(cfg, k, v)) for k, v in CONTACT_DEFAULTS.items()}


def _by_name(name: str) -> mp.Predicate:
    return next(p for p in mp.PREDICATES if p.name == name)


def holds(field: Field, m: mp.MatchedPredicate, cfg) -> np.ndarray:
    """Frames [K, T] where the matched predicate `m` holds (what a query's motion phrase
    reads): contacts from this module, every other state from `motion_phrases`."""
    if m.predicate.name == "touching":
        return contact(field, cfg, m.target)
    return mp.evaluate(m, field.features, field.centroids, field.labels, field.radius,
                       field.up, field.right, field.times, cfg)  # fmt: skip


def motion_state(field: Field, cfg, name: str, target: int | None = None) -> np.ndarray:
    """Frames [K, T] of state `name` (a `motion_phrases` predicate; `target`: the other object
    of approaching / moving away / touching, 0 the background, None any)."""
    return holds(field, mp.MatchedPredicate(_by_name(name), name, 1.0, target=target), cfg)


def support_gap(field: Field, k: int) -> np.ndarray | None:
    """Object k's height above the background surface under it [T] (`gaps[:, 0]`), the frames
    where it was not measured interpolated in time; None when it never was (or the field has
    no background gap)."""
    gl = list(field.gap_labels)
    if 0 not in gl:
        return None
    g = np.asarray(field.gaps[k, gl.index(0)], np.float64)
    ok = np.isfinite(g)
    if not ok.any():
        return None
    times = np.asarray(field.times, np.float64)
    return np.where(ok, g, np.interp(times, times[ok], g[ok]))


def _turns(height: np.ndarray, vertical: np.ndarray, s_ref: float, cfg) -> list[int]:
    """Frames where the height [T] stops falling and starts rising: the lowest frame between a
    fall run and the next rise run of the vertical velocity `vertical` [T] (beyond
    `vertical_speed` s_ref, as "falling" and "rising" read it)."""
    if len(height) < 3:
        return []
    minf = int(cfg.phrase_min_frames)
    fall = mp.clean_runs((-vertical > cfg.vertical_speed * s_ref)[None], minf)[0]
    rise = mp.clean_runs((vertical > cfg.vertical_speed * s_ref)[None], minf)[0]
    rises = intervals(rise)
    out = []
    for _, e in intervals(fall):
        nxt = [s for s, _ in rises if s > e]
        if nxt:
            out.append(e + int(np.argmin(height[e:nxt[0] + 1])))
    return out


def _band(f: int, width: float, *series: np.ndarray) -> tuple[int, int]:
    """The run of frames around `f` where every one of `series` ([T] each) stays within `width`
    above its value at `f`."""
    def within(i: int) -> bool:
        return all(x[i] <= x[f] + width for x in series)

    s = e = f
    t = len(series[0])
    while s > 0 and within(s - 1):
        s -= 1
    while e < t - 1 and within(e + 1):
        e += 1
    return s, e


def ground_contacts(field: Field, cfg) -> list[Contact]:
    """Each object's contacts with the background (see the module notes), in time order."""
    times = np.asarray(field.times, np.float64)
    c, vel, s_ref = mp.smoothed_motion(field.centroids, times, field.radius,
                                       cfg.phrase_smooth)  # fmt: skip
    up = np.asarray(field.up, np.float64)
    st = settings(cfg)
    minf = int(cfg.phrase_min_frames)
    out: list[Contact] = []
    for k, label in enumerate(field.labels):
        r = float(field.radius[k])
        h = c[k] @ up
        near_low = max(cfg.contact_gap * r, st["rebound_height"] * float(np.ptp(h)))
        raw = support_gap(field, k)
        # the surface is measured: its gap; else the height over the lowest (a flat floor)
        g = mp.smooth_in_time(raw[None], times, cfg.phrase_smooth)[0] if raw is not None \
            else h - h.min()
        mask = np.zeros(len(times), bool)
        found: list[tuple[int, int, str, int]] = []
        for f in _turns(h, vel[k] @ up, s_ref, cfg):
            if h[f] - h.min() > near_low or g[f] > st["rebound_gap"] * r:
                continue  # a turn in mid-air
            # the gap and the centroid's height both (plate Gaussians that cling to a ball
            # keep its gap closed in the air; its centroid still rises)
            s, e = _band(f, st["contact_band"] * r, g, h)
            if mask[s:e + 1].any():
                continue  # the same contact seen from a second turn
            mask[s:e + 1] = True
            closes = float(np.min(g[s:e + 1])) < cfg.contact_gap * r
            found.append((s, e, "gap" if closes else "rebound", f))
        closed = (g < cfg.contact_gap * r) & (h - h.min() <= near_low)
        for s, e in intervals(mp.clean_runs(closed[None], minf)[0]):
            if mask[s:e + 1].any():
                continue  # a closed gap around a rebound: the rebound's band holds what rests
            found.append((s, e, "gap", -1))
        for s, e, ev, f in sorted(found):
            out.append(Contact(int(label), 0, s, e, float(times[s]), float(times[e]), ev, f))
    return out


def object_contacts(field: Field, cfg) -> list[Contact]:
    """Contacts between two objects (label < other), in time order: the robust gap either way
    round below `contact_gap` radii of the object it is measured from."""
    times = np.asarray(field.times, np.float64)
    gl, labels = list(field.gap_labels), list(field.labels)
    minf = int(cfg.phrase_min_frames)
    out: list[Contact] = []
    for k, a in enumerate(labels):
        for j in range(k + 1, len(labels)):
            b = labels[j]
            rel = np.full(len(times), np.inf)
            for x, y, r in ((k, b, field.radius[k]), (j, a, field.radius[j])):
                if y in gl:
                    g = np.asarray(field.gaps[x, gl.index(y)], np.float64)
                    rel = np.minimum(rel, np.where(np.isfinite(g), g / (cfg.contact_gap * r),
                                                   np.inf))  # fmt: skip
            for s, e in intervals(mp.clean_runs((rel < 1.0)[None], minf)[0]):
                out.append(Contact(int(a), int(b), s, e, float(times[s]), float(times[e]),
                                   "gap"))  # fmt: skip
    return out


def contacts(field: Field, cfg) -> list[Contact]:
    """Every contact of the run (with the background, then between objects), by start."""
    out = ground_contacts(field, cfg) + object_contacts(field, cfg)
    return sorted(out, key=lambda x: (x.start, x.other != 0, x.label, x.other))


def contact(field: Field, cfg, target: int | None = None) -> np.ndarray:
    """Frames [K, T] where each object touches `target` (0: the background; a label: that
    object; None: anything), from `contacts`."""
    labels = list(field.labels)
    out = np.zeros((len(labels), len(field.times)), bool)
    pool = ground_contacts(field, cfg) if target == 0 else contacts(field, cfg)
    for x in pool:
        for me, other in ((x.label, x.other), (x.other, x.label)):
            if me not in labels or (target is not None and other != target):
                continue
            out[labels.index(me), x.start:x.end + 1] = True
    return out
