"""Command-line interface: ``python -m sync4d <command> ...``.

Commands:
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m sync4d",
        description="sync4d: 4D Synchronized Fields (CPU Gaussian splatting in Rust + PyTorch).",
    )
    parser.add_argument("--version", action="version", version=f"sync4d {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    commands.required = True

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
        "--quick",
        action="store_true",
        help="N=10000 at 256x256 only, fewer repeats (smoke run); --sizes/--resolutions win",
    )
    raster.set_defaults(handler="sync4d.bench.raster")
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
                f"python -m sync4d: '{args.command} {args.target}' is not available: "
                f"module {module_name} is missing from this install",
                file=sys.stderr,
            )
            return 2
        raise
    result = module.main(args)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
