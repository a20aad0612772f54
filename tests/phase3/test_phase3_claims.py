"""The paper's central Phase 3 claim as a test: kinematic conditioning carries an object's state
where observation cannot (Sec. 3.5: "under prolonged occlusion, the kinematic prediction serves
as the sole embedding"; Table 5: tIoU 0.733 against 0.279 static-only on HyperNeRF).

The scene: the embedded scene at 41 frames whose box turns yellow while it slides
(`SyntheticConfig.sliding_colour`), so its appearance follows its motion. The box is hidden at
some frames, at rest and mid-slide (`HIDDEN`): no crop there and a visible fraction of 0, as an
occluder in every view gives. Only e_hat can say "yellow" at the hidden slide frames, and only
from the kinematics (speed, acceleration ...), since the ridge map is fitted on the seen frames.
A field that sees every frame would not test this: with 29 ridge inputs e_hat reproduces the
observation, and the paper's scorer then only shows that observing beats a constant.

Scored with the paper's own scorer (Eq. 15 on e_sync, no motion phrases) for "a yellow box":
the paper's field (default: features clipped to their seen range at unseen frames), Eq. 14
as written (`clip_unobserved = false`), the W = 0 ablation (`kinematics = false`, scorer
``no-kinematics``: observations kept, no kinematic term) and the static-only ablation. Oracle
Phase 2 run, the offline encoder (it sees colours). The numbers are in docs/results/phase3.md
("The kinematic claim"); ``SYNC4D_CLAIMS_RECORD=FILE`` writes them, with a sweep over other
hidden sets, as that page's JSON record."""

from __future__ import annotations

import dataclasses
import datetime
import json
import os
import platform

import numpy as np
import pytest

from support.oracle import PHASE3_SCENE, oracle_phase2_run
from sync4d.data import synthetic as syn
from sync4d.phase3 import build as build_module
from sync4d.phase3.build import build_field
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import load_encoder
from sync4d.phase3.evaluation.query_metrics import temporal_iou
from sync4d.phase3.query import TextCache, answer

SCENE = dataclasses.replace(PHASE3_SCENE, frames=41, sliding_colour="yellow")
QUERY = "a yellow box"
BOX = 2  # the box's label
#: Time spans where the box is hidden: at rest, then in the middle of its slide.
HIDDEN = ((0.0, 0.15), (0.4, 0.6))
#: More hidden sets, for the record only (SYNC4D_CLAIMS_RECORD).
SWEEP = {
    "mid-slide 0.4-0.6": ((0.4, 0.6),),
    "slide 0.3-0.7": ((0.3, 0.7),),
    "rest 0-0.15 + slide 0.4-0.6": HIDDEN,
    "slide 0.4-0.6 + rest 0.85-1": ((0.4, 0.6), (0.85, 1.0)),
    "slide edges 0.15-0.3 + 0.7-0.85": ((0.15, 0.3), (0.7, 0.85)),
    "slide start 0.2-0.45 + rest 0.9-1": ((0.2, 0.45), (0.9, 1.0)),
}
#: The variants: (row name, scorer, config changes).
VARIANTS = (
    ("paper (clip_unobserved, the default)", "paper", {}),
    ("paper, Eq. 14 as written (clip_unobserved = false)", "paper", {"clip_unobserved": False}),
    ("W = 0 (kinematics = false)", "paper", {"kinematics": False}),
    ("static-only", "static", {}),
)


def _hidden_frames(times: np.ndarray, spans) -> np.ndarray:
    """[T] bool: the frames of `times` inside one of the time `spans`."""
    hide = np.zeros(len(times), bool)
    for a, b in spans:
        hide |= (times >= a - 1e-9) & (times <= b + 1e-9)
    return hide


class _Hiding:
    """`observe` of the build, computed once, with the box hidden at `spans`: unobserved, no
    crop, no box, a visible fraction of 0."""

    def __init__(self, original):
        self.original = original
        self.base = None
        self.spans = HIDDEN

    def __call__(self, *args, **kwargs):
        if self.base is None:
            self.base = self.original(*args, **kwargs)
        o = dataclasses.replace(self.base)
        j = o.labels.index(BOX)
        hide = _hidden_frames(o.times, self.spans)
        o.observed, o.visible, o.boxes = o.observed.copy(), o.visible.copy(), o.boxes.copy()
        o.observed[j, hide] = False
        o.visible[j, hide] = 0.0
        o.boxes[j, hide] = 0
        keep = [i for i, (a, f) in enumerate(o.crop_index) if not (a == j and hide[f])]
        o.crops = [o.crops[i] for i in keep]
        o.crop_index = [o.crop_index[i] for i in keep]
        return o


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("claims")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SYNC4D_CACHE", str(tmp / "cache"))
        enc = load_encoder("offline")
    run, _ = oracle_phase2_run(tmp, scene_config=SCENE)
    hiding = _Hiding(build_module.observe)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(build_module, "observe", hiding)
        fields = {changes_key(c): build_field(run, Phase3Config(**c), enc, threads=1)
                  for c in ({}, {"clip_unobserved": False}, {"kinematics": False})}  # fmt: skip
        hiding.spans = ()
        fields["seen"] = build_field(run, Phase3Config(), enc, threads=1)
    return run, enc, hiding, fields, TextCache(run.path, fields[""], enc)


def changes_key(changes: dict) -> str:
    return ",".join(f"{k}={v}" for k, v in sorted(changes.items()))


def _score(field, cache, scorer: str, rule: str, spans) -> dict:
    """tIoU of the top object's activation against the slide (0 when it is not the box) and
    the share of the hidden frames whose activation is right."""
    ans = answer(field, QUERY, cache=cache, scorer=scorer, rule=rule)
    top = ans["objects"][0]["name"]
    truth = (field.times >= syn.SLIDE[0] - 1e-9) & (field.times <= syn.SLIDE[1] + 1e-9)
    active = np.asarray(ans["active"][top], bool)
    hide = _hidden_frames(field.times, spans)
    right = top == "blue box"
    return {
        "top": top,
        "tiou": float(temporal_iou(active, truth)) if right else 0.0,
        "hidden_accuracy": (float(np.mean(active[hide] == truth[hide])) if right else 0.0)
        if hide.any() else None,
    }  # fmt: skip


def _table(fields: dict, cache) -> dict:
    rows = {}
    for name, scorer, changes in VARIANTS:
        f = fields[changes_key(changes)]
        rows[name] = {rule: _score(f, cache, scorer, rule, HIDDEN)
                      for rule in ("half-peak", "mean")}  # fmt: skip
        seen, both = fields["seen"], ("half-peak", "mean")
        if not changes.get("kinematics", True):  # the same ablation of the unhidden field
            rows[name]["all seen"] = {r: _score(seen, cache, "no-kinematics", r, ()) for r in both}
        elif changes:
            rows[name]["all seen"] = None  # the same field as the default's when all is seen
        else:
            rows[name]["all seen"] = {r: _score(seen, cache, scorer, r, ()) for r in both}
    return rows


def test_kinematics_carry_the_state_where_the_object_is_hidden(setup):
    run, enc, hiding, fields, cache = setup
    rows = _table(fields, cache)
    print("\n".join(f"{k}: {v}" for k, v in rows.items()))
    paper, literal, w0, static = (rows[name] for name, _, _ in VARIANTS)
    hp = "half-peak"
    assert all(r[rule]["top"] == "blue box" for r in rows.values() for rule in (hp, "mean"))
    # The paper's field finds the slide through the hidden frames; W = 0 and static-only
    # activate every frame under Appendix F's rule (their curves are nearly flat).
    assert paper[hp]["tiou"] >= 0.9 and paper[hp]["hidden_accuracy"] >= 0.9, rows
    assert paper[hp]["tiou"] - w0[hp]["tiou"] >= 0.25, rows
    assert paper[hp]["tiou"] - static[hp]["tiou"] >= 0.25, rows
    assert w0[hp]["hidden_accuracy"] <= 0.6  # e_static there: every hidden frame "yellow"
    # ... and under 4D LangSplat's mean rule, where W = 0's seen frames do count.
    assert paper["mean"]["tiou"] - w0["mean"]["tiou"] >= 0.1, rows
    # With nothing hidden the kinematic term adds nothing the mean rule can see: e_hat then
    # reproduces the observations (the old form of this test measured that).
    seen_paper, seen_w0 = paper["all seen"], w0["all seen"]
    assert seen_paper["half-peak"]["tiou"] >= 0.9
    assert seen_paper["mean"]["tiou"] == pytest.approx(seen_w0["mean"]["tiou"], abs=0.05)
    # Eq. 14 as written does not carry the state: the hidden box's visible fraction (dim 5)
    # is 0, far outside the seen range, and that one feature decides e_hat there. True today;
    # when it stops being true, docs/results/phase3.md must say so.
    assert literal[hp]["hidden_accuracy"] <= 0.6, rows
    record = os.environ.get("SYNC4D_CLAIMS_RECORD")
    if record:
        _write_record(record, run, enc, hiding, rows, cache)


def _write_record(path: str, run, enc, hiding, rows: dict, cache) -> None:
    """The JSON record of docs/results/phase3.md's claim table, with the sweep over `SWEEP`."""
    sweep = {}
    for label, spans in SWEEP.items():
        hiding.spans = spans
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(build_module, "observe", hiding)
            fs = {changes_key(c): build_field(run, Phase3Config(**c), enc, threads=1)
                  for _, _, c in VARIANTS}  # fmt: skip
        sweep[label] = {
            name: {rule: _score(fs[changes_key(c)], TextCache(run.path, fs[""], enc), scorer,
                                rule, spans)
                   for rule in ("half-peak", "mean")}
            for name, scorer, c in VARIANTS
        }  # fmt: skip
        sweep[label]["hidden_frames"] = int(_hidden_frames(fs[""].times, spans).sum())
    doc = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": f"SYNC4D_CLAIMS_RECORD={path} OMP_NUM_THREADS=1 python -m pytest -q "
                   "tests/phase3/test_phase3_claims.py -p no:cacheprovider",
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count()},  # fmt: skip
        "scene": {"frames": SCENE.frames, "size": SCENE.size,
                  "train_cameras": SCENE.train_cameras, "sliding_colour": SCENE.sliding_colour,
                  "slide": list(syn.SLIDE)},  # fmt: skip
        "query": QUERY, "encoder": "offline", "hidden": [list(s) for s in HIDDEN],
        "hidden_frames": int(_hidden_frames(np.linspace(0, 1, SCENE.frames), HIDDEN).sum()),
        "table": rows, "sweep": sweep,
    }  # fmt: skip
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(doc, fh, indent=1)
        fh.write("\n")


def test_the_ablation_switches_and_scorers_agree(setup):
    """`phase3.kinematics = false` builds the field the ``no-kinematics`` scorer scores, and
    `phase3.static_only` turns the paper's scorer into the static-only ablation."""
    _, _, _, fields, cache = setup
    default, w0 = fields[""], fields["kinematics=False"]
    np.testing.assert_allclose(w0.sync, default.unconditioned(), atol=1e-6)
    assert not np.any(w0.ridge) and np.any(default.ridge)
    for rule in ("half-peak", "mean"):
        a = answer(default, QUERY, cache=cache, scorer="no-kinematics", rule=rule)
        b = answer(w0, QUERY, cache=cache, scorer="paper", rule=rule)
        assert a["active"] == b["active"]
        assert [o["name"] for o in a["objects"]] == [o["name"] for o in b["objects"]]
    cfg = dataclasses.replace(Phase3Config(), static_only=True)
    switched = answer(default, QUERY, cache=cache, scorer="paper", cfg=cfg)
    static = answer(default, QUERY, cache=cache, scorer="static")
    assert switched["active"] == static["active"]
    assert answer(default, QUERY, cache=cache, scorer="no-kinematics", cfg=cfg)["active"] \
        == static["active"]
