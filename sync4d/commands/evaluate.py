"""``python -m sync4d eval RUN``: PSNR, SSIM and LPIPS-Alex of a run's checkpoint on the test
split, per frame and mean, written to ``RUN/eval.json`` and printed as a table."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from sync4d.data import DatasetError
from sync4d.runs import CheckpointError, RunError, evaluate_run, load_run

__all__ = ["main"]


def main(args: argparse.Namespace) -> int:
    """Run `eval` with parsed `args`; the exit status."""
    run_dir = Path(args.run)
    try:
        run = load_run(run_dir)
        scene = run.scene(args.data)
        if scene is None:
            raise RunError(
                f"{run_dir}: the run's dataset ({run.settings.get('data')}) is not "
                "there any more; pass --data PATH"
            )
        threads = args.threads or None
        if threads:
            torch.set_num_threads(threads)
        evaluate_run(run.path, run.model, scene, run.background, threads, args.split)
    except (RunError, CheckpointError, DatasetError) as e:
        print(f"eval: {e}", file=sys.stderr)
        return 2
    return 0
