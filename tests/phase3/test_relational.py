"""Relational temporal queries (`sync4d.phase3.relational`): the parser's plans for each form on
a hand-built field read through the offline encoder, the operators on hand-built activation
timelines, the query's fallback, and end to end on the embedded scene (an oracle run with the
offline encoder's field) through `query` and `eval --queries` with the committed question
set."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from support.fields import NAMES, T, bouncing_field
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import load_encoder
from sync4d.phase3.query import TextCache, answer
from sync4d.phase3.relational import (
    Atom,
    Clause,
    Plan,
    RelationalError,
    Timeline,
    evaluate_plan,
    parse,
    plan_text,
    relate,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def bb(tmp_path_factory):
    enc = load_encoder("offline")
    field = bouncing_field(enc)
    cache = TextCache(tmp_path_factory.mktemp("rel"), field, enc)
    return field, cache


def _plan(bb, text: str) -> str:
    field, cache = bb
    plan = parse(text, field, cache, dataclasses.replace(Phase3Config()))
    assert plan is not None, text
    return plan_text(plan)


# ---------------------------------------------------------------------------------------------
# The parser: a plan per form


@pytest.mark.parametrize("text, expected", [
    ("which ball lands first", "first(contact with background) over {"),
    ("the last ball to hit the floor", "last(contact with background) over {"),
    ("the second bounce of the red ball", "nth[2](contact with background) of red ball"),
    ("the green ball's first bounce", "first(contact with background) of green ball"),
    ("how many times does the red ball bounce", "count(contact with background) of red ball"),
    ("how many bounces does the green ball make",
     "count(contact with background) of green ball"),
    ("the ball that bounces only once", "count(contact with background) == 1 over {"),
    ("which ball bounces twice", "count(contact with background) == 2 over {"),
    ("which ball never bounces twice", "count(contact with background) < 2 over {"),
    ("which ball bounces the most", "max(count(contact with background)) over {"),
    ("the blue ball while the red ball is falling",
     "while(blue ball: present while falling of {red ball})"),
    ("the red ball after it lands", "after(red ball: present after contact with background of it)"),
    ("the green ball before the red ball's second bounce",
     "before(green ball: present before nth[2](contact with background) of {red ball})"),
    ("the red ball until the green ball hits the ground",
     "until(red ball: present until contact with background of {green ball})"),
    ("the highest ball", "max(height, present) over {"),
    ("which ball falls the fastest", "max(speed, falling) over {"),
    ("the longest fall", "max(duration, falling) over {"),
    ("the ball that never rises", "never(rising) over {"),
    ("the red ball while it is not falling", "while(red ball: present while not(falling) of it)"),
    ("which ball is the first to stop moving", "first(not(moving)) over {"),
])  # fmt: skip
def test_plans_of_each_form(bb, text, expected):
    assert _plan(bb, text).startswith(expected)


def test_a_form_added_in_one_class_and_one_row_is_read_evaluated_and_scored(bb, tmp_path):
    """A toy form (the object whose atom holds for the most frames, claimed for "fastest"
    before `Extreme`): one class and one `register_form` row; the parser, the evaluation and
    the question-file check then know it."""
    from sync4d.phase3.evaluation.relational_eval import read_relational
    from sync4d.phase3.relational import FORMS, Form, Selected, answer_relational, register_form

    class MostFrames(Form):
        name, order = "toy-most-frames", 5

        def claim(self, r, subject, relation, names, text):
            if r.extreme != ("speed", "max"):
                return None
            return Plan(self.name, subject, relation, names=names)

        def text(self, plan, inner, over, of, nth):
            return f"most-frames({inner}) {over}"

        def select(self, plan, act, tl, eps):
            frames = {k: float(act[k].sum()) for k in plan.subject.objects}
            order = sorted(frames, key=lambda k: -frames[k])
            return Selected(order, {k: eps[k] for k in order}, None, frames)

    register_form(MostFrames)
    try:
        field, cache = bb
        ans = answer_relational(field, "which ball falls the fastest", cache, Phase3Config())
        assert ans is not None and ans["form"] == "toy-most-frames"
        assert ans["plan"].startswith("most-frames(falling) over {")
        path = tmp_path / "q.json"
        path.write_text(json.dumps({"kind": "relational", "questions": [
            {"question": "which ball falls the fastest", "form": "toy-most-frames",
             "object": "red ball", "times": [[0.0, 0.5]]}]}))  # fmt: skip
        assert read_relational(path, NAMES)[0]["form"] == "toy-most-frames"
    finally:
        FORMS.pop("toy-most-frames")
    assert _plan(bb, "which ball falls the fastest").startswith("max(speed, falling) over {")


def test_a_paraphrased_atom_reads_through_the_encoder(bb):
    # no word of these is an atom phrase: the encoder relates them to one
    assert _plan(bb, "which ball strikes the floor first").startswith(
        "first(contact with background)")  # fmt: skip
    assert _plan(bb, "the red ball's second descent").startswith("nth[2](falling) of red ball")


def test_no_function_word_is_no_plan_and_bad_ones_say_what_to_write(bb):
    field, cache = bb
    cfg = Phase3Config()
    assert parse("the red ball", field, cache, cfg) is None
    assert parse("the red ball falling", field, cache, cfg) is None
    with pytest.raises(RelationalError, match="needs a state or event after it"):
        parse("the red ball before", field, cache, cfg)
    with pytest.raises(RelationalError, match="name one"):
        parse("the longest ball", field, cache, cfg)
    with pytest.raises(RelationalError, match="which ball lands first"):
        parse("how many", field, cache, cfg)


# ---------------------------------------------------------------------------------------------
# Answers on the hand-built field


def _top(bb, text):
    field, cache = bb
    ans = answer(field, text, cache=cache)
    top = ans["objects"][0]
    return ans, top["name"], [(iv["start"], iv["end"]) for iv in top["intervals"]]


def test_others_make_an_ordinal_and_count_is_a_count_word(bb):
    assert _plan(bb, "which ball touches the ground before the others").startswith(
        "first(contact with background) over {")  # fmt: skip
    assert _plan(bb, "which ball lands after the others").startswith("last(contact")
    assert _plan(bb, "count the bounces of the red ball").startswith(
        "count(contact with background) of red ball")  # fmt: skip


def test_verb_forms_hedges_comparatives_and_the_next_one(bb):
    # "leaves" reads through its stem "leave" (the encoder finds "leaves" far from "leaving")
    assert _plan(bb, "the ball that never leaves the ground").startswith(
        "never(moving away from background) over {")  # fmt: skip
    plan = _plan(bb, "which ball hits the plate right after the red ball does")
    head = "first(contact with background after contact with background of {red ball}) over {"
    assert plan.startswith(head) and "red" not in plan[len(head):]  # the next one of the rest
    assert _plan(bb, "which ball is higher than the others").startswith("max(height, present)")


def test_answers_on_a_bouncing_field(bb):
    ans, name, spans = _top(bb, "which ball lands first")
    assert name == "red ball" and len(spans) == 1 and spans[0][0] <= 20 <= spans[0][1]
    assert ans["plan"].startswith("first(") and ans["form"] == "ordinal-objects"
    ans, name, spans = _top(bb, "how many times does the red ball bounce")
    assert name == "red ball" and ans["count"] == 2
    _, name, spans = _top(bb, "the second bounce of the red ball")
    assert name == "red ball" and spans[0][0] <= 44 <= spans[0][1]
    _, name, _ = _top(bb, "the ball that bounces twice")
    assert name == "red ball"
    _, name, _ = _top(bb, "which ball never bounces twice")
    assert name in ("green ball", "blue ball")  # once each (the blue ball: all along)
    _, name, spans = _top(bb, "the ball that never rises")
    assert name == "blue ball" and spans == [(0, T - 1)]
    _, name, spans = _top(bb, "the green ball after the red ball's second bounce")
    assert name == "green ball" and spans[0][0] == _top(bb, "the second bounce of the red "
                                                       "ball")[2][0][0]  # fmt: skip
    _, name, _ = _top(bb, "the highest ball")
    assert name == "red ball"


def test_contact_needs_the_ball_near_its_lowest_height(bb):
    from sync4d.phase3 import states

    field, _ = bb
    cfg = Phase3Config()
    clinging = dataclasses.replace(field, gaps=np.zeros_like(field.gaps))  # gap 0 in the air
    contact = states.contact(clinging, cfg, 0)
    # only the two rebounds: the frames whose height is within `contact_band` radii of the
    # lowest (these arcs fall 0.03-0.06 radii a frame there: the lowest frame and a neighbour)
    on = np.flatnonzero(contact[0]).tolist()
    assert {20, 44} <= set(on) and set(on) <= {19, 20, 21, 43, 44, 45}, on
    assert contact[2].all()  # the blue ball lies on the plate throughout


def test_an_unreadable_question_falls_back_and_says_so(bb):
    field, cache = bb
    ans = answer(field, "the red ball before", cache=cache)
    assert ans["plan"] is None and "answered by the full scorer instead" in ans["fallback"]
    assert ans["objects"][0]["name"] == "red ball"
    plain = answer(field, "the red ball", cache=cache)
    assert plain["plan"] is None and "no relational word read" in plain["fallback"]
    off = answer(field, "which ball lands first", cache=cache, relational=False)
    assert off["plan"] is None and off["fallback"] is None
    other = answer(field, "which ball lands first", cache=cache, scorer="paper")
    assert other["plan"] is None  # the ablations stay themselves


# ---------------------------------------------------------------------------------------------
# The operators on hand-built timelines

ACT = {  # 3 objects x 12 frames
    "moving": np.array([[1, 1, 1, 1, 0, 0, 0, 0, 1, 1, 1, 1],
                        [0, 0, 0, 1, 1, 1, 1, 1, 0, 0, 0, 0],
                        [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]], bool),
    "contact": np.array([[0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 0],
                         [0, 0, 0, 0, 0, 0, 0, 1, 1, 0, 0, 0],
                         [1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1]], bool),
}
TIMES = np.linspace(0, 1, 12)
HEIGHT = np.array([np.linspace(1, 0, 12), np.full(12, 0.5), np.full(12, 0.2)])
SPEED = np.array([np.full(12, 1.0), np.r_[np.zeros(6), np.full(6, 3.0)], np.zeros(12)])


def _tl() -> Timeline:
    return Timeline(TIMES, HEIGHT, SPEED, lambda a: ACT[a.name])


def _clause(objs, atoms=(), negated=False, pronoun=False, ordinal=None) -> Clause:
    return Clause("", "x" if len(objs) == 1 and not pronoun else "", list(objs),
                  [Atom(a, a, 1.0) for a in atoms], negated, pronoun, len(objs) == 1,
                  ordinal)  # fmt: skip


def _run(form, subject, **kw):
    sel = evaluate_plan(Plan(form, subject, names=["a", "b", "c"], **kw), _tl())
    return sel.order[0], sel.spans[sel.order[0]], sel


def test_ordinal_over_objects_orders_by_onset():
    # contact onsets: a at 2, b at 7, c under way from frame 0 (no onset: last of all)
    assert _run("ordinal-objects", _clause([0, 1, 2], ["contact"]), n=1)[:2] == (0, [(2, 2)])
    assert _run("ordinal-objects", _clause([0, 1, 2], ["contact"]), n=2)[:2] == (1, [(7, 8)])
    assert _run("ordinal-objects", _clause([0, 1, 2], ["contact"]), n=-1)[0] == 1
    # moving: b starts at 3; a moves from frame 0 (no onset)
    assert _run("ordinal-objects", _clause([0, 1, 2], ["moving"]), n=1)[0] == 1


def test_ordinal_within_episodes_and_counts():
    assert _run("ordinal-episodes", _clause([0], ["contact"]), n=2)[1] == [(5, 5)]
    assert _run("ordinal-episodes", _clause([0], ["contact"]), n=-1)[1] == [(8, 8)]
    assert _run("ordinal-episodes", _clause([0], ["contact"]), n=4)[1] == []  # no 4th
    k, spans, sel = _run("count", _clause([0], ["contact"]))
    assert sel.count == 3 and spans == [(2, 2), (5, 5), (8, 8)]
    assert _run("count-select", _clause([0, 1, 2], ["contact"]), n=1)[0] == 1
    assert _run("count-select", _clause([0, 1, 2], ["contact"]), quantity="count",
                direction="max")[0] == 0  # fmt: skip


def test_relations_while_before_after_until():
    a = ACT["moving"][0]
    b = ACT["moving"][1]  # onset 3, episode 3-7
    np.testing.assert_array_equal(relate(a, b, "while"), a & b)
    np.testing.assert_array_equal(np.flatnonzero(relate(a, b, "before")), [0, 1, 2])
    np.testing.assert_array_equal(np.flatnonzero(relate(a, b, "until")), [0, 1, 2])
    np.testing.assert_array_equal(np.flatnonzero(relate(a, b, "after")), [3, 8, 9, 10, 11])
    always = np.ones(12, bool)
    assert not relate(a, always, "before").any()  # no onset: nothing before it
    # through a plan: object a while b moves; a before its own second contact
    _, spans, _ = _run("relation", _clause([0]), relation=("while", _clause([1], ["moving"])))
    assert spans == [(3, 7)]
    _, spans, _ = _run("relation", _clause([0]), relation=(
        "before", _clause([0], ["contact"], pronoun=True, ordinal=2)))  # fmt: skip
    assert spans == [(0, 4)]


def test_extremes_and_negation():
    # highest: a (starts at 1.0), over the first half of its fall
    k, spans, _ = _run("extreme", _clause([0, 1, 2]), quantity="height", direction="max")
    assert k == 0 and spans[0][0] == 0
    k, spans, _ = _run("extreme", _clause([0, 1, 2]), quantity="speed", direction="max")
    assert k == 1 and spans == [(6, 11)]
    k, spans, _ = _run("extreme", _clause([0, 1, 2], ["moving"]), quantity="duration",
                       direction="max")  # fmt: skip
    assert k == 1 and spans == [(3, 7)]
    k, spans, _ = _run("negation", _clause([0, 1, 2], ["moving"]))
    assert k == 2 and spans == [(0, 11)]
    k, spans, _ = _run("relation", _clause([0], ["moving"], negated=True))
    assert spans == [(4, 7)]


# ---------------------------------------------------------------------------------------------
# End to end on the embedded scene


@pytest.fixture(scope="module")
def embedded_run(tmp_path_factory):
    from support.oracle import oracle_phase2_run
    from sync4d.phase3.build import build_field

    run, _ = oracle_phase2_run(tmp_path_factory.mktemp("relational"), save=True)
    field = build_field(run, Phase3Config(), load_encoder("offline"), threads=1)
    field.save(run.path)
    return run.path


def test_query_prints_the_plan_and_eval_scores_the_question_set(embedded_run, capsys):
    from sync4d.cli import main

    assert main(["query", str(embedded_run), "which object starts moving first",
                 "the red ball before", "--no-plot"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    assert "plan: first(moving) over {red ball, blue box, green pillar} -> blue box" in out
    assert "plan: none (" in out and "answered by the full scorer instead" in out
    questions = ROOT / "examples" / "relational" / "embedded.json"
    assert main(["eval", str(embedded_run), "--queries", str(questions)]) == 0
    table = capsys.readouterr().out
    assert "ordinal-objects" in table and "negation" in table
    res = json.loads((embedded_run / "phase3" / "eval-embedded-relational.json").read_text())
    assert len(res["rows"]) >= 28 and len(res["forms"]) >= 6
    assert res["all"]["acc"] >= 0.95 and res["all"]["tiou"] >= 0.9
    assert all(r["plan"] for r in res["rows"])  # every question was read as a plan


def test_a_bad_question_file_is_named(embedded_run, capsys, tmp_path):
    from sync4d.cli import main

    bad = tmp_path / "q.json"
    bad.write_text(json.dumps({"kind": "relational", "questions": [
        {"question": "which object moves first", "form": "ordinal", "object": "red ball",
         "times": []}]}))  # fmt: skip
    assert main(["eval", str(embedded_run), "--queries", str(bad)]) == 2
    assert "\"form\" must be one of" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# The grammar, completed: spans, phrases of several words, sentence-initial relations, refusals


@pytest.mark.parametrize("text, plan, spans", [
    ("the green ball prior to its landing",
     "before(green ball: present before contact with background of it)", [(0, 35)]),
    ("the red ball between its two bounces", "between(red ball: present between "
     "first(contact with background) and nth[2](contact with background) of it)", [(21, 43)]),
    ("the red ball between its first and second bounce", "between(red ball: present between "
     "first(contact with background) and nth[2](contact with background) of it)", [(21, 43)]),
    ("the red ball from its first bounce to its second bounce", "from(red ball: present from "
     "first(contact with background) to nth[2](contact with background) of it)", [(20, 44)]),
    ("the red ball since its first bounce",
     "after(red ball: present after first(contact with background) of it)", [(20, 60)]),
    ("the red ball as soon as it lands",
     "after(red ball: present after contact with background of it)", [(20, 60)]),
    ("the red ball between bounces",
     "between(red ball: present between contact with background of it)", [(21, 43)]),
])  # fmt: skip
def test_spans_and_relation_phrases(bb, text, plan, spans):
    ans, name, got = _top(bb, text)
    assert ans["plan"] == plan and name == text.split()[1] + " ball" and got == spans


def test_a_relation_that_opens_the_sentence_is_read(bb):
    """"Before the red ball lands, which ball is highest?" is "which ball is highest before
    the red ball lands", with the comma or without; "when does ..." stays a question."""
    want = _plan(bb, "which ball is the highest before the red ball lands")
    assert want.startswith("max(height, present before contact with background of {red ball})")
    assert _plan(bb, "Before the red ball lands, which ball is the highest?") == want
    assert _plan(bb, "before the red ball lands which ball is the highest") == want
    assert _plan(bb, "When does the red ball hit the floor for the second time?") == \
        "nth[2](contact with background) of red ball"


@pytest.mark.parametrize("text, refusal", [
    ("which ball is the fifth to land", "there are only 3 to rank (red ball, blue ball, "
     "green ball): no fifth one (contact with background)"),
    ("the fifth bounce of the red ball", "the red ball has only 2 episodes of contact with "
     "background in the clip: no fifth one"),
    ("the first time the blue ball rises", "the blue ball has no episode of rising in the "
     "clip: no first one"),
])  # fmt: skip
def test_asking_for_what_is_not_there_is_refused_with_a_sentence(bb, text, refusal):
    field, cache = bb
    ans = answer(field, text, cache=cache)
    assert ans["plan"] is not None and ans["refusal"] == refusal
    assert all(o["score"] == 0.0 and not o["intervals"] for o in ans["objects"])
    # a question within the count is answered
    assert answer(field, "the third ball to land", cache=cache)["refusal"] is None


def test_the_ball_with_the_longest_contact(bb):
    """Contacts last as long as they do: the resting blue ball's is the longest."""
    ans, name, spans = _top(bb, "the ball with the longest contact")
    assert ans["plan"].startswith("max(duration, contact with background)")
    assert name == "blue ball" and spans == [(0, T - 1)]


def test_a_motion_onto_a_surface_is_the_contact(bb):
    """"drops onto the floor" ends on the floor: a contact, not a fall; "drops" alone falls."""
    assert _plan(bb, "how many times does the red ball drop onto the floor").startswith(
        "count(contact with background) of red ball")  # fmt: skip
    assert _plan(bb, "how many times does the red ball drop").startswith(
        "count(falling) of red ball")  # fmt: skip
