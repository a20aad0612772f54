"""Command-line interface: ``sync4d <command> ...`` (the console script) or, the same,
``python -m sync4d <command> ...``.

Commands (every option: docs/cli.md):
  fit [DATA]     Phase 1 then Phase 2 into a run folder (the embedded scene without DATA)
  process VIDEO|IMAGE_DIR  your own capture -> a dataset (frames, COLMAP poses, pinhole images)
  eval RUN       PSNR / SSIM / LPIPS of a run on its test split
  render RUN     render a run at chosen times (--time, --sweep) to PNGs and a GIF
  bench raster   time the rasterizer (forward/backward), optionally against the gsplat reference
  bench fit      Phase 1 test PSNR against training time over several budgets
  encoder export write a SigLIP-ONNX encoder directory from a Hugging Face model (internet once)
  encoder info   describe an encoder directory and check its files
  completion SHELL  print a bash or zsh completion script (shtab)

The command implementations are imported lazily, so ``--help`` stays fast and a missing optional
module only affects the command that needs it.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path

from sync4d import __version__
from sync4d.data import loaders
from sync4d.options import (
    add_bench_fit_options,
    add_bench_raster_options,
    add_threads,
    add_training_options,
    positive_float,
    positive_int,
)


def _prog() -> str:
    """The name the user typed: ``sync4d`` (console script) or ``python -m sync4d``."""
    return "python -m sync4d" if Path(sys.argv[0]).name == "__main__.py" else "sync4d"


def build_parser(prog: str = "sync4d") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog,
        description="sync4d: 4D Synchronized Fields (CPU Gaussian splatting in Rust + PyTorch).",
    )
    parser.add_argument("--version", action="version", version=f"sync4d {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    fit = commands.add_parser(
        "fit",
        help="train a deformable 4D Gaussian scene (Phase 1) and decompose its motion (Phase 2)",
        description=f"Train Phase 1, then Phase 2, on a dataset folder ({loaders.titles()}) "
        "or, without DATA, on the embedded synthetic scene. Ctrl-C saves a checkpoint; --resume "
        "continues it.",
    )
    fit.add_argument("data", nargs="?", default=None, metavar="DATA", help="dataset folder")
    fit.add_argument("--out", metavar="RUN", default=None, help="run folder (default runs/NAME)")
    add_training_options(
        fit, "hyperparameters: a TOML file or a shipped config's name (dnerf, panoptic, "
        "synthetic; default: the paper's values, synthetic for the embedded scene)",
    )  # fmt: skip
    fit.add_argument("--iters", type=positive_int, default=None, metavar="N",
                     help="bound each phase to N iterations: Phase 1 trains N, with the config's "
                     "densification, opacity-reset and SH schedules scaled to the new length; "
                     "Phase 2 trains at most N, its start and warm-up iterations and the "
                     "photometric refinement's steps per frame scaled alike. With --resume: "
                     "continue the checkpoint's phase to N iterations")  # fmt: skip
    fit.add_argument("--resolution-scale", type=positive_float, default=None, metavar="S",
                     help="downsample images by S, e.g. 0.5")  # fmt: skip
    fit.add_argument("--phases", default=None, metavar="P",
                     help="1, 2, 3 or a contiguous list such as 1,2 or 1,2,3 (default from the "
                     "config: 1,2): Phase 1 reconstruction, Phase 2 motion decomposition, Phase "
                     "3 language field; 2 alone restarts Phase 2 from RUN's Phase 1 checkpoint, "
                     "3 alone builds the field of RUN's Phase 2 checkpoint (fit RUN --phases 3 "
                     "or fit --out RUN --phases 3)")  # fmt: skip
    fit.add_argument("--encoder", default=None, metavar="DIR",
                     help="Phase 3's image-text encoder: a SigLIP-ONNX folder (python -m sync4d "
                     "encoder export) or offline (the closed-vocabulary default; "
                     "$SYNC4D_ENCODER when not given)")  # fmt: skip
    fit.add_argument("--resume", action="store_true",
                     help="continue RUN's checkpoint with the data and settings RUN recorded "
                     "(DATA and settings that contradict them are refused)")
    fit.add_argument("--force", action="store_true",
                     help="start over in an existing RUN (deletes its results)")
    fit.set_defaults(handler="sync4d.commands.fit")

    pr = commands.add_parser(
        "process",
        help="turn your own video or photos into a dataset (camera poses from COLMAP)",
        description="Extract frames from a video (PyAV) or read a folder of photos (sorted by "
        "name), recover one shared camera and every frame's pose with COLMAP (pycolmap: SIFT, "
        "matching, incremental mapping), undistort the frames to a pinhole camera and write a "
        "nerfstudio dataset (transforms.json with per-frame time, images/, sparse_pc.ply) that "
        "'fit DATA' reads. Frames COLMAP cannot register are left out and named.",
    )
    pr.add_argument("input", metavar="VIDEO|IMAGE_DIR",
                    help="a video file (mp4, mov, mkv, ...) or a folder of photos")
    pr.add_argument("--out", required=True, metavar="DATA",
                    help="dataset folder to write (new or empty)")
    pr.add_argument("--fps", type=positive_float, default=None, metavar="F",
                    help="video frames to keep per second of video time (default: every "
                    "frame, then --max-frames)")  # fmt: skip
    pr.add_argument("--max-frames", type=positive_int, default=150, metavar="N",
                    help="keep at most N frames, evenly spaced (default 150)")
    pr.add_argument("--max-size", type=positive_int, default=960, metavar="PX",
                    help="downscale frames whose longest side exceeds PX pixels (default 960)")
    pr.add_argument("--camera-model", choices=("SIMPLE_RADIAL", "OPENCV", "PINHOLE"),
                    default="SIMPLE_RADIAL",
                    help="COLMAP model of the one camera all frames share: SIMPLE_RADIAL "
                    "(default: focal + one radial term), OPENCV (two focals, k1, k2, p1, p2: "
                    "wide-angle lenses, needs large frames) or PINHOLE")  # fmt: skip
    pr.add_argument("--matcher", choices=("sequential", "exhaustive"), default="sequential",
                    help="sequential (default: each frame with its neighbours in time; "
                    "videos) or exhaustive (every pair; unordered photos, slower)")
    pr.add_argument("--threads", type=positive_int, default=None, metavar="T",
                    help="CPU threads for COLMAP (default: all cores)")
    pr.add_argument("--force", action="store_true",
                    help="replace what an earlier 'process' wrote in DATA")
    pr.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    pr.set_defaults(handler="sync4d.commands.process")

    ev = commands.add_parser(
        "eval",
        help="PSNR / SSIM / LPIPS of a run, or its temporal queries (--queries)",
        description="Evaluate a run's checkpoint on its dataset's test split "
        "(writes RUN/eval.json), or with --queries its Phase 3 field on annotated temporal "
        "queries (writes RUN/phase3/eval-NAME*.csv/json).",
    )
    ev.add_argument("run", metavar="RUN", help="run folder written by 'fit'")
    ev.add_argument("--data", default=None, metavar="DATA",
                    help="dataset folder, if it moved since training")
    ev.add_argument("--split", choices=("test", "train"), default="test")
    ev.add_argument("--queries", default=None, metavar="ANNOTATIONS",
                    help="evaluate Phase 3's temporal queries instead (Acc, vIoU, tIoU, "
                    "Appendix F): our query JSON or 4D LangSplat's annotations folder")
    ev.add_argument("--scorer", nargs="+", default=None, metavar="S",
                    choices=("full", "paper", "static", "motion", "names"),
                    help="with --queries: the scorers to report (default: all)")
    ev.add_argument("--rule", choices=("half-peak", "mean"), default=None,
                    help="with --queries: temporal activation above half the peak (Appendix "
                    "F, default) or at least the mean (4D LangSplat)")
    ev.add_argument("--encoder", default=None, metavar="DIR",
                    help="with --queries: the encoder the field was built with, if it moved")
    add_threads(ev)
    ev.set_defaults(handler="sync4d.commands.evaluate")

    rd = commands.add_parser(
        "render",
        help="render a run at chosen times",
        description="Render a run's checkpoint from one of its stored cameras at chosen times "
        "(default: a sweep over [0, 1]) to PNGs and a GIF.",
    )
    rd.add_argument("run", metavar="RUN", help="run folder (or a checkpoint file)")
    rd.add_argument("--time", nargs="+", type=float, default=None, metavar="T", dest="times",
                    help="times in [0, 1], one PNG each (default: a --sweep)")
    rd.add_argument("--sweep", type=positive_int, default=48, metavar="N", dest="frames",
                    help="frames of the default time sweep, evenly spaced over [0, 1] "
                    "(default 48)")
    # The spellings before sync4d-render's words: --times, --frames.
    rd.add_argument("--times", nargs="+", type=float, dest="times", help=argparse.SUPPRESS)
    rd.add_argument("--frames", type=positive_int, dest="frames", help=argparse.SUPPRESS)
    rd.add_argument("--camera", default=None, metavar="CAM",
                    help="test:K / train:K (K-th frame of that split), K (a test frame) or a "
                    "frame name such as cam10_000000.jpg; default test:0")
    rd.add_argument("--out", default=None, metavar="DIR",
                    help="output folder (default RUN/renders)")
    rd.add_argument("--fps", type=positive_float, default=15.0, help="GIF frame rate")
    rd.add_argument("--no-gif", action="store_true", help="write PNGs only")
    add_threads(rd)
    rd.set_defaults(handler="sync4d.commands.render")

    qy = commands.add_parser(
        "query",
        help="ask a run's language field which object matches a text, and when",
        description="Rank a run's objects for each text query and give the frames where each "
        "is active, from the Phase 3 field (fit --phases 3). Writes a timeline PNG per query.",
    )
    qy.add_argument("run", metavar="RUN",
                    help="run folder with a Phase 3 field (fit --phases 3)")
    qy.add_argument("texts", nargs="+", metavar="TEXT", help="one or more queries")
    qy.add_argument("--scorer", choices=("full", "paper", "static", "names", "motion"),
                    default="full",
                    help="full (default: motion phrases + the paper's score + object names), "
                    "paper (Eq. 15 only), static (the static-only ablation), names, motion")
    qy.add_argument("--rule", choices=("half-peak", "mean"), default=None,
                    help="temporal activation: above half the peak (Appendix F, default) or at "
                    "least the mean (4D LangSplat)")  # fmt: skip
    qy.add_argument("--encoder", default=None, metavar="DIR",
                    help="the encoder the field was built with, if it moved (a SigLIP-ONNX "
                    "folder, or offline)")  # fmt: skip
    qy.add_argument("--json", action="store_true", help="print the answers as JSON")
    qy.add_argument("--plot", default=None, metavar="DIR",
                    help="folder for the timeline PNGs (default RUN/phase3)")
    qy.add_argument("--no-plot", action="store_true", help="write no timeline PNG")
    qy.set_defaults(handler="sync4d.commands.query")

    bench = commands.add_parser("bench", help="run a benchmark")
    targets = bench.add_subparsers(dest="target", metavar="TARGET")
    targets.required = True

    raster = targets.add_parser(
        "raster",
        help="rasterizer forward/backward timings",
        description="Time sync4d.raster (forward and backward) on seeded random scenes.",
    )
    add_bench_raster_options(raster)
    raster.set_defaults(handler="sync4d.bench.raster")

    bfit = targets.add_parser(
        "fit",
        help="Phase 1 test PSNR against training time (Pareto curve)",
        description="Train one scene at several budgets (iterations x resolution scale x "
        "Gaussian cap) and write a JSON and a PNG plot of test PSNR against training time.",
    )
    add_bench_fit_options(bfit)
    bfit.set_defaults(handler="sync4d.bench.fit")

    bp3 = targets.add_parser(
        "phase3",
        help="Phase 3 build time and query latency on Phase 2 runs",
        description="Build each run's language field in a temporary folder (the run is not "
        "touched) and time its steps and text queries, cold and cached; writes a JSON.",
    )
    bp3.add_argument("runs", nargs="+", metavar="RUN", help="Phase 2 run folders")
    bp3.add_argument("--encoder", default=None, metavar="DIR",
                     help="SigLIP-ONNX folder or offline (default: $SYNC4D_ENCODER, else "
                     "offline)")  # fmt: skip
    bp3.add_argument("--queries", nargs="+", default=None, metavar="TEXT",
                     help="the queries to time (default: five identity, state and motion "
                     "queries)")  # fmt: skip
    bp3.add_argument("--repeat", type=positive_int, default=3, metavar="N",
                     help="timings per query (the median is reported; default 3)")
    bp3.add_argument("--out", default=None, metavar="FILE.json",
                     help="results JSON (default bench-phase3.json)")
    add_threads(bp3)
    bp3.set_defaults(handler="sync4d.bench.phase3")

    enc = commands.add_parser("encoder", help="export or inspect a SigLIP-ONNX encoder (Phase 3)")
    actions = enc.add_subparsers(dest="action", metavar="ACTION")
    actions.required = True
    exp = actions.add_parser(
        "export",
        help="write a SigLIP-ONNX encoder directory from a Hugging Face model",
        description="Download a SigLIP model (needs internet once and the export extra: "
        "pip install 'sync4d[export]') and write DIR: vision.onnx, text.onnx, tokenizer.json "
        "and the manifest encoder.json. Phase 3 then runs it with onnxruntime, offline "
        "(--encoder DIR or $SYNC4D_ENCODER).",
    )
    exp.add_argument("--model", default="google/siglip-base-patch16-224", metavar="NAME",
                     help="Hugging Face model id or a local save_pretrained folder "
                     "(default google/siglip-base-patch16-224)")  # fmt: skip
    exp.add_argument("--out", required=True, metavar="DIR", help="encoder directory to write")
    exp.add_argument("--force", action="store_true",
                     help="replace the encoder already in DIR")  # fmt: skip
    exp.set_defaults(handler="sync4d.commands.encoder")
    info = actions.add_parser(
        "info",
        help="describe an encoder directory and check its files",
        description="Print an encoder directory's kind, embedding size, preprocessing and "
        "files, after checking every file's sha256 and loading both graphs.",
    )
    info.add_argument("dir", metavar="DIR", help="encoder directory written by 'encoder export'")
    info.set_defaults(handler="sync4d.commands.encoder")

    comp = commands.add_parser(
        "completion",
        help="print a shell completion script (bash or zsh)",
        description="Print a completion script for the sync4d command. bash: "
        "sync4d completion bash > ~/.local/share/bash-completion/completions/sync4d; "
        "zsh: sync4d completion zsh > ~/.zfunc/_sync4d (with ~/.zfunc on $fpath).",
    )
    comp.add_argument("shell", choices=("bash", "zsh"), help="the shell to complete for")
    comp.set_defaults(handler=None)
    _complete_paths(parser)
    return parser


def _complete_paths(parser: argparse.ArgumentParser) -> None:
    """Mark path arguments (metavars DATA, RUN, DIR, FILE...) for shtab's completion: folders
    complete as folders, files as files. Without shtab the parser is unchanged."""
    try:
        import shtab
    except ImportError:
        return
    folders = {"DATA", "RUN", "DIR", "RUNS"}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _complete_paths(sub)
        elif action.metavar in folders:
            action.complete = shtab.DIRECTORY  # type: ignore[attr-defined]
        elif isinstance(action.metavar, str) and (
            action.metavar.startswith("FILE")
            or action.metavar in ("ANNOTATIONS", "CONFIG", "VIDEO|IMAGE_DIR")
        ):
            action.complete = shtab.FILE  # type: ignore[attr-defined]


def _print_completion(parser: argparse.ArgumentParser, shell: str) -> int:
    try:
        import shtab
    except ImportError:
        print("sync4d completion: needs the shtab package: python -m pip install shtab",
              file=sys.stderr)  # fmt: skip
        return 2
    print(shtab.complete(parser, shell=shell, root_prefix="sync4d"))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser(_prog())
    args = parser.parse_args(argv)
    if args.command == "completion":
        parser.prog = "sync4d"
        return _print_completion(parser, args.shell)
    module_name: str = args.handler
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and module_name.startswith(exc.name):
            print(
                f"python -m sync4d: '{args.command}' is not available: "
                f"module {module_name} is missing from this install",
                file=sys.stderr,
            )
            return 2
        raise
    if not hasattr(args, "backend"):  # e.g. query: no rendering, no torch import
        return int(module.main(args) or 0)
    from sync4d import raster

    backend = getattr(args, "backend", None)
    previous = raster.resolve_backend()
    if backend not in (None, "cpu"):
        try:
            args.backend = raster.set_default_backend(backend)
        except RuntimeError as e:
            print(f"python -m sync4d {args.command}: {e}", file=sys.stderr)
            return 2
        if backend == "wgpu":
            print(f"sync4d: backend wgpu on {_core_adapter()}", file=sys.stderr)
    try:
        result = module.main(args)
    finally:
        raster.set_default_backend(previous)  # main() may be called again in-process
    return int(result or 0)


def _core_adapter() -> str:
    from sync4d import _core

    return _core.wgpu_adapter()


if __name__ == "__main__":
    sys.exit(main())
