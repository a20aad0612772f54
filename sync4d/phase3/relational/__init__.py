"""Relational temporal queries (beyond the paper): a small grammar over what the field computes.

The package: `words` (the grammar's function words and thresholds: data), `reading` (a text's
function words and its plan) and `clauses` (a clause's subject and atoms), `forms` (the
question forms, one class each, registered), `timeline` (what the operators read, and the
field's own timeline), here the plan's text, its evaluation and the answer.

Design notes
------------
A relational question ("which ball lands first", "the second bounce of the red ball", "how
many times does the green ball hit the floor", "the blue ball while the red ball is falling",
"the highest ball", "the ball that never rises") is compiled into a *plan* of a few operators
over *atoms*, then evaluated on per-object, per-frame activations. Nothing here is new
perception: an atom is one of today's answers, so the grammar adds only the relation.

* **Atoms.** An object (its identity: the query's similarity to each object's name and the
  paper's Eq. 15 score, as the ``full`` scorer ranks objects) and a motion state or event (the
  motion predicates of `motion_phrases`: rising, falling, at rest, moving, turning, moving
  left/right, approaching, moving away, and *contact*, their "touching" predicate plus the scene
  description's contact event). The words of a clause are split between object and atom by the
  text encoder: a phrase of the atom vocabulary that occurs literally claims its words; every
  other content word goes to the atom side when the encoder finds it nearer an atom phrase than
  any object name (and at least `ATOM_MATCH`), else to the object side. The atom words are then
  matched to the nearest atom phrase by the encoder (beside a literal atom, only at
  `ATOM_EXTRA`: "stays still" is "still"). A paraphrase of an atom therefore reads as well as
  the encoder relates it; nothing in this module lists question wordings, only the grammar's
  function words (`words.ORDINALS`, `words.RELATIONS`, `words.EXTREMES`, ...).
* **Contact** (with the ground, or with a named object) and every motion state are read from
  the run's one state model, `sync4d.phase3.states`, as `query`'s motion phrases and the scene
  description read them: a contact lasts from the frame the object's gap to the surface comes
  within `contact_band` radii of its value at the touch to the frame it leaves that band.
  Approaching / moving away from the ground is falling / rising.
* **Operators** (`Plan`; one registered class per form, `forms.FORMS`), applied in this
  order: an optional *relation* filters the subject's
  frames by another clause (while / during: both hold; before / until: before the other clause's
  first onset, the start of an episode that begins after the first `phrase_min_frames` frames;
  after: from that onset on; "it" in the other clause is the subject itself; an ordinal there
  picks that episode, "after its second bounce"; a clause without a state or event repeats the
  subject's, "before the blue ball does"; "before / after the others" is the first / last over
  the class; "which ball X after Y" is the first to X after Y); then one *selection* on the
  resulting episodes (gaps shorter than `phrase_min_frames` closed): an ordinal over objects
  (the objects ordered by the onset of their first episode: "first", "second", "last"; an
  episode under way in the first `phrase_min_frames` frames has no onset in the clip and ranks
  after every observed one; "stops X" reads as the onset of not-X), an ordinal over one object's
  episodes ("the second bounce of X"), a count ("how many times": the number of episodes), a
  count selection ("once", "twice", "N times"; "never twice": fewer; "most", "fewest"), an
  extreme over a kinematic quantity ("highest" / "lowest": height along the field's up vector;
  "fastest" / "slowest": speed; "longest" / "shortest": an episode's duration) or a negation
  ("never": the object whose frames are all false; "not" inside a clause: the complement).
* **Subjects.** A selection over objects (ordinals over objects, count selections, extremes,
  "never", "which ...") reads its subject as a class: every object whose name's similarity to
  the identity words is within `CLASS_MARGIN` of the best ("ball" keeps every ball, "object"
  every object; unnamed objects: Eq. 15 within that fraction of the best), all objects
  without an identity word; an operator on one object (its episodes, a count, a relation)
  takes the best object by the `full` scorer's identity (Eq. 15 plus the names).
* **Extremes** of height or speed compare each candidate's peak (or trough) value, over the
  atom's episodes when the atom is a state (for rising and falling: the height an episode gains
  or loses, "rises highest"), else over the whole clip; the answer's interval is the atom
  episode holding it, or the run of frames around it on the extreme side of the object's
  mid-range (Appendix F's half-peak rule on the quantity; the whole clip when the object's
  quantity is flat, `FLAT`). Durations need an atom.
* **Unparsed.** A text without any function word is no relational question (`parse` returns
  None and `query` answers it with today's scorer); a text with one that cannot be read raises
  `RelationalError`, which says what to write, and `query` falls back to today's scorer,
  saying so.

Everything is numpy on the field's arrays; the text encoder is only reached through the
query's `TextCache` (cached, so a repeated question encodes nothing).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sync4d.phase3.relational.forms import FORMS, Form, register_form, select
from sync4d.phase3.relational.plan import Atom, Clause, Plan, RelationalError, Selected
from sync4d.phase3.relational.reading import parse
from sync4d.phase3.relational.registry import atoms_text
from sync4d.phase3.relational.timeline import (
    Timeline,
    clause_active,
    field_timeline,
    nth_episode,
    relate,
    span,
)
from sync4d.phase3.relational.words import ATOMS, EXTREMES, ORDINALS, RELATIONS

if TYPE_CHECKING:
    from sync4d.phase3.store import Field
    from sync4d.phase3.texts import TextCache

__all__ = ["ATOMS", "EXTREMES", "FORMS", "ORDINALS", "RELATIONS", "Atom", "Clause", "Form",
           "Plan", "RelationalError", "Selected", "Timeline", "answer_relational",
           "evaluate_plan", "parse", "plan_text", "register_form", "relate", "select"]  # fmt: skip


def _ranked_text(c: Clause) -> str:
    """A relation clause's atoms, inside its rank word when it names one episode."""
    b = atoms_text(c)
    if c.ordinal is None:
        return b
    return f"{ {1: 'first', -1: 'last'}.get(c.ordinal, f'nth[{c.ordinal}]')}({b})"


def _objects_text(c: Clause, names: list[str]) -> str:
    return "{" + ", ".join(names[k] for k in c.objects) + "}"


def plan_text(plan: Plan) -> str:
    """The plan as one line, e.g. ``first(contact with background) over {red ball, ...}``."""
    s, names = plan.subject, plan.names
    inner = atoms_text(s)
    if plan.relation is not None:
        word, other = plan.relation
        who = "it" if other.pronoun or not other.identity else _objects_text(other, names)
        b = _ranked_text(other)
        if other.then is not None:
            c = _ranked_text(other.then)
            join = "and" if word == "between" else "to"
            inner = f"{inner} {word} {b} {join} {c} of {who}"
        else:
            inner = f"{inner} {word} {b} of {who}"
    over = f"over {_objects_text(s, names)}"
    of = f"of {names[s.objects[0]]}" if s.objects else over
    nth = {1: "first", -1: "last"}.get(plan.n or 0, f"nth[{plan.n}]")
    return FORMS[plan.form].text(plan, inner, over, of, nth)


def evaluate_plan(plan: Plan, tl: Timeline) -> Selected:
    """Evaluate `plan` on the timeline `tl`: the subject's frames, related to the other
    clause (per object when it says "it", else that clause's object's frames), then the
    selection."""
    act = clause_active(plan.subject, tl)
    if plan.relation is not None:
        word, other = plan.relation
        b = clause_active(other, tl)
        then = other.then
        c = clause_active(then, tl) if then is not None else None
        has_atoms = bool(plan.subject.atoms) or plan.subject.negated

        def of(clause: Clause, frames: np.ndarray, k: int) -> np.ndarray:
            """The clause's frames as object k relates to them: its own ("it"), else those
            of the clause's object(s)."""
            if clause.pronoun or not clause.identity:
                return frames[k]
            return np.any(frames[clause.objects], axis=0)

        for k in range(act.shape[0]):
            row_a = act[k] if has_atoms else np.ones_like(act[k])
            row_b = of(other, b, k)
            if word in ("between", "from"):
                row_c = of(then, c, k) if then is not None else None
                nx = other.ordinal if then is not None else None
                act[k] = row_a & span(row_b, row_c, word, nx,
                                      then.ordinal if then is not None else None)
                continue
            if other.ordinal is not None:
                ep = nth_episode(row_b, other.ordinal)
                row_b = np.zeros_like(row_b)
                if ep is not None:
                    row_b[ep[0]:ep[1] + 1] = True
            act[k] = relate(row_a, row_b, word, tl.onset_frames())
    return select(plan, act, tl)


def answer_relational(field: Field, text: str, cache: TextCache, cfg) -> dict | None:
    """The relational answer to `text` as `query.answer`'s fields (objects ranked with their
    intervals, the per-frame activation) plus ``plan``, ``count`` and ``refusal`` (the
    sentence saying that what was asked for is not there, e.g. a fifth ball of three: then no
    object has a score or a frame); None when `text` is no relational question.
    RelationalError when it is one that cannot be read."""
    plan = parse(text, field, cache, cfg)
    if plan is None:
        return None
    tl = field_timeline(field, cfg)
    sel = evaluate_plan(plan, tl)
    k, t = len(field.labels), len(field.times)
    active = np.zeros((k, t), bool)
    for j, spans in sel.spans.items():
        for s, e in spans:
            active[j, s:e + 1] = True
    order = sel.order + [j for j in range(k) if j not in sel.order]
    # scores: the answer 1, the others by rank (1/(rank+1)), objects outside the class 0
    score = np.zeros(k)
    for r, j in enumerate(sel.order):
        score[j] = 1.0 / (r + 1)
    if sel.refusal is not None:
        score[:] = 0.0  # what was asked for is not there: no object is the answer
    elif not sel.spans.get(sel.order[0]) and plan.form not in ("count", "count-select"):
        score[sel.order[0]] = 0.5  # nothing holds: the best reading, with half the weight
    return {"plan": plan_text(plan), "form": plan.form, "count": sel.count,
            "order": order, "score": score, "active": active,
            "refusal": sel.refusal}  # fmt: skip
