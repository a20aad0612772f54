"""Hand-built language fields for tests of what Phase 3 reads of motion (no run needed)."""

from __future__ import annotations

import dataclasses

import numpy as np

from sync4d.phase3.config import Phase3Config
from sync4d.phase3.store import Field

NAMES = ["red ball", "green ball", "blue ball"]
T = 61


def bouncing_field(encoder) -> Field:
    """Three balls over 61 frames, z up: the red ball drops and bounces twice (lowest at
    frames 20 and 44), the green ball drops and bounces once (frame 36), the blue ball lies
    on the plate and never leaves it; embeddings: each ball's name, so identity reads."""
    times = np.linspace(0.0, 1.0, T)

    def arcs(lows: list[float], start: float, radius: float) -> np.ndarray:
        z = np.full(T, radius)
        knots = [0.0, *lows, 1.0]
        for i in range(len(knots) - 1):
            a, b = knots[i], knots[i + 1]
            top = start if i == 0 else 0.6 * start
            sel = (times >= a) & (times <= b)
            if i == 0:  # a fall from rest at `start`
                z[sel] = radius + (top - radius) * (1 - ((times[sel] - a) / (b - a)) ** 2)
            elif i == len(knots) - 2:  # the last rise, cut at the end
                u = (times[sel] - a) / (2 * (b - a) if b < 1 else 0.4)
                z[sel] = radius + (top - radius) * (1 - (1 - 2 * np.minimum(u, 0.5)) ** 2)
            else:
                u = (times[sel] - a) / (b - a)
                z[sel] = radius + (top - radius) * 4 * u * (1 - u)
        return z

    red = arcs([20 / 60, 44 / 60], 1.0, 0.1)
    green = arcs([36 / 60], 0.8, 0.1)
    blue = np.full(T, 0.1)
    centroids = np.zeros((3, T, 3))
    centroids[0, :, 2], centroids[1, :, 2], centroids[2, :, 2] = red, green, blue
    centroids[1, :, 0], centroids[2, :, 0] = 1.0, 2.0
    centroids[2, 30:, 0] = 2.0 + np.linspace(0.0, 0.6, T - 30)  # the blue ball rolls late
    radius = np.full(3, 0.1)
    gaps = np.full((3, 1, T), 1.0)
    gaps[:, 0] = centroids[..., 2] - radius[:, None]
    d = encoder.dim
    emb = encoder.encode_texts(NAMES)
    cfg = dataclasses.asdict(Phase3Config())
    return Field(
        labels=[1, 2, 3], names=list(NAMES), times=times,
        obs=np.repeat(emb[:, None], T, 1), observed=np.ones((3, T), bool), static=emb,
        features=np.zeros((3, T, 28)), standardised=np.zeros((3, T, 29)),
        ridge=np.zeros((3, 29, d)), pred=np.repeat(emb[:, None], T, 1),
        sync=np.repeat(emb[:, None], T, 1), visible=np.ones((3, T)),
        boxes=np.zeros((3, T, 4)), gaps=gaps, radius=radius, centroids=centroids,
        gap_labels=[0], views=[["v"] * T] * 3, up=np.array([0.0, 0.0, 1.0]),
        right=np.array([1.0, 0.0, 0.0]),
        encoder={"kind": encoder.kind, "fingerprint": encoder.fingerprint}, config=cfg,
    )  # fmt: skip
