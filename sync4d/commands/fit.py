"""``python -m sync4d fit [DATA] --out runs/NAME``: Phase 1 then Phase 2 training (``phases``)
into a run folder, then the test metrics and Phase 2's diagnostics. The command parses its
arguments into a `sync4d.pipeline.request.FitRequest`, whose `fit_request` owns what a run
folder may continue (the resume policy) and does it; what the pipeline reports
(`sync4d.events`) is printed by `sync4d.progress.TerminalRenderer`; the exit status says how
it ended (2: a bad input, 3: the watchdog's stop, 130: interrupted).

Without DATA it trains on the embedded synthetic scene (generated once into a cache folder).
The run is always ``--out RUN``, also when fit continues it (``--resume``), redoes Phase 2
(``--phases 2``) or builds its language field (``--phases 3``). ``fit RUN --phases 3`` (or
``--phases 2``, ``--resume``), the spelling before, still works for one release, with a note.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from sync4d.config import ConfigError, parse_phases
from sync4d.data import DatasetError
from sync4d.data.synthetic import default_scene_dir
from sync4d.files import LOCK_FILE, RunBusy, RunLock, WriteFailed
from sync4d.phase3.encoders.encoder import EncoderError
from sync4d.phase3.store import FieldError
from sync4d.pipeline import FitInterrupted, TrainingDiverged
from sync4d.pipeline.request import FitRequest, fit_request, fresh_config, is_run
from sync4d.progress import TerminalRenderer
from sync4d.runs import CheckpointError, RunError
from sync4d.watchdog import NonFinite

__all__ = ["main"]


def _request(args: argparse.Namespace, run_dir: Path) -> FitRequest:
    """The parsed command line as the pipeline's request."""
    return FitRequest(
        run_dir=run_dir, data=Path(args.data) if args.data else None, config=args.config,
        settings=tuple(args.set or ()), iters=args.iters,
        resolution_scale=args.resolution_scale, phases=args.phases, encoder=args.encoder,
        resume=args.resume, force=args.force, threads=args.threads,
    )  # fmt: skip


def _extends_a_run(args: argparse.Namespace) -> bool:
    """Whether the command line continues or extends an existing run: --resume, or --phases
    without Phase 1 (2, 2,3 or 3)."""
    try:
        return args.resume or (args.phases is not None and 1 not in parse_phases(args.phases))
    except ConfigError:
        return False


def main(args: argparse.Namespace) -> int:
    """Run `fit` with parsed `args`; the exit status."""
    if args.resume and args.force:
        print("fit: --resume continues RUN and --force deletes it; pass one of them",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.out is None and args.data and is_run(Path(args.data)) and _extends_a_run(args):
        args.out, args.data = args.data, None  # `fit RUN --phases 3`: RUN, not a dataset
        print("fit: `fit RUN --phases ...` is now `fit --out RUN --phases ...` (the old "
              "spelling goes after this release)", file=sys.stderr)  # fmt: skip
    name = Path(args.data).name if args.data else default_scene_dir().name
    run_dir = Path(args.out) if args.out else Path("runs") / name
    created = not run_dir.exists()
    request = _request(args, run_dir)
    try:
        fresh = fresh_config(request)
        with RunLock(run_dir, "fit"), TerminalRenderer().installed():
            fit_request(request, fresh)
            return 0
    except (ConfigError, DatasetError, CheckpointError, RunError, RunBusy, WriteFailed,
            EncoderError, FieldError) as e:  # fmt: skip
        print(f"fit: {e}", file=sys.stderr)
        return 2
    except TrainingDiverged as e:
        print(f"fit: {e}", file=sys.stderr)
        return 3
    except NonFinite as e:  # outside a training loop: the refinement, Phase 3's solve
        print(f"fit: {e}. Nothing was saved from it: the run keeps its last good checkpoint "
              "(and no new language field).", file=sys.stderr)  # fmt: skip
        return 3
    except FitInterrupted:
        return 130
    finally:
        if created and run_dir.is_dir() and {p.name for p in run_dir.iterdir()} <= {LOCK_FILE}:
            (run_dir / LOCK_FILE).unlink(missing_ok=True)
            os.rmdir(run_dir)  # a command that failed before writing anything leaves nothing
