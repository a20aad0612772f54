"""Texts against a built field: the cache of text embeddings (``RUN/phase3/texts.json``, under
the encoder's fingerprint, so a repeated text loads no encoder and encodes nothing), and which
object a text names: Eq. 15's identity score (`identity`), the similarity to the object names
(`names_score`) and a motion phrase's target (`resolve_target`). The scorers of `query` and
the relational planner of `relational` both stand on it.

The cache grows with every new text unless given a `limit` (a long-lived reader such as
`sync4d serve` keeps at most that many texts, the least recently used dropped first) and may be
kept in memory only (`persist=False`: nothing is written to the run folder).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sync4d.errors import Sync4dError
from sync4d.files import write_text_atomic
from sync4d.phase3 import motion_phrases as mp
from sync4d.phase3.encoders.encoder import Encoder, EncoderError, load_encoder
from sync4d.phase3.field import query_scores
from sync4d.phase3.store import Field
from sync4d.runs.names import FIELD_DIR, TEXT_CACHE

if TYPE_CHECKING:
    from sync4d.phase3.config import Phase3Config

__all__ = ["QueryError", "TextCache", "identity", "names_score", "resolve_target",
           "text_problem"]


class QueryError(Sync4dError, ValueError):
    """A query that cannot be answered (empty text, unknown scorer, bytes that are not text);
    the message says why."""


def text_problem(text: str) -> str | None:
    """Why `text` cannot be encoded, or None: the code points Python makes of bytes that are
    not UTF-8 (surrogate escapes, from a command line, a file name or a JSON escape) have no
    UTF-8 form, and a tokenizer cannot read them."""
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        shown = text.encode("utf-8", "backslashreplace").decode("ascii", "backslashreplace")
        if len(shown) > 60:
            shown = shown[:57] + "..."
        return (f"the text \"{shown}\" holds bytes that are not UTF-8 (an undecodable byte in "
                "the command line, a file or a JSON escape); give the query as UTF-8 text")
    return None


class TextCache:
    """Text embeddings of one run's field, keyed by text, stored in ``RUN/phase3/texts.json``;
    the encoder is loaded only when a text is missing. `limit`: the most texts kept (the least
    recently used dropped first; None: all, as the run's file keeps them); `persist`: False
    keeps new texts in memory only (`save` writes nothing)."""

    def __init__(self, run_dir: str | Path, field: Field, encoder: Encoder | str | None = None,
                 *, limit: int | None = None, persist: bool = True) -> None:  # fmt: skip
        if limit is not None and limit < 1:
            raise ValueError(f"limit: expected a positive number of texts or None, got {limit}")
        self.path = Path(run_dir) / FIELD_DIR / TEXT_CACHE
        self.field = field
        self._encoder = encoder if isinstance(encoder, Encoder) else None
        self._spec = None if isinstance(encoder, Encoder) else encoder
        self.fingerprint = field.encoder.get("fingerprint", "")
        self.limit = limit
        self.persist = persist
        self.texts: dict[str, list[float]] = {}
        self.encoded = 0
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
            if data.get("fingerprint") == self.fingerprint:
                self.texts = dict(data.get("texts", {}))
        except (OSError, ValueError, AttributeError):
            pass  # no cache, or an unreadable one: it is rebuilt
        self._bound()

    def _bound(self, used: Sequence[str] = ()) -> None:
        """With a `limit`: mark `used` as the most recent (dicts keep insertion order), then
        drop the least recently used texts beyond the limit."""
        if self.limit is None:
            return
        for t in used:
            if t in self.texts:
                self.texts[t] = self.texts.pop(t)
        while len(self.texts) > self.limit:
            del self.texts[next(iter(self.texts))]

    def encoder(self) -> Encoder:
        """The field's encoder (loaded on first use); EncoderError when it is not the one the
        field was built with."""
        if self._encoder is None:
            spec = self._spec or self.field.config.get("encoder") or None
            self._encoder = load_encoder(spec)
        if self._encoder.fingerprint != self.fingerprint:
            raise EncoderError(
                f"the field in {self.path.parent} was built with encoder "
                f"{self.field.encoder.get('kind')} ({self.fingerprint[:12]}), not "
                f"{self._encoder.kind} ({self._encoder.fingerprint[:12]}); give that encoder "
                "with --encoder or rebuild the field (fit --out RUN --phases 3)"
            )
        return self._encoder

    def get(self, texts: list[str]) -> np.ndarray:
        """Unit embeddings [n, D] of `texts`, encoding only those not cached."""
        missing = sorted({t for t in texts if t not in self.texts})
        for t in missing:
            problem = text_problem(t)
            if problem:
                raise QueryError(problem)
        if missing:
            emb = self.encoder().encode_texts(missing)
            for t, e in zip(missing, emb, strict=True):
                self.texts[t] = [float(x) for x in e]
            self.encoded += len(missing)
            self.save()
        out = np.asarray([self.texts[t] for t in texts], dtype=np.float64)
        self._bound(texts)
        return out

    def similarity(self, a: list[str], b: list[str]) -> np.ndarray:
        """Cosine similarities [len(a), len(b)] of two text lists."""
        return self.get(a) @ self.get(b).T

    def save(self) -> None:
        """Write the cache atomically (beside the field); nothing when not `persist`."""
        if self.persist and self.path.parent.is_dir():
            write_text_atomic(self.path, json.dumps(
                {"fingerprint": self.fingerprint, "texts": self.texts}) + "\n")


def resolve_target(m: mp.MatchedPredicate, field: Field, cache: TextCache) -> None:
    """Set `m.target` from its target text (background words, names, embeddings)."""
    text = m.target_text
    if not text or m.target is not None:
        return
    words = text.split()
    if any(w in mp.BACKGROUND_WORDS for w in words):
        m.target = 0
        return
    low = [n.lower() for n in field.names]
    for j, n in enumerate(low):
        if n and n in text:
            m.target = field.labels[j]
            return
    q = cache.get([text])[0]
    named = not all(n.startswith("object ") for n in field.names)
    sims = cache.get(field.names) @ q if named else field.static @ q
    m.target = field.labels[int(np.argmax(sims))]


def identity(field: Field, text: str, cache: TextCache, cfg: Phase3Config,
              static_only: bool) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(S [K], sims [K, T]): Eq. 15 of `text`, constant when it is empty."""
    if not text.strip():
        k, t = field.observed.shape
        return np.zeros(k), np.zeros((k, t))
    q = cache.get([text])[0]
    return query_scores(field.static, field.temporal(static_only or cfg.static_only), q,
                        cfg.w_static, cfg.w_temporal)  # fmt: skip


def names_score(field: Field, text: str, cache: TextCache) -> np.ndarray | None:
    """Text-text similarity [K] of `text` to the object names; None when unnamed."""
    if all(n.startswith("object ") for n in field.names) or not text.strip():
        return None
    return cache.get(field.names) @ cache.get([text])[0]
