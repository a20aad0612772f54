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
        "--out", metavar="FILE.json", default=None, help="also write the results as JSON here"
    )
    raster.add_argument(
        "--sizes",
        nargs="+",
        type=_positive_int,
        metavar="N",
        default=None,
        help="scene sizes as Gaussian counts, e.g. --sizes 1000 10000 (default: the bench's set)",
    )
    raster.add_argument(
        "--threads",
        nargs="+",
        type=_positive_int,
        metavar="T",
        default=None,
        help="rayon thread counts to time, e.g. --threads 1 2 (default: 1 and all cores)",
    )
    raster.add_argument(
        "--no-reference",
        action="store_true",
        help="skip the gsplat torch reference timings",
    )
    raster.add_argument(
        "--quick", action="store_true", help="small sizes and few repeats (smoke run)"
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
