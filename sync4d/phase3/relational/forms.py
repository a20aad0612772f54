"""The question forms, one small class each, registered by name (`FORMS`, `register_form`):
each form claims the readings it answers (`Form.claim`, tried in `Form.order`), prints its
plan (`Form.text`) and selects objects and intervals from the subject's related frames
(`Form.select`). The evaluation's and the CLI's choices of form come from `FORMS`; a new
form is one class and one `register_form` row.

A claim may compile to another registered form's plan when the grammar says so: a superlative
over a count ("the most bounces") is a count selection."""

from __future__ import annotations

import numpy as np

from sync4d.phase3.relational.plan import Plan, RelationalError, Selected
from sync4d.phase3.relational.registry import (
    FORMS,
    Form,
    atoms_text,
    forms_by_order,
    need_atom,
    nth_word,
    ranked,
    register_form,
    select,
)
from sync4d.phase3.relational.timeline import peak_run

__all__ = ["FORMS", "Count", "CountSelect", "Extreme", "Form", "Negation", "OrdinalEpisodes",
           "OrdinalObjects", "Relation", "forms_by_order", "register_form", "select"]


class OrdinalObjects(Form):
    """The nth object (by the onset of its first episode) of a class: "which ball lands
    first"; "which ball lands after the red ball" is the next one."""

    name, order = "ordinal-objects", 51

    def claim(self, r, subject, relation, names, text):
        if r.ordinal is not None:
            need_atom(text, subject, "an ordinal")
            return Plan(self.name, subject, relation, r.ordinal, names=names)
        if relation is not None and relation[0] == "after" and not subject.specific \
                and subject.atoms:  # fmt: skip
            return Plan(self.name, subject, relation, 1, names=names)
        return None

    def text(self, plan, inner, over, of, nth):
        return f"{nth}({inner}) {over}"

    def select(self, plan, act, tl, eps):
        cands, t = plan.subject.objects, act.shape[1]
        # by onset: an episode under way from the clip's first frames has none in the clip
        lead = tl.onset_frames()
        start = {k: next((float(s) for s, _ in eps[k] if s >= lead), t + (0.0 if eps[k]
                         else np.inf)) for k in cands}  # fmt: skip
        eps = {k: [e for e in eps[k] if e[0] >= lead] or eps[k] for k in cands}
        order = sorted([k for k in cands if np.isfinite(start[k])],
                       key=lambda k: (start[k], cands.index(k)))  # fmt: skip
        n = plan.n or 1
        onset = [k for k in order if start[k] < t] or order
        refusal = None
        names = ", ".join(plan.names[k] for k in cands)
        if n > len(cands):
            refusal = (f"there are only {len(cands)} to rank ({names}): no {nth_word(n)} "
                       f"one ({atoms_text(plan.subject)})")  # fmt: skip
        elif n != -1 and n > len(order):
            refusal = (f"only {len(order)} of {names} show {atoms_text(plan.subject)} in the "
                       f"clip: no {nth_word(n)} one")  # fmt: skip
        if order and refusal is None:
            pick = onset[-1] if n == -1 else order[n - 1]
            order = [pick] + [k for k in order if k != pick]
        order += [k for k in cands if k not in order]
        spans = {} if refusal else {k: eps[k][:1] for k in cands}
        return Selected(order, spans, None, {k: -start[k] for k in cands}, refusal)


class OrdinalEpisodes(Form):
    """The nth episode of one object: "the second bounce of the red ball"."""

    name, order = "ordinal-episodes", 50

    def claim(self, r, subject, relation, names, text):
        if r.ordinal is None:
            return None
        need_atom(text, subject, "an ordinal")
        episodes_of_one = subject.specific and not r.which
        if not episodes_of_one and not (len(subject.objects) < 2 and r.which):
            return None  # the class's objects: `OrdinalObjects`
        return Plan(self.name, subject, relation, r.ordinal, names=names)

    def text(self, plan, inner, over, of, nth):
        return f"{nth}({inner}) {of}"

    def select(self, plan, act, tl, eps):
        k = plan.subject.objects[0]
        n = plan.n or 1
        e = eps[k]
        pick = ([e[-1]] if n == -1 else [e[n - 1]]) if e and (n == -1 or n <= len(e)) else []
        refusal = None
        if not pick:
            had = f"only {len(e)} episode{'s' if len(e) != 1 else ''}" if e else "no episode"
            refusal = (f"the {plan.names[k]} has {had} of {atoms_text(plan.subject)} "
                       f"in the clip: no {nth_word(n)} one")  # fmt: skip
        return Selected([k], {k: pick}, None, {k: float(bool(pick))}, refusal)


class Count(Form):
    """How many episodes one object has: "how many times does the red ball bounce"."""

    name, order = "count", 20

    def claim(self, r, subject, relation, names, text):
        if not r.count_ask:
            return None
        need_atom(text, subject, "how many times")
        return Plan(self.name, subject, relation, names=names)

    def text(self, plan, inner, over, of, nth):
        return f"count({inner}) {of}"

    def select(self, plan, act, tl, eps):
        k = plan.subject.objects[0]
        return Selected([k], {k: eps[k]}, len(eps[k]), {k: float(len(eps[k]))})


class CountSelect(Form):
    """The object with a given count ("bounces twice", "never twice": fewer) or the most /
    fewest episodes (claimed by `Extreme`)."""

    name, order = "count-select", 30

    def claim(self, r, subject, relation, names, text):
        if r.count_n is None:
            return None
        need_atom(text, subject, "a count such as \"twice\"")
        # "never twice": fewer than that many
        return Plan(self.name, subject, relation, r.count_n,
                    direction="fewer" if r.never else None, names=names)  # fmt: skip

    def text(self, plan, inner, over, of, nth):
        if plan.quantity == "count":
            return f"{plan.direction}(count({inner})) {over}"
        return f"count({inner}) {'<' if plan.direction == 'fewer' else '=='} {plan.n} {over}"

    def select(self, plan, act, tl, eps):
        cands = plan.subject.objects
        n = {k: len(eps[k]) for k in cands}
        if plan.quantity == "count":
            key = {k: float(n[k]) if plan.direction == "max" else -float(n[k]) for k in cands}
        else:
            want = plan.n or 0
            key = {k: (1.0 - n[k] / (want + 1) if n[k] < want else -float(n[k] - want + 1))
                   if plan.direction == "fewer" else -abs(n[k] - want) for k in cands}
        order = ranked(cands, key, reverse=True)
        return Selected(order, eps, n[order[0]], key)


class Relation(Form):
    """The subject's frames related to another clause's: "the blue ball while the red ball is
    falling". Claims whatever no other form does."""

    name, order = "relation", 1000

    def claim(self, r, subject, relation, names, text):
        return Plan(self.name, subject, relation, names=names)

    def text(self, plan, inner, over, of, nth):
        s, word = plan.subject, plan.relation[0] if plan.relation else "while"
        who = plan.names[s.objects[0]] if s.specific else over[len("over "):]
        return f"{word}({who}: {inner})"

    def select(self, plan, act, tl, eps):
        cands = plan.subject.objects
        cnt = {k: float(act[k].sum()) for k in cands}
        return Selected(ranked(cands, cnt, reverse=True), eps, None, cnt)


class Extreme(Form):
    """The object with the highest / lowest height, the fastest / slowest speed or the
    longest / shortest episode ("the highest bounce"); over counts, a count selection."""

    name, order = "extreme", 10

    def claim(self, r, subject, relation, names, text):
        if r.extreme is None:
            return None
        q, d = r.extreme
        if q == "duration" and not subject.atoms:
            raise RelationalError(f"{text!r}: \"{'longest' if d == 'max' else 'shortest'}\" "
                                  "compares episodes of a state or event; name one (\"the "
                                  "longest fall\", \"which ball rests the longest\")")  # fmt: skip
        form = CountSelect.name if q == "count" else self.name
        return Plan(form, subject, relation, None, q, d, names)

    def text(self, plan, inner, over, of, nth):
        return f"{plan.direction}({plan.quantity}, {inner}) {over}"

    def select(self, plan, act, tl, eps):
        cands = plan.subject.objects
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
                    v = abs(seg[-1] - seg[0]) if vertical else \
                        (seg.max() if sign > 0 else seg.min())  # fmt: skip
                    cand.append((float(v) * sign, (s, e)))
                best[k] = max(cand, key=lambda x: x[0]) if cand else (-np.inf, None)
            else:
                events = bool(plan.subject.atoms) and plan.relation is None
                qq = np.where(act[k], q, np.nan) if not (act[k].all() or events) else q
                if np.isnan(qq).all():
                    best[k] = (-np.inf, None)
                    continue
                fill = np.nanmin(qq) if sign > 0 else np.nanmax(qq)
                v, run = peak_run(np.where(np.isnan(qq), fill, qq), plan.direction or "max",
                                  scale)  # fmt: skip
                best[k] = (v * sign, run)
        key = {k: best[k][0] for k in cands}
        order = ranked(cands, key, reverse=True)
        return Selected(order, {k: [best[k][1]] if best[k][1] else [] for k in cands}, None,
                        key)  # fmt: skip


class Negation(Form):
    """The object whose frames never hold the clause: "the ball that never rises"."""

    name, order = "negation", 40

    def claim(self, r, subject, relation, names, text):
        if not r.never:
            return None
        need_atom(text, subject, "\"never\"")
        return Plan(self.name, subject, relation, names=names)

    def text(self, plan, inner, over, of, nth):
        return f"never({inner}) {over}"

    def select(self, plan, act, tl, eps):
        cands, t = plan.subject.objects, act.shape[1]
        frames = {k: float(act[k].sum()) for k in cands}
        order = ranked(cands, frames)
        return Selected(order, {k: [(0, t - 1)] if frames[k] == 0 else [] for k in cands},
                        None, {k: -frames[k] for k in cands})  # fmt: skip


for _form in (OrdinalObjects, OrdinalEpisodes, Count, CountSelect, Relation, Extreme, Negation):
    register_form(_form)
