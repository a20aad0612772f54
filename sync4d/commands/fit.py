"""``python -m sync4d fit [DATA] --out runs/NAME``: Phase 1 then Phase 2 training (``phases``)
into a run folder, then the test metrics and Phase 2's diagnostics. The command parses its
arguments into a `sync4d.pipeline.request.FitRequest`, whose `fit_request` owns what a run
folder may continue (the resume policy) and does it; what the pipeline reports
(`sync4d.events`) is printed by `sync4d.terminal.TerminalRenderer`; the exit status says how
it ended (2: a bad input, 3: the watchdog's stop, 130: interrupted).

Without DATA it trains on the embedded synthetic scene (generated once into a cache folder).
The run is always ``--out RUN``, also when fit continues it (``--resume``), redoes Phase 2
(``--phases 2``) or builds its language field (``--phases 3``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from sync4d.data import loaders
from sync4d.data.synthetic import default_scene_dir
from sync4d.errors import Sync4dError
from sync4d.files import LOCK_FILE, RunLock
from sync4d.options import add_encoder, add_training_options, positive_float, positive_int
from sync4d.terminal import TerminalRenderer

if TYPE_CHECKING:  # the pipeline loads torch: imported when fit runs, not for its --help
    from sync4d.pipeline.request import FitRequest

__all__ = ["add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d fit`` (`sync4d.cli`)."""
    p.description = (
        f"Train Phase 1, then Phase 2, on a dataset folder ({loaders.titles()}) or, without "
        "DATA, on the embedded synthetic scene, into the run folder RUN; --phases 3 adds the "
        "language field. Ctrl-C saves a checkpoint; fit --out RUN --resume continues it."
    )
    p.add_argument("data", nargs="?", default=None, metavar="DATA",
                   help="dataset folder (optional when RUN exists: the run records it)")
    p.add_argument("--out", metavar="RUN", default=None,
                   help="the run folder to write, new or existing (default runs/NAME)")
    add_training_options(
        p, "hyperparameters: a TOML file or a shipped config's name (dnerf, panoptic, "
        "synthetic; default: the paper's values, synthetic for the embedded scene)",
    )  # fmt: skip
    p.add_argument("--iters", type=positive_int, default=None, metavar="N",
                   help="bound each phase to N iterations: Phase 1 trains N, with the config's "
                   "densification, opacity-reset and SH schedules scaled to the new length; "
                   "Phase 2 trains at most N, its start and warm-up iterations and the "
                   "photometric refinement's steps per frame scaled alike. With --resume: "
                   "continue the checkpoint's phase to N iterations")  # fmt: skip
    p.add_argument("--resolution-scale", type=positive_float, default=None, metavar="S",
                   help="downsample images by S, e.g. 0.5")  # fmt: skip
    p.add_argument("--phases", default=None, metavar="P",
                   help="1, 2, 3 or a contiguous list such as 1,2 or 1,2,3 (default from the "
                   "config: 1,2): Phase 1 reconstruction, Phase 2 motion decomposition, Phase "
                   "3 language field; 2 alone restarts Phase 2 from RUN's Phase 1 checkpoint, "
                   "3 alone builds the field of RUN's Phase 2 checkpoint "
                   "(fit --out RUN --phases 3)")  # fmt: skip
    add_encoder(p, "Phase 3's image-text encoder: ", default=True)
    p.add_argument("--resume", action="store_true",
                   help="continue RUN's checkpoint with the data and settings RUN recorded "
                   "(DATA and settings that contradict them are refused)")
    p.add_argument("--force", action="store_true",
                   help="start over in an existing RUN (deletes its results)")


def _request(args: argparse.Namespace, run_dir: Path) -> FitRequest:
    """The parsed command line as the pipeline's request."""
    from sync4d.pipeline.request import FitRequest

    return FitRequest(
        run_dir=run_dir, data=Path(args.data) if args.data else None, config=args.config,
        settings=tuple(args.set or ()), iters=args.iters,
        resolution_scale=args.resolution_scale, phases=args.phases, encoder=args.encoder,
        resume=args.resume, force=args.force, threads=args.threads,
    )  # fmt: skip


def main(args: argparse.Namespace) -> int:
    """Run `fit` with parsed `args`; the exit status."""
    from sync4d.pipeline import FitInterrupted
    from sync4d.pipeline.request import fit_request, is_run
    from sync4d.watchdog import NonFinite

    if args.resume and args.force:
        print("fit: --resume continues RUN and --force deletes it; pass one of them",
              file=sys.stderr)  # fmt: skip
        return 2
    if args.data and is_run(Path(args.data)):
        print(f"fit: {args.data} is a run folder, not a dataset: a run is named --out RUN "
              "(fit --out RUN --resume | --phases 2 | --phases 3)", file=sys.stderr)  # fmt: skip
        return 2
    name = Path(args.data).name if args.data else default_scene_dir().name
    run_dir = Path(args.out) if args.out else Path("runs") / name
    created = not run_dir.exists()
    request = _request(args, run_dir)
    try:
        with RunLock(run_dir, "fit"), TerminalRenderer().installed():
            fit_request(request)  # reads the config the request needs, once
            return 0
    except NonFinite as e:  # outside a training loop: the refinement, Phase 3's solve
        print(f"fit: {e}. Nothing was saved from it: the run keeps its last good checkpoint "
              "(and no new language field).", file=sys.stderr)  # fmt: skip
        return e.exit_code
    except Sync4dError as e:  # exit 2; 3: TrainingDiverged (the watchdog's stop in a loop)
        print(f"fit: {e}", file=sys.stderr)
        return e.exit_code
    except FitInterrupted:
        return 130
    finally:
        if created and run_dir.is_dir() and {p.name for p in run_dir.iterdir()} <= {LOCK_FILE}:
            (run_dir / LOCK_FILE).unlink(missing_ok=True)
            os.rmdir(run_dir)  # a command that failed before writing anything leaves nothing
