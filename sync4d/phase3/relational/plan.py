"""What a relational question compiles to: atoms, clauses and the plan (the form and its
parameters), and what evaluating a plan gives (`Selected`). Data only; `reading` builds plans,
`forms` renders and selects, `timeline` evaluates."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field

from sync4d.errors import Sync4dError
from sync4d.phase3.relational.words import ATOMS

__all__ = ["Atom", "Clause", "Plan", "RelationalError", "Selected"]


class RelationalError(Sync4dError, ValueError):
    """A relational question that cannot be read; the message says what to write instead."""


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
    #: "between X and Y" / "from X to Y": the second clause (Y); this clause is X.
    then: Clause | None = None


@dataclass
class Plan:
    """A compiled question: the `form` (a name in `forms.FORMS`), the `subject` clause, an
    optional relation (word, other clause) and the selection's parameters."""

    form: str
    subject: Clause
    relation: tuple[str, Clause] | None = None
    n: int | None = None  # ordinal rank (-1 last) or the count of a count selection
    quantity: str | None = None  # extreme: height, speed, duration, count
    direction: str | None = None  # max or min
    names: list[str] = dc_field(default_factory=list)  # the field's object names


@dataclass
class Selected:
    """An operator's result: objects ranked (field indices, best first), each object's
    intervals, the answer's count (count forms) and a ranking key per object (for scores)."""

    order: list[int]
    spans: dict[int, list[tuple[int, int]]]
    count: int | None = None
    keys: dict[int, float] = dc_field(default_factory=dict)
    #: Set when the question asks for what is not there ("the fifth ball to land" of three
    #: balls): the sentence that says so; the answer then names no object.
    refusal: str | None = None
