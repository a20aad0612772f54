"""Stepping a trainer in tests: the library has one training loop (the pipeline's); tests that
drive a `Phase1Trainer` directly step it here."""

from __future__ import annotations

from sync4d.phase1.trainer import Phase1Trainer


def train(trainer: Phase1Trainer, iterations: int) -> dict:
    """Run `iterations` steps of `trainer`; the last step's stats ({} for none)."""
    stats: dict = {}
    for _ in range(iterations):
        stats = trainer.step()
    return stats
