"""The grammar's words: the function words a relational question is read by (the only literal
words of the method besides the motion-phrase lexicon of `motion_phrases`), the thresholds
the reading uses, and the atoms (motion predicates and the contact event) a clause can name.
Data, no logic beyond splitting a text into words."""

from __future__ import annotations

import re
from dataclasses import dataclass

from sync4d.phase3 import motion_phrases as mp

__all__ = ["ATOMS", "COMPARATIVES", "CONTACT_WORDS", "COUNT_WORDS", "DETERMINERS", "ENDINGS",
           "EXTREMES", "HEDGES", "NEGATIONS", "NUMBERS", "ONTO", "ORDINALS", "OTHERS",
           "PRONOUNS", "QUESTION_WORDS", "RELATIONS", "RELATION_PHRASES", "SPAN_JOINS", "STOP",
           "TOWARDS", "AtomDef", "stems", "words"]  # fmt: skip

#: Ordinal words and their rank (-1: the last).
ORDINALS = {"first": 1, "second": 2, "third": 3, "fourth": 4, "fifth": 5, "sixth": 6,
            "1st": 1, "2nd": 2, "3rd": 3, "4th": 4, "5th": 5, "last": -1, "final": -1}
#: Relation words between two clauses.
RELATIONS = {"while": "while", "whilst": "while", "when": "while", "during": "during",
             "before": "before", "after": "after", "until": "until", "till": "until",
             "since": "after", "between": "between"}
#: Relation phrases of several words, read as one relation word.
RELATION_PHRASES = {("prior", "to"): "before", ("as", "soon", "as"): "after",
                    ("up", "to"): "until", ("by", "the", "time"): "until"}
#: "between X and Y" (the frames after X ends and before Y begins) and "from X to Y" (from X's
#: start to Y's end): the words that join the two clauses.
SPAN_JOINS = {"between": ("and",), "from": ("to", "until", "till")}
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
#: Words that open the main clause after a sentence-initial relation without a comma
#: ("before the red ball lands which ball is highest").
QUESTION_WORDS = ("which", "what", "who", "how", "where", "when")
#: Pronouns that refer back to the subject.
PRONOUNS = ("it", "itself", "they", "them", "its")

#: A content word is read as part of the atom when the encoder finds it at least this near an
#: atom phrase (and nearer than any object name).
ATOM_MATCH = 0.4
#: ... and at least this right after a determiner (`DETERMINERS`).
ATOM_STRONG = 0.6
#: ... and at least this beside an atom read literally ("stays still" is "still").
ATOM_EXTRA = 0.7
#: Objects within this identity score of the best one form the class of a selection's subject.
CLASS_MARGIN = 0.12
#: A quantity varying by at most this fraction of the largest range among the compared
#: objects has no peak of its own (extremes answer the whole clip for it).
FLAT = 0.05
#: Names of the contact event (the scene description's "contact", "rebound"); "reach" was
#: added after measuring the paraphrase set (2026-12-06: "which ball reaches the plate first"
#: read as approaching; docs/phase3-queries.md says so).
CONTACT_WORDS = ("contact", "rebound", "bounce", "reach")
#: Telic prepositions: a motion towards a surface or object followed by one of these ("comes
#: down onto the plate", "falls into the box") means the motion's end there, the contact.
ONTO = ("onto", "into")
#: The atoms a telic preposition turns into a contact.
TOWARDS = ("falling", "moving", "approaching")


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


def words(text: str) -> list[str]:
    """`text` lower-cased and split into words ("n't" as " not", "'s" apart)."""
    text = text.lower().replace("\u2019", "'").replace("n't", " not")
    text = re.sub(r"'s\b", " 's", text)
    return re.findall(r"[a-z0-9']+", text)


def stems(word: str) -> list[str]:
    """`word` and, for a third-person verb form, its stems ("leaves": "leave", "leav")."""
    out = [word]
    if len(word) > 3 and word.endswith("ies"):
        out.append(word[:-3] + "y")
    elif len(word) > 3 and word.endswith("es"):
        out += [word[:-1], word[:-2]]
    elif len(word) > 3 and word.endswith("s") and not word.endswith("ss"):
        out.append(word[:-1])
    return out
