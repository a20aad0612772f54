"""The run's one state model (`sync4d.phase3.states`): a state asked as a motion phrase, as a
relation and read from the scene description gives one interval; contacts last as long as the
geometry says (a slow landing longer than a quick bounce, a ball at rest throughout); a turn in
mid-air is no contact."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from support.fields import NAMES, T, bouncing_field
from sync4d.export.describe import motion_segments, pairwise_events
from sync4d.phase3 import states
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import load_encoder
from sync4d.phase3.query import TextCache, answer

#: (phrase, the same state said as a relation's clause, where the description has it)
WAYS = [("touching the ground", "touches the ground", "contact"),
        ("rising", "is rising", "rising"),
        ("falling", "is falling", "falling")]  # fmt: skip


@pytest.fixture(scope="module")
def bb(tmp_path_factory):
    enc = load_encoder("offline")
    field = bouncing_field(enc)
    return field, TextCache(tmp_path_factory.mktemp("states"), field, enc)


def _frames(intervals) -> list[tuple[int, int]]:
    return [(iv["start"], iv["end"]) for iv in intervals]


def _of(ans: dict, name: str) -> list[tuple[int, int]]:
    return _frames(next(o for o in ans["objects"] if o["name"] == name)["intervals"])


@pytest.mark.parametrize("ball", NAMES)
@pytest.mark.parametrize("phrase, clause, exported", WAYS)
def test_one_state_asked_three_ways_is_one_interval(bb, ball, phrase, clause, exported):
    field, cache = bb
    cfg = Phase3Config()
    k = NAMES.index(ball)
    plain = answer(field, f"the {ball} {phrase}", cache=cache)
    assert plain["plan"] is None  # the motion phrase, read by the full scorer
    relation = answer(field, f"the {ball} while it {clause}", cache=cache)
    assert relation["plan"].startswith("while(") and relation["objects"][0]["name"] == ball
    if exported == "contact":
        desc = [(e["start"], e["end"]) for e in pairwise_events(field, cfg)
                if e["kind"] == "contact" and e["objects"] == [field.labels[k], 0]]
    else:
        desc = [(s["start"], s["end"]) for s in motion_segments(field, cfg)[k]
                if s["state"] == exported]
    assert _of(plain, ball) == _frames(relation["objects"][0]["intervals"]) == desc, (
        plain["objects"], relation["objects"][0], desc)


def test_contacts_last_as_long_as_the_geometry_says():
    """A ball that lands slowly (its last frames within `contact_band` radii of the plate for
    longer) gets a longer contact than a quick bounce; the resting ball touches throughout."""
    field = bouncing_field(load_encoder("offline"))
    cfg = Phase3Config()
    quick = {x.label: x for x in states.ground_contacts(field, cfg) if x.turn == 36}
    c = field.centroids.copy()
    # the green ball's bounce at frame 36 flattened: within 0.003 (0.03 radii) for 7 frames
    c[1, 33:40, 2] = 0.1 + 0.001 * np.abs(np.arange(-3, 4))
    gaps = field.gaps.copy()
    gaps[1, 0] = c[1, :, 2] - 0.1
    slow = dataclasses.replace(field, centroids=c, gaps=gaps)
    slow_contact = [x for x in states.ground_contacts(slow, cfg) if x.label == 2]
    assert len(slow_contact) == 1 and slow_contact[0].frames > quick[2].frames
    assert 33 <= slow_contact[0].start and slow_contact[0].end <= 39, slow_contact
    rest = [x for x in states.ground_contacts(field, cfg) if x.label == 3]
    assert [(x.start, x.end, x.evidence) for x in rest] == [(0, T - 1, "gap")]


def test_a_field_without_the_contact_settings_reads_the_defaults():
    """A field built before `contact_band` and the rebound settings were Phase 3 settings is
    read with their defaults."""
    old = {k: v for k, v in vars(Phase3Config()).items() if k not in states.CONTACT_DEFAULTS}
    from types import SimpleNamespace

    assert states.settings(SimpleNamespace(**old)) == states.CONTACT_DEFAULTS
