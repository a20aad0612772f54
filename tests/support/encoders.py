"""Deterministic stand-ins for an image-text encoder, for tests of what Phase 3 and the export
do with embeddings (the real encoders have their own tests)."""

from __future__ import annotations

import numpy as np

from sync4d.phase3.encoders.encoder import Encoder, normalise_rows

COLOURS = {"red": (1.0, 0.1, 0.1), "green": (0.1, 0.8, 0.1), "blue": (0.1, 0.2, 1.0)}


class ColourEncoder(Encoder):
    """Images: the mean colour of the crop's saturated pixels; texts: the colour words they
    name (a tiny closed vocabulary, exact and deterministic)."""

    kind = "test-colour"
    closed_vocabulary = True

    def __init__(self) -> None:
        self.images = 0
        self.texts = 0

    @property
    def dim(self) -> int:
        return 4

    @property
    def fingerprint(self) -> str:
        return "colour-v1"

    def encode_images(self, images):
        self.images += len(images)
        out = []
        for im in images:
            px = im.reshape(-1, 3)
            sat = px.max(1) - px.min(1)
            sel = px[sat > 0.25] if (sat > 0.25).sum() > 3 else px
            out.append(np.r_[sel.mean(0), 0.05])
        return normalise_rows(np.stack(out))

    def encode_texts(self, texts):
        self.texts += len(texts)
        out = []
        for t in texts:
            v = np.array([0.0, 0.0, 0.0, 0.05])
            for word, rgb in COLOURS.items():
                if word in t.split():
                    v[:3] += rgb
            out.append(v)
        return normalise_rows(np.stack(out))
