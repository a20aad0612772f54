"""Answering a text query on a built field: which object, and when.

The scorers are registered here, once each: a function decorated with `@_scorer(name, summary)`
scores every object for a text and says when it is active. The registry (`SCORER_TABLE`, in
registration order) gives `SCORERS` (their names), the order `eval --queries` reports them in,
and the choices and help of the command line; adding a scorer touches this file only. The
design of each is its function's docstring: ``full`` (the default), ``paper`` (Eq. 15),
``static`` (the static-only ablation), ``motion`` and ``names`` (both beyond the paper).

Text embeddings are cached in ``RUN/phase3/texts.json`` under the encoder's fingerprint, so a
repeated query loads no encoder and encodes nothing (`sync4d.phase3.texts`, which also says
which object a text names, for these scorers and the relational planner alike).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3 import states
from sync4d.phase3.activation import activate, intervals
from sync4d.phase3.encoders.encoder import Encoder
from sync4d.phase3.field import query_scores
from sync4d.phase3.store import Field, FieldError, load_field
from sync4d.phase3.texts import (
    QueryError,
    TextCache,
    identity,
    names_score,
    resolve_target,
    text_problem,
)

if TYPE_CHECKING:
    from sync4d.phase3.config import Phase3Config

__all__ = ["DEFAULT_SCORER", "SCORERS", "SCORER_TABLE", "QueryError", "Scorer", "TextCache",
           "field_settings",
           "answer", "query"]


@dataclass
class _Scored:
    score: np.ndarray  # [K] ranking score
    active: np.ndarray  # [K, T] bool
    sims: np.ndarray  # [K, T] the per-frame curve the timeline plots
    identity: np.ndarray  # [K]
    motion: np.ndarray | None = None  # [K] fraction of frames the motion holds


_Result = tuple[_Scored, list[mp.MatchedPredicate], str]


@dataclass(frozen=True)
class Scorer:
    """A registered scorer: its `name` (``--scorer NAME``), a one-line `summary` (the command
    line's help) and `score(field, text, rule, cfg, cache)` -> (scores, matched motion phrases,
    the identity text). `needs_names`: it answers only runs whose objects are named
    (`eval --queries` leaves it out on others)."""

    name: str
    summary: str
    score: Callable[[Field, str, str, Any, TextCache], _Result]
    needs_names: bool = False


#: Every scorer by name, in the order `eval --queries` reports them.
SCORER_TABLE: dict[str, Scorer] = {}


def _scorer(name: str, summary: str, *, needs_names: bool = False):
    """Register the decorated function as scorer `name` (see `Scorer`)."""

    def register(fn: Callable[[Field, str, str, Any, TextCache], _Result]):
        SCORER_TABLE[name] = Scorer(name, summary, fn, needs_names)
        return fn

    return register


def _by_frames(field: Field, text: str, rule: str, s: np.ndarray, sims: np.ndarray) -> _Result:
    """Scores `s` [K] whose active frames are `rule` on the per-frame similarities `sims`."""
    k = field.observed.shape[0]
    act = np.stack([activate(sims[j], rule) for j in range(k)])
    return _Scored(s, act, sims, s), [], text


def _motion(field: Field, text: str, rule: str, cfg: Phase3Config, cache: TextCache,
            with_names: bool) -> _Result:  # fmt: skip
    """The query's motion phrases decide the frames; the identity part is the paper's score of
    the rest of the query, plus the names' when `with_names` (and the objects are named)."""
    k, t = field.observed.shape
    matched, rest = mp.match_predicates(text, cache.similarity, cfg.phrase_match)
    s, sims = identity(field, rest if matched else text, cache, cfg, False)
    ident = s.copy()
    if with_names:
        ns = names_score(field, rest if matched else text, cache)
        if ns is not None:
            ident = ident + ns
    if not matched:
        act = np.stack([activate(sims[j], rule) for j in range(k)])
        return _Scored(ident, act, sims, ident), [], text
    truth = np.ones((k, t), bool)
    for m in matched:
        resolve_target(m, field, cache)
        truth &= states.holds(field, m, cfg)
    frac = truth.mean(1)
    # Ranking: the motion happens at all (2), how often (1), then identity (< 1 in size).
    span = float(np.ptp(ident)) if k > 1 else 0.0
    ident_n = (ident - ident.min()) / span if span > 0 else np.zeros(k)
    score = 2.0 * truth.any(1) + frac + 0.999 * ident_n
    return _Scored(score, truth, truth.astype(np.float64), ident, frac), matched, rest


@_scorer("full", "motion phrases + the paper's score + object names")
def _full(field: Field, text: str, rule: str, cfg: Phase3Config, cache: TextCache) -> _Result:
    """`motion` whose identity part is the paper's score plus the names' (when the objects are
    named); without a motion phrase it is `paper` plus `names`."""
    return _motion(field, text, rule, cfg, cache, True)


@_scorer("paper", "Eq. 15 only")
def _paper(field: Field, text: str, rule: str, cfg: Phase3Config, cache: TextCache) -> _Result:
    """Eq. 15, S(k; q) = w_s <e_static_k, q> + w_t max_f <e_sync_k,f, q>; the top object's
    active frames by Appendix F's rule on <e_sync_k,f, q> (or 4D LangSplat's mean rule)."""
    s, sims = identity(field, text, cache, cfg, False)
    return _by_frames(field, text, rule, s, sims)


@_scorer("static", "the static-only ablation")
def _static(field: Field, text: str, rule: str, cfg: Phase3Config, cache: TextCache) -> _Result:
    """`paper` with e_sync = e_static (the paper's static-only ablation)."""
    s, sims = identity(field, text, cache, cfg, True)
    return _by_frames(field, text, rule, s, sims)


@_scorer("no-kinematics", "the W = 0 ablation: observations kept, no kinematic term")
def _no_kinematics(field: Field, text: str, rule: str, cfg: Phase3Config,
                   cache: TextCache) -> _Result:  # fmt: skip
    """`paper` on the field with every ridge map W_k = 0 (`Field.unconditioned`: e_hat =
    e_static, blended with the observations and smoothed as e_sync is): what the kinematic
    conditioning adds (`phase3.kinematics = false` builds the same field)."""
    if cfg.static_only or not text.strip():
        return _static(field, text, rule, cfg, cache)
    s, sims = query_scores(field.static, field.unconditioned(), cache.get([text])[0],
                           cfg.w_static, cfg.w_temporal)  # fmt: skip
    return _by_frames(field, text, rule, s, sims)


@_scorer("motion", "the query's motion phrases, then the paper's score")
def _motion_only(field: Field, text: str, rule: str, cfg: Phase3Config,
                 cache: TextCache) -> _Result:  # fmt: skip
    """Beyond the paper: the query's motion phrases (`motion_phrases`) decide the frames; the
    objects are ranked first by whether the motion happens at all, then by the fraction of
    frames it holds, then by the paper's score of the rest of the query (its identity part)."""
    return _motion(field, text, rule, cfg, cache, False)


@_scorer("names", "the query's similarity to object names", needs_names=True)
def _names(field: Field, text: str, rule: str, cfg: Phase3Config, cache: TextCache) -> _Result:
    """Beyond the paper: identity by the text-text similarity of the query to each object's
    name (from the masks' labels.json), when the ranking of `paper` would need an
    open-vocabulary image encoder; frames as `paper`."""
    _, sims = identity(field, text, cache, cfg, False)
    ns = names_score(field, text, cache)
    if ns is None:
        raise QueryError("the names scorer needs named objects (labels.json beside the "
                         "masks); this run's objects have no names")  # fmt: skip
    return _by_frames(field, text, rule, ns, sims)


#: The scorers' names, in `SCORER_TABLE`'s order; `query` answers with the first by default.
SCORERS: tuple[str, ...] = tuple(SCORER_TABLE)
DEFAULT_SCORER = SCORERS[0]


#: The Phase 3 settings a query reads (the field records every one it was built with).
_QUERY_KEYS = ("w_static", "w_temporal", "activation", "static_only", "moving_speed",
               "rest_speed", "vertical_speed", "closing_speed", "contact_gap", "phrase_match",
               "phrase_smooth", "phrase_min_frames")  # fmt: skip


def field_settings(field: Field) -> SimpleNamespace:
    """The settings the field was built with, as attributes (no torch import for a query)."""
    missing = [k for k in _QUERY_KEYS if k not in field.config]
    if missing:
        raise FieldError(f"the field's header lacks the settings {missing}; rebuild it with "
                         "`fit --out RUN --phases 3`")  # fmt: skip
    return SimpleNamespace(**field.config)


def answer(
    field: Field, text: str, *, cache: TextCache, scorer: str = DEFAULT_SCORER,
    rule: str | None = None, cfg: Phase3Config | None = None, relational: bool = True,
) -> dict:  # fmt: skip
    """The answer to `text` on `field` as plain data: every object ranked with its score and
    active frame intervals (frames and times), the matched motion phrases, the timeline.
    With the default scorer (and `relational`), a relational question ("which ball lands
    first", `sync4d.phase3.relational`) is answered by its plan: ``plan`` says how it was read
    (None: no relational question), ``fallback`` why one was not (today's scorer answered)."""
    text = " ".join(str(text).split())
    if not text:
        raise QueryError("empty query: give a text such as \"the red ball while it is falling\"")
    problem = text_problem(text)
    if problem:
        raise QueryError(problem)
    if scorer not in SCORERS:
        raise QueryError(f"unknown scorer {scorer!r}: expected one of {', '.join(SCORERS)}")
    cfg = cfg or field_settings(field)
    rule = rule or cfg.activation
    plan = fallback = None
    if relational and scorer == DEFAULT_SCORER:
        from sync4d.phase3.relational import RelationalError, answer_relational

        try:
            rel = answer_relational(field, text, cache, cfg)
        except RelationalError as e:
            rel, fallback = None, f"{e}; answered by the {scorer} scorer instead"
        else:
            if rel is None:
                fallback = (f"no relational word read (first, how many, before, while, "
                            f"highest, never, ...); answered by the {scorer} scorer")  # fmt: skip
        if rel is not None:
            plan = rel
            sc = _Scored(rel["score"], rel["active"], rel["active"].astype(np.float64),
                         rel["score"])  # fmt: skip
            matched, rest = [], text
    if plan is None:
        sc, matched, rest = SCORER_TABLE[scorer].score(field, text, rule, cfg, cache)
    order = np.argsort(-sc.score, kind="stable") if plan is None else np.asarray(plan["order"])
    times = field.times
    objects = []
    for j in order:
        iv = intervals(sc.active[j])
        objects.append({
            "label": field.labels[j], "name": field.names[j], "score": float(sc.score[j]),
            "identity_score": float(sc.identity[j]),
            "motion_fraction": None if sc.motion is None else float(sc.motion[j]),
            "intervals": [{"start": int(a), "end": int(b), "t0": float(times[a]),
                           "t1": float(times[b])} for a, b in iv],  # fmt: skip
            "active_frames": int(sc.active[j].sum()),
        })  # fmt: skip
    return {
        "query": text, "scorer": scorer, "rule": rule, "identity_text": rest,
        "plan": None if plan is None else plan["plan"],
        "form": None if plan is None else plan["form"],
        "count": None if plan is None else plan["count"], "fallback": fallback,
        "refusal": None if plan is None else plan["refusal"],
        "encoder": field.encoder.get("kind"),
        "closed_vocabulary": bool(field.encoder.get("closed_vocabulary", False)),
        "motion_phrases": [{"predicate": m.predicate.name, "phrase": m.phrase,
                            "similarity": m.similarity, "target": m.target}
                           for m in matched],  # fmt: skip
        "objects": objects,
        "times": [float(x) for x in times],
        "timeline": {field.names[j]: [float(x) for x in sc.sims[j]] for j in range(len(order))},
        "active": {field.names[j]: [bool(x) for x in sc.active[j]] for j in range(len(order))},
    }


def query(
    run_dir: str | Path, text: str, *, scorer: str = DEFAULT_SCORER, rule: str | None = None,
    encoder: Encoder | str | None = None,
) -> dict:  # fmt: skip
    """Answer `text` on the field of the run in `run_dir` (see `answer`); `encoder` overrides
    the one the field records (it must be the same model)."""
    field = load_field(run_dir)
    return answer(field, text, cache=TextCache(run_dir, field, encoder), scorer=scorer, rule=rule)
