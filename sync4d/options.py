"""Argument types and option groups of the command line, kept light (argparse only) so that
`cli` and the benchmarks' programmatic entry points build the same options without importing
each other."""

from __future__ import annotations

import argparse
import math
import sys

__all__ = [
    "add_bench_fit_options",
    "add_bench_raster_options",
    "add_threads",
    "add_training_options",
    "background_colour",
    "frame_count",
    "port_number",
    "positive_float",
    "positive_int",
    "thread_count",
    "renamed",
    "resolution",
]


class _Renamed(argparse.Action):
    """An option's spelling before a rename (see `renamed`)."""

    def __init__(self, option_strings: list[str], dest: str, now: str = "", **kw) -> None:
        super().__init__(option_strings, dest, **kw)
        self.now = now

    def __call__(self, parser, namespace, values, option_string=None) -> None:  # noqa: ANN001
        print(f"sync4d: `{option_string}` is now `{self.now}` (the old spelling goes after this "
              "release)", file=sys.stderr)  # fmt: skip
        setattr(namespace, self.dest, values)


def renamed(p: argparse.ArgumentParser, old: str, now: str, dest: str, **kw) -> None:
    """Keep option `old` working for one release as a hidden spelling of `now` (an option, or
    a positional argument): it stores into `dest` and notes the new spelling on stderr."""
    p.add_argument(old, action=_Renamed, now=now, dest=dest, help=argparse.SUPPRESS, **kw)


#: The largest count `positive_int` takes: a C int, what torch, numpy and Rust take as a size.
MAX_INT = 2**31 - 1
#: The most CPU threads `thread_count` takes.
MAX_THREADS = 1024
#: The most frames `frame_count` takes (a render sweep, an exported sequence).
MAX_FRAMES = 100_000


def _integer(text: str, low: int, high: int, what: str) -> int:
    """`text` as an integer in [low, high], or an argparse error saying which are taken."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text[:80]!r}") from None
    if not low <= value <= high:
        digits = str(value)
        shown = digits if len(digits) <= 20 else f"{digits[:12]}... ({len(digits)} digits)"
        raise argparse.ArgumentTypeError(f"expected {what} from {low} to {high}, got {shown}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1 (and at most `MAX_INT`) (argparse type)."""
    return _integer(text, 1, MAX_INT, "a positive integer")


def thread_count(text: str) -> int:
    """A CPU thread count: an integer in 1..`MAX_THREADS` (argparse type)."""
    return _integer(text, 1, MAX_THREADS, "a thread count")


def port_number(text: str) -> int:
    """A TCP port: an integer in 1..65535 (argparse type)."""
    return _integer(text, 1, 65535, "a port number")


def frame_count(text: str) -> int:
    """A number of frames: an integer in 1..`MAX_FRAMES` (argparse type)."""
    return _integer(text, 1, MAX_FRAMES, "a frame count")


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text[:80]!r}"
                                         ) from None  # fmt: skip
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a finite positive number, got {value}")
    return value


#: Background colours `background_colour` knows by name.
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def background_colour(text: str) -> tuple[float, float, float]:
    """``white``, ``black`` or ``R,G,B`` with each channel in [0, 1] (argparse type)."""
    if text.lower() in BACKGROUNDS:
        return BACKGROUNDS[text.lower()]
    try:
        rgb = tuple(float(v) for v in text.split(","))
    except ValueError:
        rgb = ()
    if len(rgb) != 3 or not all(0.0 <= v <= 1.0 for v in rgb):
        raise argparse.ArgumentTypeError(
            f"expected white, black or R,G,B with channels in [0, 1], got {text[:80]!r}"
        )
    return rgb  # type: ignore[return-value]


def resolution(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` (e.g. ``800x800``, ``960x536``) as ``(width, height)``."""
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected WIDTHxHEIGHT such as 800x800, got {text[:80]!r}"
        ) from None
    if not (1 <= width <= 16384 and 1 <= height <= 16384):
        raise argparse.ArgumentTypeError(f"width and height must lie in 1..16384, got "
                                         f"{text[:80]!r}")
    return width, height


def add_threads(p: argparse.ArgumentParser) -> None:
    """--threads and --backend: every command that renders or trains."""
    p.add_argument(
        "--threads",
        type=thread_count,
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


def add_training_options(p: argparse.ArgumentParser, config_help: str) -> None:
    """Options shared by every command that trains: config file, overrides, threads."""
    p.add_argument("--config", metavar="FILE.toml", default=None, help=config_help)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                   help="override a config value, e.g. --set phase1.densify.stop=10000 "
                   "(repeatable)")  # fmt: skip
    add_threads(p)


def add_bench_raster_options(p: argparse.ArgumentParser) -> None:
    """The options of `bench raster`."""
    renamed(p, "--run", "bench raster RUN", "run", default=None)  # sets run=None by default
    p.add_argument(
        "run",
        nargs="?",
        default=argparse.SUPPRESS,  # absent: keeps --run's value
        metavar="RUN",
        help="time the rasterizer on this trained run's own Gaussians at its test cameras "
        "instead of the random scenes (one thread count: the first of --thread-counts)",
    )
    p.add_argument(
        "--out",
        metavar="FILE.json",
        default=None,
        help="where to write the results as JSON (default: bench-raster.json in the cwd)",
    )
    p.add_argument(
        "--sizes",
        nargs="+",
        type=positive_int,
        metavar="N",
        default=None,
        help="scene sizes as Gaussian counts, e.g. --sizes 1000 10000 "
        "(default: 10000 100000 1000000)",
    )
    p.add_argument(
        "--resolutions",
        nargs="+",
        type=resolution,
        metavar="WxH",
        default=None,
        help="image sizes, e.g. --resolutions 800x800 960x536 (default: 256x256 800x800 960x536)",
    )
    p.add_argument(
        "--thread-counts",
        dest="threads",
        nargs="+",
        type=thread_count,
        metavar="T",
        default=None,
        help="thread counts to time (rayon on the op, torch.set_num_threads for torch), "
        "e.g. --thread-counts 1 2 (default: 1 2)",
    )
    p.add_argument(  # the spelling before --thread-counts
        "--threads", dest="threads", nargs="+", type=thread_count, help=argparse.SUPPRESS
    )
    p.add_argument(
        "--repeats",
        type=positive_int,
        metavar="K",
        default=None,
        help="timed sync4d calls per measurement, median reported "
        "(default: 5, 3 for N >= 1M, 3 with --quick)",
    )
    p.add_argument(
        "--reference-max-gb",
        type=positive_float,
        metavar="GB",
        default=None,
        help="kill a reference run whose RSS passes this many GiB (default: 18, and never more "
        "than the memory available minus 1.5 GiB)",
    )
    p.add_argument(
        "--memory-method",
        choices=("auto", "clear_refs", "subprocess"),
        default="auto",
        help="peak-memory method: reset VmHWM via /proc/self/clear_refs, or run each "
        "measurement in a child process and read its ru_maxrss (default: auto)",
    )
    p.add_argument(
        "--no-reference",
        action="store_true",
        help="skip the gsplat torch reference timings",
    )
    p.add_argument(
        "--no-wgpu",
        action="store_true",
        help="skip the wgpu backend timings (default: timed when a wgpu adapter opens, "
        "e.g. lavapipe)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="N=10000 at 256x256 only, fewer repeats (smoke run); --sizes/--resolutions win",
    )
    p.add_argument(
        "--frames",
        type=positive_int,
        metavar="K",
        default=3,
        help="with RUN: test frames timed, evenly spread over the split (default: 3)",
    )
    p.add_argument(
        "--data",
        metavar="DATA",
        default=None,
        help="with RUN: the run's dataset folder, when it moved since the run",
    )
    p.add_argument(
        "--variant",
        action="append",
        default=None,
        metavar="NAME:KEY=VALUE,...",
        help="with RUN: also time rasterize with these keyword arguments (alpha_max, eps2d, "
        "antialiased, backend), frame by frame beside the default (repeatable)",
    )


def add_bench_fit_options(p: argparse.ArgumentParser) -> None:
    """The options of `bench fit`."""
    p.add_argument("data", nargs="*", default=[], metavar="DATA",
                      help="dataset folders, each trained with every budget and variant in "
                      "one invocation (default: the embedded synthetic scene)")
    add_training_options(p, "hyperparameters of every budget (default as for 'fit')")
    p.add_argument("--iters", nargs="+", type=positive_int, metavar="N", default=None,
                      help="iteration budgets (default: 1/8, 1/4, 1/2 and all of the config's)")
    p.add_argument("--scales", nargs="+", type=positive_float, metavar="S", default=None,
                      help="resolution scales (default: the config's)")
    p.add_argument("--caps", nargs="+", type=positive_int, metavar="N", default=None,
                      help="Gaussian caps (default: the config's max_gaussians)")
    p.add_argument("--variant", action="append", default=None, metavar="NAME[:KEY=VALUE,...]",
                      help="a config variant to compare (repeatable): NAME, then the --set "
                      "overrides it adds, e.g. --variant off --variant "
                      "skip:phase1.static.enabled=true; every budget trains each variant in "
                      "turn, so both see the same machine load. budget=F among them trains that "
                      "variant F times the iterations (schedules scaled alike): equal-time "
                      "comparisons")  # fmt: skip
    p.add_argument("--out", metavar="FILE.json", default=None,
                      help="results JSON (default bench-fit-NAME.json, bench-fit-scenes.json "
                      "for several; the plots go beside it)")
    p.add_argument("--keep-runs", metavar="DIR", default=None,
                      help="keep each budget's run folder under DIR")
    p.add_argument("--runs", nargs="+", metavar="RUN", default=None,
                      help="train nothing: tabulate these finished fit runs (one per scene, "
                      "say) and copy each one's worst test view beside --out")
