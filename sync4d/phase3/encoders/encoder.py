"""The image-text encoder interface of Phase 3 (Sec. 3.5: E_img, E_txt) and how one is chosen.

Every encoder maps images and texts into one embedding space of `dim` dimensions (a property of
the loaded model, never assumed) and returns L2-normalised float32 rows. Two kinds exist:

* ``siglip``: a SigLIP model exported to ONNX (vision and text graphs plus tokenizer files) in a
  local directory, run with onnxruntime (`sync4d.phase3.encoders.siglip`). The paper's encoder.
* ``offline``: the closed-vocabulary default that needs no download
  (`sync4d.phase3.encoders.offline`): ImageNet AlexNet features mapped linearly into MiniLM's
  sentence space, the map fitted on generated renders of coloured shapes. It knows
  colours and shapes, not the open world.

`load_encoder(spec)` picks one: a directory path means SigLIP-ONNX from that directory,
``"offline"`` (or nothing, with ``$SYNC4D_ENCODER`` unset) the offline default.
"""

from __future__ import annotations

import abc
import os
from pathlib import Path

import numpy as np

from sync4d.files import file_sha256

__all__ = ["ENCODER_ENV", "Encoder", "EncoderError", "file_sha256", "load_encoder",
           "normalise_rows"]

#: Environment variable naming the encoder when ``--encoder`` is not given.
ENCODER_ENV = "SYNC4D_ENCODER"


class EncoderError(RuntimeError):
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


def load_encoder(spec: str | Path | None = None) -> Encoder:
    """The encoder named by `spec`: a SigLIP-ONNX model directory, or ``"offline"``; None reads
    ``$SYNC4D_ENCODER`` and falls back to the offline default."""
    if spec is None or str(spec) == "":
        spec = os.environ.get(ENCODER_ENV) or "offline"
    if str(spec) == "offline":
        from sync4d.phase3.encoders.offline import OfflineEncoder

        return OfflineEncoder()
    path = Path(spec)
    if not path.is_dir():
        raise EncoderError(
            f"{path}: no such encoder directory; give a folder written by "
            "`python -m sync4d encoder export --out DIR`, or --encoder offline"
        )
    from sync4d.phase3.encoders.siglip import SiglipOnnxEncoder

    return SiglipOnnxEncoder(path)
