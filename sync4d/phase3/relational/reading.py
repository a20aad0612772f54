"""Reading a question: its function words (`split`: ordinals, relation words, counts,
superlatives, "never"), its clauses (`clauses.read_clause`), and the plan (`parse`): the
first registered form (`forms.forms_by_order`) that claims the reading."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from sync4d.phase3.relational.clauses import read_clause
from sync4d.phase3.relational.forms import forms_by_order
from sync4d.phase3.relational.plan import Atom, Plan, RelationalError
from sync4d.phase3.relational.words import (
    COMPARATIVES,
    COUNT_WORDS,
    EXTREMES,
    HEDGES,
    NUMBERS,
    ORDINALS,
    OTHERS,
    RELATIONS,
    STOP,
)
from sync4d.phase3.relational.words import words as split_words

if TYPE_CHECKING:
    from sync4d.phase3.store import Field
    from sync4d.phase3.texts import TextCache

__all__ = ["Reading", "parse", "split"]


@dataclass
class Reading:
    """What the function words of a question say before the clauses are read."""

    left: list[str]
    right: list[str] | None
    relation: str | None
    ordinal: int | None = None
    count_ask: bool = False
    count_n: int | None = None
    extreme: tuple[str, str] | None = None
    never: bool = False
    which: bool = False
    right_ordinal: int | None = None


def split(text: str) -> Reading | None:
    """The question's function words; None when it has none (not a relational question)."""
    words = split_words(text)
    which = bool(words) and words[0] in ("which", "what", "who")
    words = [w for i, w in enumerate(words)
             if not (w in HEDGES and i + 1 < len(words) and words[i + 1] in RELATIONS)]
    for i, w in enumerate(words[:-2]):  # "higher than the others": a superlative
        if w in COMPARATIVES and words[i + 1] == "than" and any(
                x in OTHERS or x in ("any", "all", "every") for x in words[i + 2:]):
            words = words[:i] + [COMPARATIVES[w]]
            break
    rel, right, left = None, None, words
    for i, w in enumerate(words):
        if w in RELATIONS and i > 0:
            rel, left, right = RELATIONS[w], words[:i], words[i + 1:]
            break
    r = Reading(left=list(left), right=right, relation=rel, which=which)
    out: list[str] = []
    i = 0
    lw = r.left
    while i < len(lw):
        w = lw[i]
        nxt = lw[i + 1] if i + 1 < len(lw) else ""
        hit = next((c for c in COUNT_WORDS if tuple(lw[i:i + len(c)]) == c), None)
        if hit is not None:
            r.count_ask = True
            i += len(hit)
            if i < len(lw) and lw[i] in ("times", "time"):
                i += 1
            continue
        if w in ORDINALS:
            r.ordinal = ORDINALS[w]
            i += 1
            if i < len(lw) and lw[i] == "time":  # "for the first time"
                i += 1
            continue
        if w in EXTREMES and not (w == "least" and nxt in EXTREMES):
            r.extreme = EXTREMES[w]
            i += 1
            continue
        if w in ("once", "twice", "thrice"):
            r.count_n = NUMBERS[w]
            i += 1
            continue
        if (w in NUMBERS or w.isdigit()) and nxt in ("times", "time"):
            r.count_n = int(w) if w.isdigit() else NUMBERS[w]
            i += 2
            continue
        if w == "never":
            r.never = True
            i += 1
            continue
        out.append(w)
        i += 1
    r.left = out
    if r.relation in ("before", "after") and r.right is not None and r.ordinal is None \
            and any(w in OTHERS for w in r.right) \
            and all(w in OTHERS or w in STOP for w in r.right):  # fmt: skip
        r.ordinal = 1 if r.relation == "before" else -1
        r.relation, r.right, r.which = None, None, True
    if r.right is not None:
        rest = []
        for w in r.right:
            if w in ORDINALS and r.right_ordinal is None:
                r.right_ordinal = ORDINALS[w]
            else:
                rest.append(w)
        r.right = rest
    if r.relation is None and not (r.ordinal or r.count_ask or r.count_n or r.extreme
                                   or r.never):  # fmt: skip
        return None
    return r


def parse(text: str, field: Field, cache: TextCache, cfg) -> Plan | None:
    """The plan of `text` on `field`, None when it has no function word of the grammar;
    RelationalError when it has one but cannot be read."""
    r = split(text)
    if r is None:
        return None
    selection = bool(r.ordinal or r.count_n or r.extreme or r.never) or r.which
    subj_words = r.left
    # "the second bounce of the red ball": the words after "of" name the subject
    if "of" in subj_words and not r.count_ask:
        i = subj_words.index("of")
        after = subj_words[i + 1:]
        if after:
            subj_words = after + subj_words[:i]
    if not [w for w in subj_words if w not in STOP] and r.relation is None:
        raise RelationalError(f"{text!r}: no object or state to apply "
                              f"{_op_word(r)} to; ask e.g. \"which ball lands first\" or "
                              "\"the second bounce of the red ball\"")  # fmt: skip
    if r.ordinal and not r.which and not r.count_ask:
        # an ordinal names one object's episodes unless the subject is a class
        probe = read_clause(subj_words, field, cache, cfg, generic=True)
        generic = not probe.specific
    else:
        generic = selection and not r.count_ask
    subject = read_clause(subj_words, field, cache, cfg, generic=generic)
    relation = None
    if r.relation is not None:
        other = read_clause(r.right or [], field, cache, cfg, generic=False)
        other.ordinal = r.right_ordinal
        if not other.atoms and subject.atoms:  # "... before the blue ball does"
            other.atoms = [Atom(a.name, a.words, a.similarity, a.target, a.target_text)
                           for a in subject.atoms]  # fmt: skip
        if not other.atoms and not other.negated:
            raise RelationalError(
                f"{text!r}: \"{r.relation}\" needs a state or event after it (\"... while "
                "the red ball is falling\", \"... after it hits the ground\"); none was read "
                f"in {' '.join(r.right or []) or 'nothing'!r}")  # fmt: skip
        relation = (r.relation, other)
        if other.specific and not other.pronoun and not subject.specific:
            rest = [k for k in subject.objects if k not in other.objects]
            subject.objects = rest or subject.objects
    names = list(field.names)
    for form in forms_by_order():
        plan = form.claim(r, subject, relation, names, text)
        if plan is not None:
            return plan
    raise RelationalError(f"{text!r}: no question form reads it")  # no catch-all registered


def _op_word(r: Reading) -> str:
    if r.count_ask:
        return "\"how many\""
    if r.ordinal:
        return "an ordinal"
    if r.extreme:
        return "a superlative"
    return "the relation"


