"""The question forms' interface (`Form`), their registry (`FORMS`, `register_form`,
`forms_by_order`), the selection that applies a plan's form (`select`) and the helpers the
forms share. The forms themselves are in `forms`."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from sync4d.phase3.relational.plan import Clause, Plan, RelationalError, Selected
from sync4d.phase3.relational.timeline import Timeline, episodes

if TYPE_CHECKING:
    from sync4d.phase3.relational.reading import Reading

__all__ = ["FORMS", "Form", "atoms_text", "forms_by_order", "need_atom", "nth_word", "ranked",
           "register_form", "select"]


def need_atom(text: str, c: Clause, what: str) -> None:
    """RelationalError unless clause `c` has an atom for `what` to count."""
    if not c.atoms:
        raise RelationalError(f"{text!r}: {what} counts episodes of a state or event, and "
                              f"none was read in {c.text!r}; name one (\"bounces\", \"is "
                              "falling\", \"at rest\", \"touches the blue ball\")")  # fmt: skip


def nth_word(n: int) -> str:
    """"first", "second", ..., "last" for rank `n` (-1: last)."""
    words = {1: "first", 2: "second", 3: "third", 4: "fourth", 5: "fifth", 6: "sixth",
             -1: "last"}
    return words.get(n, f"{n}th")


def atoms_text(c: Clause) -> str:
    """A clause's atoms as the plan prints them ("contact with background & falling",
    "not(falling)"; "present" without an atom)."""
    a = " & ".join(str(x) for x in c.atoms) or "present"
    return f"not({a})" if c.negated else a


def ranked(cands: list[int], key: dict[int, float], reverse: bool = False) -> list[int]:
    """`cands` by `key` (descending with `reverse`), ties in their own order."""
    return sorted(cands, key=lambda k: (-key[k] if reverse else key[k], cands.index(k)))


class Form(ABC):
    """A question form. `name` is what `Plan.form` and question files say; `order` ranks the
    claims (lower first; the first plan returned wins)."""

    name: ClassVar[str]
    order: ClassVar[int]

    @abstractmethod
    def claim(self, r: Reading, subject: Clause, relation: tuple[str, Clause] | None,
              names: list[str], text: str) -> Plan | None:  # fmt: skip
        """The plan of the reading `r` when this form answers it, else None."""

    @abstractmethod
    def text(self, plan: Plan, inner: str, over: str, of: str, nth: str) -> str:
        """The plan as one line, given the subject's atoms and relation (`inner`), its
        objects (`over`), its one object (`of`) and the rank word (`nth`)."""

    @abstractmethod
    def select(self, plan: Plan, act: np.ndarray, tl: Timeline,
               eps: dict[int, list[tuple[int, int]]]) -> Selected:  # fmt: skip
        """Objects ranked and their intervals from the subject's related frames `act` [K, T]
        (`eps`: each candidate's episodes of them)."""


#: The registered forms by name, in the order question files and summaries list them.
FORMS: dict[str, Form] = {}


def register_form(form: type[Form]) -> type[Form]:
    """Register `form` (a class decorator, or one call) under its `name`."""
    if form.name in FORMS:
        raise ValueError(f"form {form.name!r} is registered twice")
    FORMS[form.name] = form()
    return form


def forms_by_order() -> list[Form]:
    """The registered forms in the order their claims are tried."""
    return sorted(FORMS.values(), key=lambda f: f.order)


def select(plan: Plan, act: np.ndarray, tl: Timeline) -> Selected:
    """Apply `plan`'s selection to the subject's (already related) frames `act` [K, T]."""
    eps = {k: episodes(act[k]) for k in plan.subject.objects}
    return FORMS[plan.form].select(plan, act, tl, eps)
