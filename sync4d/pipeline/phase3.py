"""Phase 3 in the pipeline: the language field of a finished Phase 2 run, built with the run's
own recorded settings (or a config file's), saved into the run folder with the text cache of
the object names. `fit` (after Phase 2, or `--phases 3` alone) and `bench phase3` both build
through `build_phase3`, so they cannot drift apart.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

from sync4d.config import RunConfig, apply_overrides, load_config
from sync4d.phase3.config import Phase3Config
from sync4d.pipeline.record import read_record, recorded_config

__all__ = ["Phase3Build", "build_phase3", "phase3_config", "phase3_run_config",
           "resolved_encoder"]  # fmt: skip


@dataclass(frozen=True)
class Phase3Build:
    """A built field (`sync4d.phase3.store.Field`), the encoder that built it, the folder it
    was saved to (None when not saved) and the Gaussian count of the run's model."""

    field: object
    encoder: object
    folder: Path | None
    gaussians: int


def phase3_run_config(run_dir: Path, config: str | Path | None = None,
                      overrides: list[str] | tuple[str, ...] = ()) -> RunConfig:  # fmt: skip
    """The config of the run in `run_dir` as Phase 3 rebuilds its field: the one it recorded
    (or `config`'s file), then `overrides` (``phase3.*=...``)."""
    cfg: RunConfig = (load_config(config) if config
                      else recorded_config(read_record(run_dir), run_dir))  # fmt: skip
    return apply_overrides(cfg, list(overrides))


def phase3_config(run_dir: Path, config: str | Path | None = None,
                  overrides: list[str] | tuple[str, ...] = ()) -> Phase3Config:  # fmt: skip
    """Phase 3's settings for the run in `run_dir` (`phase3_run_config`'s ``phase3``)."""
    return phase3_run_config(run_dir, config, overrides).phase3


def resolved_encoder(cfg3: Phase3Config) -> Phase3Config:
    """`cfg3` with its encoder spelled as the field records it: "offline", or the absolute
    folder of a SigLIP-ONNX model ("" means $SYNC4D_ENCODER, else offline)."""
    spec = cfg3.encoder or os.environ.get("SYNC4D_ENCODER") or "offline"
    resolved = str(Path(spec).resolve()) if spec != "offline" else spec
    return dataclasses.replace(cfg3, encoder=resolved)


def build_phase3(run_dir: Path, cfg3: Phase3Config, *, threads: int | None = None,
                 data: Path | None = None, save: bool = True,
                 encoder=None) -> Phase3Build:  # fmt: skip
    """Build the language field of the Phase 2 run in `run_dir` with `cfg3` (the dataset from
    `data` or the run's record; `encoder` loaded from `cfg3` when None); with `save`, write it
    and the text cache of its object names into the run folder."""
    from sync4d.phase3 import build_field, load_encoder
    from sync4d.phase3.query import TextCache
    from sync4d.runs import load_run

    run = load_run(run_dir)
    if encoder is None:
        encoder = load_encoder(cfg3.encoder or None)
    field = build_field(run, resolved_encoder(cfg3), encoder, data=data, threads=threads)
    if not save:
        return Phase3Build(field, encoder, None, run.model.num_gaussians)
    folder = field.save(run_dir)
    TextCache(run_dir, field, encoder).get(field.names)
    return Phase3Build(field, encoder, folder, run.model.num_gaussians)
