"""The command line's shared options and argument types, in one place: every command's
`add_arguments` (in its own module) builds its options from these, so one option means one
thing everywhere (``--threads``, ``--backend``, ``--encoder``, ``--rule``, ``--config`` and
``--set``). Light (argparse and `sync4d.settings`): the registries an option's help lists
(encoders, activation rules) are read when the option is added, which the command line does
only for the command it runs."""

from __future__ import annotations

import argparse
import math

from sync4d.runs.names import BACKGROUNDS
from sync4d.settings import BACKENDS

__all__ = [
    "BACKGROUNDS",
    "add_backend",
    "add_encoder",
    "add_rule",
    "add_threads",
    "add_training_options",
    "background_colour",
    "encoder_help",
    "frame_count",
    "port_number",
    "positive_float",
    "positive_int",
    "resolution",
    "thread_count",
]


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


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text[:80]!r}") from None
    if not (value >= 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {value}")
    return value




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


def add_threads(p: argparse.ArgumentParser, what: str = "torch and the rasterizer") -> None:
    """--threads T: the CPU threads of `what` (the command line sets torch's before the command
    runs, `sync4d.cli`)."""
    p.add_argument("--threads", type=thread_count, default=None, metavar="T",
                   help=f"CPU threads for {what} (default: all cores)")


def add_backend(p: argparse.ArgumentParser) -> None:
    """--backend: the compositing backend of a command that renders or trains (`sync4d.cli`
    selects it before the command runs)."""
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="cpu",
        help="compositing backend: the Rust CPU path (default), wgpu (a GPU, else a CPU "
        "Vulkan driver such as lavapipe) or auto (wgpu on a GPU, else cpu)",
    )


def encoder_help(prefix: str = "", default: bool = False) -> str:
    """--encoder's help: `prefix`, then the encoder kinds of
    `sync4d.phase3.encoders.encoder.ENCODERS`; `default`: with the default when it is not
    given."""
    from sync4d.phase3.encoders.encoder import DEFAULT_ENCODER, ENCODER_ENV, describe_specs

    last = f"; ${ENCODER_ENV}, else {DEFAULT_ENCODER}, when not given" if default else ""
    return f"{prefix}{describe_specs(summaries=True)}{last}"


def add_encoder(p: argparse.ArgumentParser,
                prefix: str = "the encoder the field was built with, if it moved: ",
                default: bool = False) -> None:  # fmt: skip
    """--encoder DIR: Phase 3's image-text encoder (by default: of a command that reads a
    built field, the encoder if it moved); its help lists the encoder kinds (`encoder_help`)."""
    p.add_argument("--encoder", default=None, metavar="DIR", help=encoder_help(prefix, default))


def add_rule(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """--rule: a temporal activation rule of `sync4d.phase3.activation.RULES`."""
    from sync4d.phase3.activation import RULES

    rules = "; ".join(f"{name}: {rule.summary}" for name, rule in RULES.items())
    p.add_argument("--rule", choices=tuple(RULES), default=None,
                   help=f"{prefix}temporal activation, {rules} (default: the field's "
                   "phase3.activation)")  # fmt: skip


def add_training_options(p: argparse.ArgumentParser, config_help: str) -> None:
    """Options shared by every command that trains: config file, overrides, threads, backend."""
    p.add_argument("--config", metavar="FILE.toml", default=None, help=config_help)
    p.add_argument("--set", action="append", metavar="KEY=VALUE", default=[],
                   help="override a config value, e.g. --set phase1.densify.stop=10000 "
                   "(repeatable)")  # fmt: skip
    add_threads(p)
    add_backend(p)
