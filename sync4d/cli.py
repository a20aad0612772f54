"""Command-line interface: ``python -m sync4d <command> ...``.

Commands:
  fit [DATA]     Phase 1 training (the embedded synthetic scene when DATA is omitted)
  eval RUN       PSNR / SSIM / LPIPS of a run on its test split
  render RUN     render a run's checkpoint at chosen times to PNGs and a GIF
  bench raster   time the rasterizer (forward/backward), optionally against the gsplat reference

The command implementations are imported lazily, so ``--help`` stays fast and a missing optional
module only affects the command that needs it.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from sync4d import __version__


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {value}")
    return value


def _resolution(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (e.g. ``800x800``, ``960x536``) as ``(width, height)``."""
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 800x800, got {text!r}"
        ) from None
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise argparse.ArgumentTypeError(f"width and height must lie in 1..16384, got {text!r}")
    return width, height


def _add_threads(p: argparse.ArgumentParser) -> None:
    """--threads and --backend: every command that renders or trains."""
    p.add_argument(
        "--threads",
        type=_positive_int,
        default=None,
        metavar="T",
        help="CPU threads for torch and the rasterizer (default: all cores)",
    )
    p.add_argument(
        "--backend",
        choices=("cpu", "wgpu", "auto"),
        default="cpu",
        help="compositing backend: the Rust CPU path (default), wgpu (a GPU, else a CPU "
        "Vulkan driver such as lavapipe) or auto (wgpu on a GPU, else cpu)",
    )


def _add_training_options(p: argparse.ArgumentParser, config_help: str) -> None:
    """Options shared by every command that trains: config file, overrides, threads."""
    p.add_argument("--config", metavar="FILE.toml", default=None, help=config_help)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                   help="override a config value, e.g. --set phase1.densify.stop=10000 "
                   "(repeatable)")  # fmt: skip
    _add_threads(p)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sync4d",
        description="sync4d: 4D Synchronized Fields (CPU Gaussian splatting in Rust + PyTorch).",
    )
    parser.add_argument("--version", action="version", version=f"sync4d {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

    fit = commands.add_parser(
        "fit",
        help="train a deformable 4D Gaussian scene (Phase 1) and decompose its motion (Phase 2)",
        description="Train Phase 1, then Phase 2, on a dataset folder (D-NeRF/Blender, "
        "nerfstudio, HyperNeRF, COLMAP, Dynamic-3DGS Panoptic) or, without DATA, on the "
        "embedded synthetic scene. Ctrl-C saves a checkpoint; --resume continues it.",
    )
    fit.add_argument("data", nargs="?", default=None, metavar="DATA", help="dataset folder")
    fit.add_argument("--out", metavar="RUN", default=None, help="run folder (default runs/NAME)")
    _add_training_options(
        fit, "hyperparameters (default: the paper's values; configs/synthetic.toml for the "
        "embedded scene)",
    )  # fmt: skip
    fit.add_argument("--iters", type=_positive_int, default=None, metavar="N",
                     help="training iterations; the config's densification, opacity-reset and "
                     "SH schedules are scaled to the new length")
    fit.add_argument("--resolution-scale", type=_positive_float, default=None, metavar="S",
                     help="downsample images by S, e.g. 0.5")  # fmt: skip
    fit.add_argument("--phases", default=None, metavar="P",
                     help="1, 2 or 1,2 (default from the config: 1,2): Phase 1 reconstruction, "
                     "Phase 2 motion decomposition; 2 alone restarts Phase 2 from RUN's Phase 1 "
                     "checkpoint")  # fmt: skip
    fit.add_argument("--resume", action="store_true", help="continue RUN's checkpoint")
    fit.add_argument("--force", action="store_true", help="start over in an existing RUN")
    fit.set_defaults(handler="sync4d.commands.fit")

    ev = commands.add_parser(
        "eval",
        help="PSNR / SSIM / LPIPS of a run",
        description="Evaluate a run's checkpoint on its dataset's test split "
        "(writes RUN/eval.json).",
    )
    ev.add_argument("run", metavar="RUN", help="run folder written by 'fit'")
    ev.add_argument("--data", default=None, metavar="DATA",
                    help="dataset folder, if it moved since training")
    ev.add_argument("--split", choices=("test", "train"), default="test")
    _add_threads(ev)
    ev.set_defaults(handler="sync4d.commands.evaluate")

    rd = commands.add_parser(
        "render",
        help="render a run at chosen times",
        description="Render a run's checkpoint from one of its stored cameras at chosen times "
        "(default: a sweep over [0, 1]) to PNGs and a GIF.",
    )
    rd.add_argument("run", metavar="RUN", help="run folder (or a checkpoint file)")
    rd.add_argument("--times", nargs="+", type=float, default=None, metavar="T",
                    help="times in [0, 1] (default: --frames evenly spaced)")
    rd.add_argument("--frames", type=_positive_int, default=48, metavar="N",
                    help="frames in the default time sweep (default 48)")
    rd.add_argument("--camera", default=None, metavar="CAM",
                    help="test:K / train:K (K-th frame of that split), K (a test frame) or a "
                    "frame name such as cam10_000000.jpg; default test:0")
    rd.add_argument("--out", default=None, metavar="DIR",
                    help="output folder (default RUN/renders)")
    rd.add_argument("--fps", type=_positive_float, default=15.0, help="GIF frame rate")
    rd.add_argument("--no-gif", action="store_true", help="write PNGs only")
    _add_threads(rd)
    rd.set_defaults(handler="sync4d.commands.render")

    bench = commands.add_parser("bench", help="run a benchmark")
    targets = bench.add_subparsers(dest="target", metavar="TARGET")
    targets.required = True

    raster = targets.add_parser(
        "raster",
        help="rasterizer forward/backward timings",
        description="Time sync4d.raster (forward and backward) on seeded random scenes.",
    )
    raster.add_argument(
        "--out",
        metavar="FILE.json",
        default=None,
        help="where to write the results as JSON (default: bench-raster.json in the cwd)",
    )
    raster.add_argument(
        "--sizes",
        nargs="+",
        type=_positive_int,
        metavar="N",
        default=None,
        help="scene sizes as Gaussian counts, e.g. --sizes 1000 10000 "
        "(default: 10000 100000 1000000)",
    )
    raster.add_argument(
        "--resolutions",
        nargs="+",
        type=_resolution,
        metavar="WxH",
        default=None,
        help="image sizes, e.g. --resolutions 800x800 960x536 (default: 256x256 800x800 960x536)",
    )
    raster.add_argument(
        "--threads",
        nargs="+",
        type=_positive_int,
        metavar="T",
        default=None,
        help="thread counts to time (rayon on the op, torch.set_num_threads for torch), "
        "e.g. --threads 1 2 (default: 1 2)",
    )
    raster.add_argument(
        "--repeats",
        type=_positive_int,
        metavar="K",
        default=None,
        help="timed sync4d calls per measurement, median reported "
        "(default: 5, 3 for N >= 1M, 3 with --quick)",
    )
    raster.add_argument(
        "--reference-max-gb",
        type=_positive_float,
        metavar="GB",
        default=None,
        help="kill a reference run whose RSS passes this many GiB (default: 18, and never more "
        "than the memory available minus 1.5 GiB)",
    )
    raster.add_argument(
        "--memory-method",
        choices=("auto", "clear_refs", "subprocess"),
        default="auto",
        help="peak-memory method: reset VmHWM via /proc/self/clear_refs, or run each "
        "measurement in a child process and read its ru_maxrss (default: auto)",
    )
    raster.add_argument(
        "--no-reference",
        action="store_true",
        help="skip the gsplat torch reference timings",
    )
    raster.add_argument(
        "--no-wgpu",
        action="store_true",
        help="skip the wgpu backend timings (default: timed when a wgpu adapter opens, "
        "e.g. lavapipe)",
    )
    raster.add_argument(
        "--quick",
        action="store_true",
        help="N=10000 at 256x256 only, fewer repeats (smoke run); --sizes/--resolutions win",
    )
    raster.set_defaults(handler="sync4d.bench.raster")

    bfit = targets.add_parser(
        "fit",
        help="Phase 1 test PSNR against training time (Pareto curve)",
        description="Train one scene at several budgets (iterations x resolution scale x "
        "Gaussian cap) and write a JSON and a PNG plot of test PSNR against training time.",
    )
    bfit.add_argument("data", nargs="?", default=None, metavar="DATA",
                      help="dataset folder (default: the embedded synthetic scene)")
    _add_training_options(bfit, "hyperparameters of every budget (default as for 'fit')")
    bfit.add_argument("--iters", nargs="+", type=_positive_int, metavar="N", default=None,
                      help="iteration budgets (default: 1/8, 1/4, 1/2 and all of the config's)")
    bfit.add_argument("--scales", nargs="+", type=_positive_float, metavar="S", default=None,
                      help="resolution scales (default: the config's)")
    bfit.add_argument("--caps", nargs="+", type=_positive_int, metavar="N", default=None,
                      help="Gaussian caps (default: the config's max_gaussians)")
    bfit.add_argument("--out", metavar="FILE.json", default=None,
                      help="results JSON (default bench-fit-NAME.json; the plot goes beside it)")
    bfit.add_argument("--keep-runs", metavar="DIR", default=None,
                      help="keep each budget's run folder under DIR")
    bfit.set_defaults(handler="sync4d.bench.fit")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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
