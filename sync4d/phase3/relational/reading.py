"""Reading a question: its function words (`split`: ordinals, relation words, counts,
superlatives, "never"), its clauses (`clauses.read_clause`), and the plan (`parse`): the
first registered form (`forms.forms_by_order`) that claims the reading."""

from __future__ import annotations

import dataclasses
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
    QUESTION_WORDS,
    RELATION_PHRASES,
    RELATIONS,
    SPAN_JOINS,
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
    #: "between X and Y", "from X to Y": Y's words (`right` holds X's) and Y's ordinal.
    then: list[str] | None = None
    then_ordinal: int | None = None


#: Auxiliaries after which an opening "when" asks a question ("when does it land") rather than
#: opening a relation clause ("when the red ball lands, ...").
_AUXILIARIES = ("does", "do", "did", "is", "are", "was", "were", "will", "can", "would")
#: Words before "from" that make it part of a motion phrase ("moving away from"), not a span.
_NOT_SPAN = ("away", "farther", "further", "receding", "off", "apart")


def _joined(words: list[str]) -> list[str]:
    """`words` with each relation phrase of several words (`RELATION_PHRASES`: "prior to",
    "as soon as") replaced by its relation word."""
    out, i = [], 0
    while i < len(words):
        hit = next(((ph, rel) for ph, rel in RELATION_PHRASES.items()
                    if tuple(words[i:i + len(ph)]) == ph), None)  # fmt: skip
        if hit is None:
            out.append(words[i])
            i += 1
        else:
            out.append(hit[1])
            i += len(hit[0])
    return out


def _words_in_order(text: str) -> list[str]:
    """The question's words with a relation clause that opens the sentence moved after the
    main clause ("Before the red ball lands, which ball is highest?" reads as "which ball is
    highest before the red ball lands"): the opening clause ends at the first comma, else
    before the first question word."""
    words = _joined(split_words(text))
    if not words or words[0] not in RELATIONS:
        return words
    if words[0] == "when" and len(words) > 1 and words[1] in _AUXILIARIES:
        return words  # "when does the red ball land": a question, not a relation
    if "," in text:
        head, tail = text.split(",", 1)
        front, main = _joined(split_words(head)), _joined(split_words(tail))
        if front and front[0] in RELATIONS and main:
            return main + front
    j = next((i for i, w in enumerate(words) if i > 1 and w in QUESTION_WORDS
              and w != "when"), None)  # fmt: skip
    return words[j:] + words[:j] if j is not None else words


def _span(words: list[str], i: int) -> tuple[list[str], list[str]] | None:
    """(X's words, Y's words) of "between X and Y" / "from X to Y" at `words[i]`; "between its
    two bounces" is X = its first bounce, Y = its second. None when it is no span."""
    w, rest = words[i], words[i + 1:]
    if w == "from" and (i == 0 or words[i - 1] in _NOT_SPAN):
        return None
    joins = [j for j, x in enumerate(rest) if x in SPAN_JOINS.get(w, ())]
    if joins:
        return rest[:joins[0]], rest[joins[0] + 1:]
    if w == "between":
        pair = [j for j, x in enumerate(rest) if x in ("two", "both")]
        if pair:
            x = rest[:pair[0]] + rest[pair[0] + 1:]
            return ["first", *x], ["second", *x]
    return None


def split(text: str) -> Reading | None:
    """The question's function words; None when it has none (not a relational question)."""
    words = _words_in_order(text)
    which = bool(words) and words[0] in ("which", "what", "who")
    words = [w for i, w in enumerate(words)
             if not (w in HEDGES and i + 1 < len(words) and words[i + 1] in RELATIONS)]
    for i, w in enumerate(words[:-2]):  # "higher than the others": a superlative
        if w in COMPARATIVES and words[i + 1] == "than" and any(
                x in OTHERS or x in ("any", "all", "every") for x in words[i + 2:]):
            words = words[:i] + [COMPARATIVES[w]]
            break
    rel, right, left, then = None, None, words, None
    for i, w in enumerate(words):
        if w in SPAN_JOINS and i > 0:
            span = _span(words, i)
            if span is not None:
                rel, left, (right, then) = w, words[:i], span
                break
        if w in RELATIONS and i > 0:
            rel, left, right = RELATIONS[w], words[:i], words[i + 1:]
            break
    r = Reading(left=list(left), right=right, relation=rel, which=which, then=then)
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
        r.right, r.right_ordinal = _ordinal_apart(r.right)
    if r.then is not None:
        r.then, r.then_ordinal = _ordinal_apart(r.then)
    if r.relation is None and not (r.ordinal or r.count_ask or r.count_n or r.extreme
                                   or r.never):  # fmt: skip
        return None
    return r


def _ordinal_apart(words: list[str]) -> tuple[list[str], int | None]:
    """`words` without their first ordinal word, and its rank (None: none)."""
    rest, rank = [], None
    for w in words:
        if w in ORDINALS and rank is None:
            rank = ORDINALS[w]
        else:
            rest.append(w)
    return rest, rank


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
        if r.then is not None:  # between X and Y, from X to Y: each borrows the other's atoms
            then = read_clause(r.then, field, cache, cfg, generic=False)
            then.ordinal = r.then_ordinal
            if not other.atoms and then.atoms:  # "between its first and second bounce"
                other.atoms = _copies(then.atoms)
            if not then.atoms and other.atoms:
                then.atoms = _copies(other.atoms)
            if not other.identity and then.identity:
                other.objects, other.identity, other.pronoun = \
                    then.objects, then.identity, then.pronoun  # fmt: skip
            other.then = then
        if not other.atoms and subject.atoms:  # "... before the blue ball does"
            other.atoms = _copies(subject.atoms)
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


def _copies(atoms: list[Atom]) -> list[Atom]:
    return [dataclasses.replace(a) for a in atoms]


def _op_word(r: Reading) -> str:
    if r.count_ask:
        return "\"how many\""
    if r.ordinal:
        return "an ordinal"
    if r.extreme:
        return "a superlative"
    return "the relation"


