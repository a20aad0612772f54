"""The image-text encoder interface of Phase 3 (Sec. 3.5: E_img, E_txt) and how one is chosen.

Every encoder maps images and texts into one embedding space of `dim` dimensions (a property of
the loaded model, never assumed) and returns L2-normalised float32 rows. Two kinds exist:

* ``siglip``: a SigLIP model exported to ONNX (vision and text graphs plus tokenizer files) in a
  local directory, run with onnxruntime (`sync4d.phase3.encoders.siglip`). The paper's encoder.
* ``offline``: the closed-vocabulary default that needs no download
  (`sync4d.phase3.encoders.offline`): ImageNet AlexNet features mapped linearly into MiniLM's
  sentence space, the map fitted on generated renders of coloured shapes. It knows
  colours and shapes, not the open world.

The kinds are registered once, in `ENCODERS`: `load_encoder(spec)` picks one (a directory path
means SigLIP-ONNX from that directory, ``"offline"`` or nothing, with ``$SYNC4D_ENCODER`` unset,
the offline default), and the config's allowed values and the command line's help read it.
"""

from __future__ import annotations

import abc
import importlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sync4d.errors import Sync4dError
from sync4d.files import file_sha256

__all__ = ["CONVERT_COMMAND", "DEFAULT_ENCODER", "ENCODERS", "ENCODER_ENV", "Encoder",
           "EncoderError", "EncoderKind", "describe_specs", "encoder_problem", "file_sha256",
           "load_encoder", "normalise_rows"]

#: Environment variable naming the encoder when ``--encoder`` is not given.
ENCODER_ENV = "SYNC4D_ENCODER"
#: The command that writes a SigLIP-ONNX folder, as messages name it.
CONVERT_COMMAND = "python -m sync4d encoder convert"


@dataclass(frozen=True)
class EncoderKind:
    """An encoder kind `load_encoder` knows: `kind` (`Encoder.kind`, what a field records),
    `word` (the spec that names it, such as "offline"; "" for the kind read from a model folder),
    `noun` (how help texts name the spec), a one-line `summary`, and the `module` and `cls`
    that load it (imported on use: a cached query loads none)."""

    kind: str
    word: str
    noun: str
    summary: str
    module: str
    cls: str


#: Every encoder kind, by kind; the default first.
ENCODERS: dict[str, EncoderKind] = {e.kind: e for e in (
    EncoderKind("offline", "offline", '"offline"', "the closed-vocabulary default",
                "sync4d.phase3.encoders.offline", "OfflineEncoder"),
    EncoderKind("siglip", "", "a SigLIP-ONNX model folder",
                "the paper's encoder; `sync4d encoder convert` writes one",
                "sync4d.phase3.encoders.siglip", "SiglipOnnxEncoder"),
)}  # fmt: skip
#: The spec of the default kind (no --encoder and no $SYNC4D_ENCODER).
DEFAULT_ENCODER = next(iter(ENCODERS.values())).word
_NAMED = {e.word: e for e in ENCODERS.values() if e.word}
_FOLDER = next(e for e in ENCODERS.values() if not e.word)


def describe_specs(*extra: str, summaries: bool = False) -> str:
    """The specs `load_encoder` accepts, for help texts: '"offline" or a SigLIP-ONNX model
    folder', after `extra` ones; with `summaries`, each followed by its summary in brackets."""
    words = [*extra, *(f"{e.noun} ({e.summary})" if summaries else e.noun
                       for e in ENCODERS.values())]  # fmt: skip
    return ", ".join(words[:-1]) + " or " + words[-1] if len(words) > 1 else words[0]


def encoder_problem(text: str) -> str | None:
    """What is wrong with an encoder spec (`phase3.encoder`), None if nothing ("" is
    $SYNC4D_ENCODER, else the default)."""
    if text == "" or text in _NAMED:
        return None
    if Path(text).is_file():
        return f"expected a model folder (vision.onnx, text.onnx, ...), got the file {text!r}"
    return None


class EncoderError(Sync4dError, RuntimeError):
    """An encoder that cannot be loaded or used; the message names the file and what to do."""


def normalise_rows(x: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Rows of `x` [n, D] scaled to unit L2 norm (zero rows stay zero), as float32."""
    x = np.asarray(x, dtype=np.float64)
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return (x / np.maximum(n, eps)).astype(np.float32)


class Encoder(abc.ABC):
    """An image-text encoder: `encode_images` and `encode_texts` return unit rows [n, dim]."""

    #: Short kind name ("siglip", "offline").
    kind: str = ""
    #: Whether only a closed vocabulary (colours, shapes) is meaningful to it.
    closed_vocabulary: bool = False

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Embedding dimension D of the loaded model."""

    @property
    @abc.abstractmethod
    def fingerprint(self) -> str:
        """A digest of the model files: embeddings cached under another fingerprint are stale."""

    @abc.abstractmethod
    def encode_images(self, images: list[np.ndarray]) -> np.ndarray:
        """Embeddings [n, dim] (float32, unit rows) of `images`: each [H, W, 3] float in [0, 1]
        (any size; the encoder resizes)."""

    @abc.abstractmethod
    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Embeddings [n, dim] (float32, unit rows) of `texts`."""

    def describe(self) -> dict:
        """What the field file records about the encoder."""
        return {"kind": self.kind, "dim": self.dim, "fingerprint": self.fingerprint,
                "closed_vocabulary": self.closed_vocabulary}  # fmt: skip


def _encoder_class(entry: EncoderKind) -> type[Encoder]:
    return getattr(importlib.import_module(entry.module), entry.cls)


def load_encoder(spec: str | Path | None = None) -> Encoder:
    """The encoder named by `spec` (see `ENCODERS`): a SigLIP-ONNX model directory, or
    ``"offline"``; None reads ``$SYNC4D_ENCODER`` and falls back to the offline default."""
    if spec is None or str(spec) == "":
        spec = os.environ.get(ENCODER_ENV) or DEFAULT_ENCODER
    if str(spec) in _NAMED:
        return _encoder_class(_NAMED[str(spec)])()
    path = Path(spec)
    if not path.is_dir():
        raise EncoderError(
            f"{path}: no such encoder directory; give a folder written by "
            f"`{CONVERT_COMMAND} --out DIR`, or --encoder {DEFAULT_ENCODER}"
        )
    return _encoder_class(_FOLDER)(path)
