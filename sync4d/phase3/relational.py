"""Relational temporal queries (beyond the paper): a small grammar over what the field computes.

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
  function words (`ORDINALS`, `RELATIONS`, `EXTREMES`, ...).
* **Contact with the ground** is the union of rebounds and the gap evidence (the height above
  the surface under the object below `contact_gap` times its radius, as "touching the ground"
  reads today, and the object within that of its lowest height over the clip: a reconstruction
  whose plate Gaussians cling to a ball would keep it "touching" in the air) where a run of it
  holds no rebound (rolling, resting; around a rebound it is the ball passing near the surface).
  A rebound is a fall followed by a rise whose lowest point between them is at most
  max(`contact_gap` radius, a quarter of the object's height range) above the object's lowest
  height over the clip. A rebound is an instant; it is reported as the frames within
  ``EVENT_WINDOW`` (normalised time, at least one frame each side) of the lowest point, so an
  interval score of an instant measures its timing rather than failing on one frame. Approaching
  / moving away from the ground is falling / rising.
* **Operators** (`Plan`), applied in this order: an optional *relation* filters the subject's
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

import re
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import TYPE_CHECKING

import numpy as np

from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3.activation import intervals
from sync4d.phase3.texts import TextCache, identity, names_score, resolve_target

if TYPE_CHECKING:
    from sync4d.phase3.store import Field

__all__ = ["ATOMS", "EXTREMES", "FORMS", "ORDINALS", "RELATIONS", "Clause", "Plan",
           "RelationalError", "Timeline", "answer_relational", "evaluate_plan", "parse",
           "plan_text", "relate", "select"]  # fmt: skip


class RelationalError(ValueError):
    """A relational question that cannot be read; the message says what to write instead."""


# --- the grammar's function words (the only literal words of the method) ---------------------

#: Ordinal words and their rank (-1: the last).
ORDINALS = {"first": 1, "second": 2, "third": 3, "fourth": 4, "fifth": 5, "sixth": 6,
            "1st": 1, "2nd": 2, "3rd": 3, "4th": 4, "5th": 5, "last": -1, "final": -1}
#: Relation words between two clauses.
RELATIONS = {"while": "while", "whilst": "while", "when": "while", "during": "during",
             "before": "before", "after": "after", "until": "until", "till": "until"}
#: Superlatives: (quantity, direction).
EXTREMES = {"highest": ("height", "max"), "lowest": ("height", "min"),
            "fastest": ("speed", "max"), "quickest": ("speed", "max"),
            "slowest": ("speed", "min"), "longest": ("duration", "max"),
            "shortest": ("duration", "min"), "most": ("count", "max"),
            "fewest": ("count", "min"), "least": ("count", "min")}
#: Count words of a count selection ("twice", "three times").
NUMBERS = {"once": 1, "twice": 2, "thrice": 3, "one": 1, "single": 1, "two": 2, "three": 3,
           "four": 4, "five": 5, "six": 6, "seven": 7, "eight": 8, "nine": 9, "ten": 10}
#: A count question.
COUNT_WORDS = (("how", "many"), ("how", "often"), ("number", "of"), ("count",))
#: "... before the others": the relation is an ordinal over the subject's class.
OTHERS = ("others", "other", "rest", "ones", "remaining")
#: Adverbs that only tighten a relation word ("right after", "just before").
HEDGES = ("right", "just", "immediately", "shortly", "soon", "directly", "long")
#: Comparatives read as superlatives before "than the others / any other".
COMPARATIVES = {"higher": "highest", "lower": "lowest", "faster": "fastest",
                "slower": "slowest", "longer": "longest", "shorter": "shortest"}
#: Negation.
NEGATIONS = ("never", "not", "no")
#: Words that carry no content (questions, articles, auxiliaries, pronouns).
STOP = frozenset("""the a an is are was were be being been does do did doing it its itself
they them their that which who whom what whose when where how one ones to of for time times
has have had ever in at there this these those s 's by from and or than any all each every
only exactly just again start starts started starting begin begins began beginning come
comes came coming become becomes became get gets got getting""".split())  # fmt: skip
#: Words after which the next content word names the object unless the encoder finds it
#: clearly an atom (at least `ATOM_STRONG`): "the fall" is an atom, "the object" is not.
DETERMINERS = ("the", "a", "an", "which", "what", "each", "every", "any")
#: Words that end a state ("stops rising", "stop moving"): with another atom in the clause,
#: the clause means its negation (alone, "stops" is a content word: it reads as "at rest").
ENDINGS = ("stop", "stops", "stopped", "stopping", "cease", "ceases", "ceased", "quit", "quits",
           "finish", "finishes", "finished")
#: Pronouns that refer back to the subject.
PRONOUNS = ("it", "itself", "they", "them", "its")

#: The question forms, as `Plan.form` names them.
FORMS = ("ordinal-objects", "ordinal-episodes", "count", "count-select", "relation",
         "extreme", "negation")  # fmt: skip

#: A content word is read as part of the atom when the encoder finds it at least this near an
#: atom phrase (and nearer than any object name).
ATOM_MATCH = 0.4
#: ... and at least this right after a determiner (`DETERMINERS`).
ATOM_STRONG = 0.6
#: ... and at least this beside an atom read literally ("stays still" is "still").
ATOM_EXTRA = 0.7
#: Objects within this identity score of the best one form the class of a selection's subject.
CLASS_MARGIN = 0.12
#: Half-width (normalised time) of the interval reported for an instantaneous event.
EVENT_WINDOW = 0.03
#: A quantity varying by at most this fraction of the largest range among the compared
#: objects has no peak of its own (extremes answer the whole clip for it).
FLAT = 0.05
#: Names of the contact event (the scene description's "contact", "rebound").
CONTACT_WORDS = ("contact", "rebound", "bounce")


@dataclass(frozen=True)
class AtomDef:
    """An atom of the grammar: a motion predicate (`motion_phrases`) or the contact event."""

    name: str
    phrases: tuple[str, ...]
    relational: bool = False


def _atom_defs() -> tuple[AtomDef, ...]:
    out = []
    for p in mp.PREDICATES:
        if p.name in ("fastest", "slowest"):  # extremes are operators here
            continue
        phrases = tuple(ph for ph in p.phrases if ph != "on")
        if p.name == "touching":
            out.append(AtomDef("contact", phrases + CONTACT_WORDS, True))
        else:
            out.append(AtomDef(p.name, phrases, p.relational))
    return tuple(out)


#: The atoms, by name.
ATOMS: dict[str, AtomDef] = {a.name: a for a in _atom_defs()}


def _words(text: str) -> list[str]:
    text = text.lower().replace("\u2019", "'").replace("n't", " not")
    text = re.sub(r"'s\b", " 's", text)
    return re.findall(r"[a-z0-9']+", text)


@dataclass
class Atom:
    """A matched atom: its `name` (a key of `ATOMS`), the `words` read, the match
    `similarity` (1.0 literal) and the target (a field label; 0 the background; None any)."""

    name: str
    words: str
    similarity: float
    target: int | None = None
    target_text: str = ""

    def __str__(self) -> str:
        if self.target is None or not ATOMS[self.name].relational:
            return self.name
        prep = {"contact": " with", "moving away": " from"}.get(self.name, "")
        return f"{self.name}{prep} {self.target_text or 'background'}"


@dataclass
class Clause:
    """A read clause: the subject's identity text, its objects (field indices: one, or a
    class), its atoms (AND), negation, and whether it names the subject by a pronoun."""

    text: str
    identity: str
    objects: list[int]
    atoms: list[Atom]
    negated: bool = False
    pronoun: bool = False
    specific: bool = True
    ordinal: int | None = None  # in a relation's other clause: only its nth episode


@dataclass
class Plan:
    """A compiled question: the `form` (`FORMS`), the `subject` clause, an optional relation
    (word, other clause) and the selection's parameters."""

    form: str
    subject: Clause
    relation: tuple[str, Clause] | None = None
    n: int | None = None  # ordinal rank (-1 last) or the count of a count selection
    quantity: str | None = None  # extreme: height, speed, duration, count
    direction: str | None = None  # max or min
    names: list[str] = dc_field(default_factory=list)  # the field's object names


def _atoms_text(c: Clause) -> str:
    a = " & ".join(str(x) for x in c.atoms) or "present"
    return f"not({a})" if c.negated else a


def _objects_text(c: Clause, names: list[str]) -> str:
    return "{" + ", ".join(names[k] for k in c.objects) + "}"


def plan_text(plan: Plan) -> str:
    """The plan as one line, e.g. ``first(contact with background) over {red ball, ...}``."""
    s, names = plan.subject, plan.names
    inner = _atoms_text(s)
    if plan.relation is not None:
        word, other = plan.relation
        who = "it" if other.pronoun or not other.identity else _objects_text(other, names)
        b = _atoms_text(other)
        if other.ordinal is not None:
            b = f"{ {1: 'first', -1: 'last'}.get(other.ordinal, f'nth[{other.ordinal}]')}({b})"
        inner = f"{inner} {word} {b} of {who}"
    if plan.form == "relation":
        return f"{word}({names[s.objects[0]] if s.specific else _objects_text(s, names)}: " \
               f"{inner})"  # fmt: skip
    over = f"over {_objects_text(s, names)}"
    of = f"of {names[s.objects[0]]}" if s.objects else over
    nth = {1: "first", -1: "last"}.get(plan.n or 0, f"nth[{plan.n}]")
    if plan.form == "ordinal-objects":
        return f"{nth}({inner}) {over}"
    if plan.form == "ordinal-episodes":
        return f"{nth}({inner}) {of}"
    if plan.form == "count":
        return f"count({inner}) {of}"
    if plan.form == "count-select":
        if plan.quantity == "count":
            return f"{plan.direction}(count({inner})) {over}"
        return f"count({inner}) {'<' if plan.direction == 'fewer' else '=='} {plan.n} {over}"
    if plan.form == "extreme":
        return f"{plan.direction}({plan.quantity}, {inner}) {over}"
    return f"never({inner}) {over}"


# --- parsing ---------------------------------------------------------------------------------


@dataclass
class _Reading:
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


def _split(text: str) -> _Reading | None:
    """The question's function words; None when it has none (not a relational question)."""
    words = _words(text)
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
    r = _Reading(left=list(left), right=right, relation=rel, which=which)
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


def _stems(word: str) -> list[str]:
    """`word` and, for a third-person verb form, its stems ("leaves": "leave", "leav")."""
    out = [word]
    if len(word) > 3 and word.endswith("ies"):
        out.append(word[:-3] + "y")
    elif len(word) > 3 and word.endswith("es"):
        out += [word[:-1], word[:-2]]
    elif len(word) > 3 and word.endswith("s") and not word.endswith("ss"):
        out.append(word[:-1])
    return out


def _sim(cache: TextCache, a: list[str], b: list[str]) -> np.ndarray:
    return cache.similarity(a, b) if a and b else np.zeros((len(a), len(b)))


def _identity_scores(field: Field, text: str, cache: TextCache, cfg) -> np.ndarray:
    """The `full` scorer's identity of `text` per object: Eq. 15 plus the names' similarity."""
    s, _ = identity(field, text, cache, cfg, False)
    ns = names_score(field, text, cache)
    return s + ns if ns is not None else s


def _read_clause(words: list[str], field: Field, cache: TextCache, cfg, *,
                 generic: bool) -> Clause:  # fmt: skip
    """Split `words` into the subject's identity and its atoms (see the module notes)."""
    text = " ".join(words)
    negated = any(w in NEGATIONS for w in words)
    words = [w for w in words if w not in NEGATIONS]
    role = [""] * len(words)  # "atom", "id", "bg", "" (stop)
    found: list[tuple[int, int, Atom]] = []
    pairs = sorted(((len(ph.split()), ph, a) for a in ATOMS.values() for ph in a.phrases),
                   key=lambda x: -x[0])  # fmt: skip
    for n, ph, a in pairs:
        if any(f[2].name == a.name for f in found):
            continue
        pw = ph.split()
        for i in range(len(words) - n + 1):
            if words[i:i + n] == pw and not any(role[i:i + n]):
                role[i:i + n] = ["atom"] * n
                found.append((i, i + n, Atom(a.name, ph, 1.0)))
                break
    content = [i for i, w in enumerate(words) if not role[i] and w not in STOP]
    for i in content:
        if words[i] in mp.BACKGROUND_WORDS:
            role[i] = "bg"
    content = [i for i in content if not role[i]]
    phrases = [ph for a in ATOMS.values() for ph in a.phrases]
    named = not all(n.startswith("object ") for n in field.names)
    if content:
        cw = [words[i] for i in content]
        # a verb's third person ("leaves", "lands") read as its stem when that is nearer
        forms = [_stems(w) for w in cw]
        flat = [f for fs in forms for f in fs]
        sims = _sim(cache, flat, phrases).max(1)
        sa, pos = np.zeros(len(cw)), 0
        for j, fs in enumerate(forms):
            best = int(np.argmax(sims[pos:pos + len(fs)]))
            sa[j] = sims[pos + best]
            words[content[j]] = fs[best]
            pos += len(fs)
        sn = _sim(cache, cw, field.names).max(1) if named else np.full(len(cw), -1.0)
        for j, i in enumerate(content):
            need = ATOM_STRONG if i > 0 and words[i - 1] in DETERMINERS else ATOM_MATCH
            role[i] = "atom" if sa[j] >= need and sa[j] > sn[j] else "id"
    # spans of atom words not claimed by a literal phrase
    i = 0
    while i < len(words):
        if role[i] == "atom" and not any(s <= i < e for s, e, _ in found):
            j = i
            while j + 1 < len(words) and (role[j + 1] == "atom" or (not role[j + 1] and any(
                    role[m] == "atom" for m in range(j + 2, min(j + 3, len(words)))))):
                if any(s <= j + 1 < e for s, e, _ in found):
                    break
                j += 1
            span = words[i:j + 1]
            grams = [" ".join(span[a:b]) for a in range(len(span))
                     for b in range(a + 1, min(a + 4, len(span) + 1))
                     if span[a] not in STOP and span[b - 1] not in STOP]  # fmt: skip
            literal = any(f[2].similarity == 1.0 for f in found)
            whole = " ".join(w for w in span if w not in STOP) if span else ""
            if whole and float(_sim(cache, [whole], phrases).max()) >= ATOM_MATCH:
                grams = [whole]  # the span as a whole, when it reads as an atom
            if grams:
                sims = _sim(cache, grams, phrases)
                gi, pi = np.unravel_index(int(np.argmax(sims)), sims.shape)
                name = next(a.name for a in ATOMS.values() if phrases[pi] in a.phrases)
                if not any(f[2].name == name for f in found) and (
                        not literal or sims[gi, pi] >= ATOM_EXTRA):
                    found.append((i, j + 1, Atom(name, " ".join(span), float(sims[gi, pi]))))
            i = j + 1
        else:
            i += 1
    found.sort(key=lambda f: f[0])
    # targets: identity / background words right after a relational atom
    subject_words: list[str] = []
    pronoun = any(w in PRONOUNS for w in words)
    for idx, w in enumerate(words):
        if role[idx] not in ("id", "bg"):
            continue
        owner = None
        for _s, e, a in found:
            if e <= idx and ATOMS[a.name].relational:
                between = words[e:idx]
                if all(role[e + m] in ("", "id", "bg") for m in range(len(between))) \
                        and "of" not in between:  # fmt: skip
                    owner = a
        if owner is not None:
            owner.target_text = (owner.target_text + " " + w).strip()
        elif role[idx] == "id":
            subject_words.append(w)
    ending = [i for i, w in enumerate(words) if w in ENDINGS]
    if ending and any(not (s <= ending[0] < e) for s, e, _ in found):
        found = [f for f in found if not (f[0] <= ending[0] < f[1])]
        negated = not negated
    if not subject_words:  # "how many bounces does the blue ball make": the subject
        for _, _, a in found:
            tw = a.target_text.split()
            if tw and not any(w in mp.BACKGROUND_WORDS for w in tw):
                subject_words, a.target_text = tw, ""
                break
    for _, _, a in found:
        _resolve(a, field, cache)
    identity = " ".join(subject_words)
    k = len(field.labels)
    if not identity:
        objects, specific = list(range(k)), False
    else:
        score = _identity_scores(field, identity, cache, cfg)
        if generic:
            # the class: by the names alone when there are names (the image side of Eq. 15
            # favours some object for any word), else by Eq. 15 relative to its best
            if named:
                cls = _sim(cache, [identity], field.names)[0]
                margin = CLASS_MARGIN
            else:
                cls, margin = score, CLASS_MARGIN * max(float(np.abs(score).max()), 1e-9)
            top = float(cls.max())
            objects = [j for j in np.argsort(-score, kind="stable") if cls[j] >= top - margin]
            specific = len(objects) == 1
        else:
            objects, specific = [int(np.argmax(score))], True
    return Clause(text=text, identity=identity, objects=[int(j) for j in objects],
                  atoms=[a for _, _, a in found], negated=negated,
                  pronoun=pronoun and not identity, specific=specific)  # fmt: skip


def _resolve(a: Atom, field: Field, cache: TextCache) -> None:
    """The target label of a relational atom (the background for contact without one)."""
    if not ATOMS[a.name].relational:
        return
    if not a.target_text:
        a.target = 0 if a.name == "contact" and 0 in field.gap_labels else None
        return
    m = mp.MatchedPredicate(mp.Predicate(a.name, (), True), a.words, a.similarity,
                            target_text=a.target_text)  # fmt: skip
    resolve_target(m, field, cache)
    a.target = m.target
    if a.target == 0:
        a.target_text = "background"
    elif a.target in field.labels:
        a.target_text = field.names[field.labels.index(a.target)]


def parse(text: str, field: Field, cache: TextCache, cfg) -> Plan | None:
    """The plan of `text` on `field`, None when it has no function word of the grammar;
    RelationalError when it has one but cannot be read."""
    r = _split(text)
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
        probe = _read_clause(subj_words, field, cache, cfg, generic=True)
        generic = not probe.specific
    else:
        generic = selection and not r.count_ask
    subject = _read_clause(subj_words, field, cache, cfg, generic=generic)
    relation = None
    if r.relation is not None:
        other = _read_clause(r.right or [], field, cache, cfg, generic=False)
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
    if r.extreme is not None:
        q, d = r.extreme
        if q == "duration" and not subject.atoms:
            raise RelationalError(f"{text!r}: \"{'longest' if d == 'max' else 'shortest'}\" "
                                  "compares episodes of a state or event; name one (\"the "
                                  "longest fall\", \"which ball rests the longest\")")  # fmt: skip
        form = "count-select" if q == "count" else "extreme"
        plan = Plan(form, subject, relation, None, q, d, names)
    elif r.count_ask:
        _need_atom(text, subject, "how many times")
        plan = Plan("count", subject, relation, names=names)
    elif r.count_n is not None:
        _need_atom(text, subject, "a count such as \"twice\"")
        # "never twice": fewer than that many
        plan = Plan("count-select", subject, relation, r.count_n,
                    direction="fewer" if r.never else None, names=names)  # fmt: skip
    elif r.never:
        _need_atom(text, subject, "\"never\"")
        plan = Plan("negation", subject, relation, names=names)
    elif r.ordinal is not None:
        _need_atom(text, subject, "an ordinal")
        form = "ordinal-episodes" if subject.specific and not r.which else "ordinal-objects"
        if form == "ordinal-objects" and len(subject.objects) < 2 and r.which:
            form = "ordinal-episodes"
        plan = Plan(form, subject, relation, r.ordinal, names=names)
    elif relation is not None and relation[0] == "after" and not subject.specific \
            and subject.atoms:  # "which ball lands after the red ball": the next one
        plan = Plan("ordinal-objects", subject, relation, 1, names=names)
    else:
        plan = Plan("relation", subject, relation, names=names)
    return plan


def _op_word(r: _Reading) -> str:
    if r.count_ask:
        return "\"how many\""
    if r.ordinal:
        return "an ordinal"
    if r.extreme:
        return "a superlative"
    return "the relation"


def _need_atom(text: str, c: Clause, what: str) -> None:
    if not c.atoms:
        raise RelationalError(f"{text!r}: {what} counts episodes of a state or event, and "
                              f"none was read in {c.text!r}; name one (\"bounces\", \"is "
                              "falling\", \"at rest\", \"touches the blue ball\")")  # fmt: skip


# --- evaluation ------------------------------------------------------------------------------


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

    def window(self) -> int:
        """Frames each side of an instantaneous event (`EVENT_WINDOW`, at least 1)."""
        dt = float(np.median(np.diff(self.times))) if len(self.times) > 1 else 1.0
        return max(1, int(round(EVENT_WINDOW / max(dt, 1e-9))))


def _clause_active(c: Clause, tl: Timeline) -> np.ndarray:
    k, t = tl.height.shape
    act = np.ones((k, t), bool)
    for a in c.atoms:
        act &= np.asarray(tl.activation(a), bool)
    act = ~act if c.negated else act
    for row in act:
        eps = _episodes(row)
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


def _episodes(row: np.ndarray) -> list[tuple[int, int]]:
    return intervals(np.asarray(row, bool))


def _peak_run(q: np.ndarray, direction: str, scale: float = 0.0) -> tuple[float, tuple[int, int]]:
    """(extreme value, the run around it on its side of the mid-range) of `q` [T]; the whole
    clip when `q` varies by at most `FLAT` of `scale` (the largest range among the compared
    objects): a still object's speed or height has no peak but its noise."""
    f = int(np.argmax(q) if direction == "max" else np.argmin(q))
    lo, hi = float(q.min()), float(q.max())
    side = q >= lo + 0.5 * (hi - lo) if direction == "max" else q <= lo + 0.5 * (hi - lo)
    if hi - lo <= FLAT * scale or hi == lo:
        side = np.ones_like(q, bool)
    for s, e in _episodes(side):
        if s <= f <= e:
            return float(q[f]), (s, e)
    return float(q[f]), (f, f)


@dataclass
class Selected:
    """An operator's result: objects ranked (field indices, best first), each object's
    intervals, the answer's count (count forms) and a ranking key per object (for scores)."""

    order: list[int]
    spans: dict[int, list[tuple[int, int]]]
    count: int | None = None
    keys: dict[int, float] = dc_field(default_factory=dict)


def select(plan: Plan, act: np.ndarray, tl: Timeline) -> Selected:
    """Apply `plan`'s selection to the subject's (already related) frames `act` [K, T]."""
    cands = plan.subject.objects
    t = act.shape[1]
    eps = {k: _episodes(act[k]) for k in cands}
    form = plan.form

    def ranked(key: dict[int, float], reverse: bool = False) -> list[int]:
        return sorted(cands, key=lambda k: (-key[k] if reverse else key[k], cands.index(k)))

    if form == "relation":
        cnt = {k: float(act[k].sum()) for k in cands}
        order = ranked(cnt, reverse=True)
        return Selected(order, eps, None, cnt)
    if form == "ordinal-objects":
        # by onset: an episode under way from the clip's first frames has none in the clip
        lead = tl.onset_frames()
        start = {k: next((float(s) for s, _ in eps[k] if s >= lead), t + (0.0 if eps[k]
                         else np.inf)) for k in cands}  # fmt: skip
        eps = {k: [e for e in eps[k] if e[0] >= lead] or eps[k] for k in cands}
        order = sorted([k for k in cands if np.isfinite(start[k])],
                       key=lambda k: (start[k], cands.index(k)))  # fmt: skip
        n = plan.n or 1
        onset = [k for k in order if start[k] < t] or order
        if order:
            pick = onset[-1] if n == -1 else order[min(n, len(order)) - 1]
            order = [pick] + [k for k in order if k != pick]
        order += [k for k in cands if k not in order]
        return Selected(order, {k: eps[k][:1] for k in cands}, None,
                        {k: -start[k] for k in cands})  # fmt: skip
    if form == "ordinal-episodes":
        k = cands[0]
        n = plan.n or 1
        e = eps[k]
        pick = ([e[-1]] if n == -1 else [e[n - 1]]) if e and (n == -1 or n <= len(e)) else []
        return Selected([k], {k: pick}, None, {k: float(bool(pick))})
    if form == "count":
        k = cands[0]
        return Selected([k], {k: eps[k]}, len(eps[k]), {k: float(len(eps[k]))})
    if form == "count-select":
        n = {k: len(eps[k]) for k in cands}
        if plan.quantity == "count":
            key = {k: float(n[k]) if plan.direction == "max" else -float(n[k]) for k in cands}
        else:
            want = plan.n or 0
            key = {k: (1.0 - n[k] / (want + 1) if n[k] < want else -float(n[k] - want + 1))
                   if plan.direction == "fewer" else -abs(n[k] - want) for k in cands}
        order = ranked(key, reverse=True)
        return Selected(order, eps, n[order[0]], key)
    if form == "negation":
        frames = {k: float(act[k].sum()) for k in cands}
        order = ranked(frames)
        return Selected(order, {k: [(0, t - 1)] if frames[k] == 0 else [] for k in cands},
                        None, {k: -frames[k] for k in cands})  # fmt: skip
    # extreme
    sign = 1.0 if plan.direction == "max" else -1.0
    best: dict[int, tuple[float, tuple[int, int] | None]] = {}
    quantity = tl.height if plan.quantity == "height" else tl.speed
    scale = max(float(np.ptp(quantity[k])) for k in cands) if cands else 0.0
    for k in cands:
        if plan.quantity == "duration":
            cand = [((e - s + 1) * sign, (s, e)) for s, e in eps[k]]
            best[k] = max(cand, key=lambda x: x[0]) if cand else (-np.inf, None)
            continue
        q = tl.height[k] if plan.quantity == "height" else tl.speed[k]
        if plan.subject.atoms and all(a.name != "contact" for a in plan.subject.atoms):
            cand = []
            vertical = plan.quantity == "height" and all(
                a.name in ("rising", "falling") for a in plan.subject.atoms)
            for s, e in eps[k]:
                seg = q[s:e + 1]
                v = abs(seg[-1] - seg[0]) if vertical else (seg.max() if sign > 0 else seg.min())
                cand.append((float(v) * sign, (s, e)))
            best[k] = max(cand, key=lambda x: x[0]) if cand else (-np.inf, None)
        else:
            events = bool(plan.subject.atoms) and plan.relation is None
            qq = np.where(act[k], q, np.nan) if not (act[k].all() or events) else q
            if np.isnan(qq).all():
                best[k] = (-np.inf, None)
                continue
            fill = np.nanmin(qq) if sign > 0 else np.nanmax(qq)
            v, run = _peak_run(np.where(np.isnan(qq), fill, qq), plan.direction or "max",
                               scale)  # fmt: skip
            best[k] = (v * sign, run)
    key = {k: best[k][0] for k in cands}
    order = ranked(key, reverse=True)
    return Selected(order, {k: [best[k][1]] if best[k][1] else [] for k in cands}, None, key)


def evaluate_plan(plan: Plan, tl: Timeline) -> Selected:
    """Evaluate `plan` on the timeline `tl`: the subject's frames, related to the other
    clause (per object when it says "it", else that clause's object's frames), then the
    selection."""
    act = _clause_active(plan.subject, tl)
    if plan.relation is not None:
        word, other = plan.relation
        b = _clause_active(other, tl)
        has_atoms = bool(plan.subject.atoms) or plan.subject.negated
        for k in range(act.shape[0]):
            row_b = b[k] if (other.pronoun or not other.identity) else \
                np.any(b[other.objects], axis=0)
            if other.ordinal is not None:
                eps = _episodes(row_b)
                n = other.ordinal
                row_b = np.zeros_like(row_b)
                if eps and (n == -1 or n <= len(eps)):
                    s, e = eps[-1] if n == -1 else eps[n - 1]
                    row_b[s:e + 1] = True
            row_a = act[k] if has_atoms else np.ones_like(act[k])
            act[k] = relate(row_a, row_b, word, tl.onset_frames())
    return select(plan, act, tl)


# --- the field's timeline --------------------------------------------------------------------


def rebounds(times: np.ndarray, height: np.ndarray, s_ref: float, tol: np.ndarray,
             cfg, lowest: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """Rebounds [K, T] of heights `height` [K, T] (already smoothed in time): a fall followed
    by a rise (vertical speed beyond `vertical_speed` times `s_ref`, as "falling" and "rising"
    read it), whose lowest frame between them is at most max(`tol` [K], a quarter of the
    object's height range) above its lowest height over the clip; marked as that lowest frame
    +- the event window (`EVENT_WINDOW`). `lowest` [K, T] (bool), when given, gets the lowest
    frames."""
    k, t = height.shape
    vu = np.gradient(height, times, axis=1) if t > 1 else np.zeros_like(height)
    minf = int(cfg.phrase_min_frames)
    fall = mp.clean_runs(-vu > cfg.vertical_speed * s_ref, minf)
    rise = mp.clean_runs(vu > cfg.vertical_speed * s_ref, minf)
    w = Timeline(times, height, height, None).window()
    out = np.zeros((k, t), bool)
    for j in range(k):
        band = max(float(tol[j]), 0.25 * float(np.ptp(height[j])))
        rises = _episodes(rise[j])
        for _, e in _episodes(fall[j]):
            nxt = [s for s, _ in rises if s > e]
            if not nxt:
                continue
            f = e + int(np.argmin(height[j, e:nxt[0] + 1]))
            if height[j, f] - height[j].min() <= band:
                out[j, max(0, f - w):min(t, f + w + 1)] = True
                if lowest is not None:
                    lowest[j, f] = True
    return out


def ground_contact(field: Field, cfg) -> np.ndarray:
    """Contact with the background [K, T] (see the module notes): a rebound (`rebounds`) of
    M_phi's smoothed centroid height, or a run of small gaps, within the same tolerance of the
    object's lowest height, that holds no rebound (rolling, resting: a run around a rebound is
    the ball passing near the surface on its way)."""
    times, k = field.times, len(field.labels)
    c, _, s_ref = mp.smoothed_motion(field.centroids, times, field.radius, cfg.phrase_smooth)
    tol = cfg.contact_gap * np.asarray(field.radius, np.float64)
    out = np.zeros((k, len(times)), bool)
    lowest = np.zeros_like(out)
    hits = rebounds(times, c @ field.up, s_ref, tol, cfg, lowest)
    gl = list(field.gap_labels)
    if 0 in gl:
        g = np.asarray(field.gaps[:, gl.index(0)], np.float64)
        near = mp.clean_runs(np.where(np.isfinite(g), g, np.inf) < tol[:, None],
                             int(cfg.phrase_min_frames))  # fmt: skip
        h = c @ field.up  # touching needs the object near its lowest height, too
        near &= (h - h.min(axis=1, keepdims=True)) <= tol[:, None]
        for j in range(k):  # a run of small gaps around a rebound is that rebound's
            for s, e in _episodes(near[j]):
                if not lowest[j, s:e + 1].any():
                    out[j, s:e + 1] = True
    return out | hits


#: Approaching / moving away from the background is falling / rising (the scene
#: description's approach and separation events with the background: the height changes).
_TOWARDS_GROUND = {"approaching": "falling", "moving away": "rising"}


def field_timeline(field: Field, cfg) -> Timeline:
    """The timeline of `field`: M_phi's smoothed centroid height and speed, and the atoms
    evaluated by the motion predicates (contact with the background: `ground_contact`)."""
    c, vel, _ = mp.smoothed_motion(field.centroids, field.times, field.radius,
                                   cfg.phrase_smooth)  # fmt: skip
    memo: dict[tuple[str, int | None], np.ndarray] = {}

    def activation(a: Atom) -> np.ndarray:
        key = (a.name, a.target)
        if key not in memo:
            if a.name == "contact" and a.target == 0:
                memo[key] = ground_contact(field, cfg)
            else:
                name = "touching" if a.name == "contact" else a.name
                if a.target == 0 and name in _TOWARDS_GROUND:
                    name = _TOWARDS_GROUND[name]
                pred = next(p for p in mp.PREDICATES if p.name == name)
                m = mp.MatchedPredicate(pred, a.words, a.similarity, target=a.target)
                memo[key] = mp.evaluate(m, field.features, field.centroids, field.gaps,
                                        field.gap_labels, field.labels, field.radius,
                                        field.up, field.right, field.times, cfg)  # fmt: skip
        return memo[key]

    return Timeline(np.asarray(field.times), c @ field.up, np.linalg.norm(vel, axis=-1),
                    activation, int(cfg.phrase_min_frames))  # fmt: skip


def answer_relational(field: Field, text: str, cache: TextCache, cfg) -> dict | None:
    """The relational answer to `text` as `query.answer`'s fields (objects ranked with their
    intervals, the per-frame activation) plus ``plan`` and ``count``; None when `text` is no
    relational question. RelationalError when it is one that cannot be read."""
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
    if not sel.spans.get(sel.order[0]) and plan.form not in ("count", "count-select"):
        score[sel.order[0]] = 0.5  # nothing holds: the best reading, with half the weight
    return {"plan": plan_text(plan), "form": plan.form, "count": sel.count,
            "order": order, "score": score, "active": active}  # fmt: skip
