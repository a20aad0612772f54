"""Phase 3 as a stage: the language field of the run's Phase 2 model, built after the fit's
summary (it trains nothing) with the fit's ``phase3`` settings and saved into the run folder
(`sync4d.pipeline.phase3.build_phase3`).
"""

from __future__ import annotations

from sync4d.events import FieldBuilt, Phase3Started, emit
from sync4d.pipeline.phase3 import build_phase3
from sync4d.pipeline.stages.base import FitState, Stage

__all__ = ["PHASE3", "Phase3Stage"]


class Phase3Stage(Stage):
    """Phase 3: the language field of the finished Phase 2 run in the run folder."""

    phase = 3
    name = "phase3"
    task = "phase3"

    def start(self, fit: FitState) -> None:
        from sync4d.phase3 import load_encoder

        cfg3 = fit.cfg.phase3
        encoder = load_encoder(cfg3.encoder or None)
        emit(Phase3Started(encoder.kind, encoder.dim, bool(encoder.closed_vocabulary)))
        built = build_phase3(fit.run_dir, cfg3, threads=fit.threads, data=fit.data_path,
                             encoder=encoder)  # fmt: skip
        field, t = built.field, built.field.timings
        emit(FieldBuilt(len(field.labels), len(field.times), int(t["crops"]),
                        float(field.observed.mean()), t["total_s"], t["observe_s"],
                        t["encode_s"], str(built.folder)))  # fmt: skip
        fit.built = built

    def counts(self, fit: FitState) -> dict:
        return dict(fit.built.field.counts)


#: The Phase 3 stage.
PHASE3 = Phase3Stage()
