"""``python -m sync4d eval RUN``: PSNR, SSIM and LPIPS-Alex of a run's checkpoint on the test
split, per frame and mean, written to ``RUN/eval.json`` and printed as a table. Another split
(``--split train``) or another dataset (``--data`` whose frames differ from the run's) writes
``RUN/eval-<split>.json`` or ``RUN/eval-<dataset>-<split>.json`` instead. Images with alpha
(D-NeRF's) are scored on the run's background and on white and black (the peers score D-NeRF
on black), the others with the colour in the tag: ``RUN/eval-black.json``; ``--background
COLOUR`` scores on that one colour only."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.files import RunLock
from sync4d.options import add_backend, add_rule, add_threads, background_colour

__all__ = ["add_arguments", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d eval`` (`sync4d.cli`)."""
    from sync4d.phase3.query import SCORERS

    p.description = (
        "Evaluate a run's checkpoint on its dataset's test split (writes RUN/eval.json), or "
        "with --queries its Phase 3 field on annotated temporal queries (writes "
        "RUN/phase3/eval-NAME*.csv/json)."
    )
    p.add_argument("run", metavar="RUN", help="run folder written by 'fit'")
    p.add_argument("--data", default=None, metavar="DATA",
                   help="dataset folder, if it moved since training")
    p.add_argument("--split", choices=("test", "train"), default="test")
    p.add_argument("--background", type=background_colour, default=None, metavar="COLOUR",
                   help="composite render and ground truth on this colour only: white, "
                   "black or R,G,B in [0, 1]; another than the run's own writes "
                   "RUN/eval-<colour>.json (default: the run's own, and for images with alpha "
                   "white and black too, as Deformable-3DGS and SC-GS score D-NeRF on black)")
    p.add_argument("--queries", default=None, metavar="ANNOTATIONS",
                   help="evaluate Phase 3's temporal queries instead (Acc, vIoU, tIoU, "
                   "Appendix F): our query JSON or 4D LangSplat's annotations folder; a relational "
                   "question file (\"kind\": \"relational\") reports Acc, tIoU and counts per "
                   "question form")
    p.add_argument("--scorer", nargs="+", default=None, metavar="S", choices=SCORERS,
                   help=f"with --queries: the scorers to report, of {', '.join(SCORERS)} "
                   "(default: all, in that order)")
    add_rule(p, "with --queries: ")
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help="with --queries: the encoder the field was built with, if it moved")
    add_threads(p)
    add_backend(p)


def _queries(args: argparse.Namespace) -> int:
    """`eval RUN --queries ANNOTATIONS`: Acc / vIoU / tIoU per scorer, printed as a table."""
    import torch

    from sync4d.phase3.evaluation.query_eval import evaluate_queries
    from sync4d.phase3.evaluation.relational_eval import is_relational
    from sync4d.phase3.query import SCORERS
    from sync4d.report import align_table

    if is_relational(args.queries):
        return _relational(args)
    try:
        with RunLock(args.run, "eval"):
            if args.threads:
                torch.set_num_threads(args.threads)
            summary = evaluate_queries(
                args.run, args.queries, scorers=tuple(args.scorer or SCORERS),
                rule=args.rule, data=args.data, threads=args.threads,
                encoder=args.encoder,
            )  # fmt: skip
    except Sync4dError as e:
        print(f"eval: {e}", file=sys.stderr)
        return e.exit_code

    def cell(v: object) -> str:
        return "-" if v is None else f"{v:.3f}"

    rows = [[s, cell(m.get("acc")), cell(m.get("viou")), cell(m.get("tiou")),
             cell(m.get("object_accuracy"))] for s, m in summary.items()]  # fmt: skip
    print(align_table(["scorer", "Acc", "vIoU", "tIoU", "object"], rows))
    print(f"rows: {Path(args.run) / 'phase3'}/eval-*.csv")
    return 0


def _relational(args: argparse.Namespace) -> int:
    """`eval RUN --queries QUESTIONS.json` with a relational question file: Acc (right
    object), tIoU, count accuracy and plan accuracy (the question's form read, and its count
    right) per question form, printed as a table."""
    from sync4d.phase3.evaluation.relational_eval import evaluate_relational
    from sync4d.report import align_table

    try:
        with RunLock(args.run, "eval"):
            summary = evaluate_relational(args.run, args.queries, encoder=args.encoder)
    except Sync4dError as e:
        print(f"eval: {e}", file=sys.stderr)
        return e.exit_code

    def cell(v: object) -> str:
        return "-" if v is None else f"{v:.3f}"

    rows = [[form, str(m["n"]), cell(m["acc"]), cell(m["tiou"]), cell(m["count_acc"]),
             cell(m["plan_acc"])]
            for form, m in [*summary["forms"].items(), ("all", summary["all"])]]  # fmt: skip
    print(align_table(["form", "questions", "Acc (object)", "tIoU", "count", "plan"], rows))
    print(f"rows: {summary['rows_file']}")
    return 0


def main(args: argparse.Namespace) -> int:
    """Run `eval` with parsed `args`; the exit status."""
    if getattr(args, "queries", None):
        return _queries(args)
    import torch

    from sync4d.pipeline.evaluate import evaluate_run, with_backgrounds
    from sync4d.pipeline.record import dataset_differences
    from sync4d.runs import RunError, load_run
    from sync4d.runs.names import background_tag
    from sync4d.terminal import TerminalRenderer

    run_dir = Path(args.run)
    try:
        run = load_run(run_dir)
        with RunLock(run.path, "eval"):
            scene = run.scene(args.data)
            if scene is None:
                raise RunError(
                    f"{run_dir}: the run's dataset ({run.settings.get('data')}) is not "
                    "there any more; pass --data PATH"
                )
            other = bool(dataset_differences(run.settings.get("dataset", {}), scene))
            tag = f"{scene.name}-{args.split}" if other else None
            if tag is None and args.split != "test":
                tag = args.split
            chosen = getattr(args, "background", None)
            threads = args.threads or None
            if threads:
                torch.set_num_threads(threads)
            with TerminalRenderer().installed():
                if chosen is None:  # the run's background, and for RGBA images white and black
                    with_backgrounds(run.path, run.model, scene, run.background, threads,
                                     args.split, tag=tag)  # fmt: skip
                else:
                    if list(chosen) != list(run.background):
                        tag = "-".join(t for t in (tag, background_tag(chosen)) if t)
                    evaluate_run(run.path, run.model, scene, list(chosen), threads, args.split,
                                 tag=tag)  # fmt: skip
    except Sync4dError as e:  # exit 2; 3: the watchdog's stop on a render (NonFinite)
        print(f"eval: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("eval: interrupted; nothing written", file=sys.stderr)
        return 130
    return 0
