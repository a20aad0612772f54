"""Reading one clause: which of its words name the subject and which name its atoms (a
motion state or event), through the text encoder (the package notes), and the targets of the
relational atoms ("touches the blue ball")."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3.relational.plan import Atom, Clause
from sync4d.phase3.relational.words import (
    ATOM_EXTRA,
    ATOM_MATCH,
    ATOM_STRONG,
    ATOMS,
    CLASS_MARGIN,
    DETERMINERS,
    ENDINGS,
    NEGATIONS,
    ONTO,
    PRONOUNS,
    STOP,
    TOWARDS,
    stems,
)
from sync4d.phase3.texts import TextCache, identity, names_score, resolve_target

if TYPE_CHECKING:
    from sync4d.phase3.store import Field

__all__ = ["read_clause", "resolve"]


def _sim(cache: TextCache, a: list[str], b: list[str]) -> np.ndarray:
    return cache.similarity(a, b) if a and b else np.zeros((len(a), len(b)))


def _identity_scores(field: Field, text: str, cache: TextCache, cfg) -> np.ndarray:
    """The `full` scorer's identity of `text` per object: Eq. 15 plus the names' similarity."""
    s, _ = identity(field, text, cache, cfg, False)
    ns = names_score(field, text, cache)
    return s + ns if ns is not None else s


def read_clause(words: list[str], field: Field, cache: TextCache, cfg, *,
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
        forms = [stems(w) for w in cw]
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
    # "comes down onto the plate": a motion towards something that ends on it is the contact
    for n, (s, e, a) in enumerate(found):
        if a.name not in TOWARDS:
            continue
        if any(w in ONTO for w in words[s:e]):  # the span read already holds it
            found[n] = (s, e, Atom("contact", a.words, a.similarity))
        elif e < len(words) and words[e] in ONTO:
            role[e] = "atom"
            found[n] = (s, e + 1, Atom("contact", f"{a.words} {words[e]}", a.similarity))
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
        resolve(a, field, cache)
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


def resolve(a: Atom, field: Field, cache: TextCache) -> None:
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
