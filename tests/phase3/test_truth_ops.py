"""The question sets' truth operators (`examples/relational/truth_ops.py`) are code of their own:
they import nothing of the method, and they answer hand-built states as the docs say."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[2] / "examples" / "relational"
sys.path.insert(0, str(HERE))

import truth_ops  # noqa: E402


def test_the_truth_imports_nothing_of_the_method():
    tree = ast.parse((HERE / "truth_ops.py").read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if m.startswith("sync4d")], names


def _spec(form, subject=None, atoms=(), n=None, relation=None, quantity=None, direction=None):
    return dict(question="", form=form, subject=subject, atoms=list(atoms), n=n,
                quantity=quantity, direction=direction, relation=relation, negated=False)


def test_ordinals_counts_relations_on_hand_built_states():
    t = 20
    contact = np.zeros((3, t), bool)
    contact[0, 5:8] = contact[0, 14:16] = True  # a: two contacts
    contact[1, 9:12] = True  # b: one, after a's first
    contact[2, 0:4] = True  # c: under way from the start (no onset)
    states = {"contact": contact}
    names = ["a", "b", "c"]
    h = s = np.zeros((3, t))
    assert truth_ops.answer(_spec("ordinal-objects", atoms=["contact"], n=1), names, states,
                            h, s)[:2] == (0, [(5, 7)])  # fmt: skip
    assert truth_ops.answer(_spec("ordinal-objects", atoms=["contact"], n=-1), names, states,
                            h, s)[0] == 1  # c has no onset  # fmt: skip
    assert truth_ops.answer(_spec("count", "a", ["contact"]), names, states, h, s)[2] == 2
    k, spans, _ = truth_ops.answer(_spec("relation", "b", relation=("before", "a", ["contact"],
                                                                      False, 2)),
                                   names, states, h, s)  # fmt: skip
    assert k == 1 and spans == [(0, 13)]  # before a's second contact
