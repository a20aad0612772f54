"""Command-line interface: ``sync4d <command> ...`` (the console script) or, the same,
``python -m sync4d <command> ...``.

Every command is one row of `COMMANDS`: its words, its forms (the grammar, `GRAMMAR`), its help
line and the module that runs it. That module owns the rest: its ``add_arguments(parser)``
gives the command its description and arguments (the shared ones from `sync4d.options`), its
``main(args)`` runs it. `build_parser`, ``--help``, the shell completion and docs/cli.md
(`scripts/gen_docs.py`) all come from the table, and so does the command list at the end of
this docstring. Adding a command is a row here and its module.

A command's module is imported only when its arguments are needed (`main` adds those of the
command it runs alone): ``sync4d --help`` imports no command module, ``sync4d query`` no torch.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

from sync4d import __version__
from sync4d.commands.completion import mark_paths, print_script
from sync4d.errors import Sync4dError

__all__ = ["COMMANDS", "GRAMMAR", "GROUPS", "Command", "build_parser", "command_parsers", "main"]

#: The one rule every command's arguments follow (--help's epilog, docs/cli.md).
GRAMMAR = """\
The grammar, the same for every command:
  * Positional arguments name what a command works on; --out names the folder or file it
    writes. Folders are DATA (a dataset), RUN (a run folder) or DIR (any other).
  * A run is made and extended by fit alone, and fit always names it --out RUN: a new run
    (fit DATA --out RUN), or one continued (--resume), refit from Phase 2 (--phases 2) or
    given its language field (--phases 3), where DATA is optional: the run records it.
  * Every other command that reads a run takes it first, as RUN (eval, render, query, export,
    bench raster, bench phase3, view, serve); --data DATA names the run's dataset if it has
    moved.
  * export writes several files at once, so each of its options names one (--scene FILE)."""


@dataclass(frozen=True)
class Command:
    """One command of the command line (a row of `COMMANDS`)."""

    #: Its words: "fit", "bench raster".
    name: str
    #: Its forms, by `GRAMMAR`: "fit [DATA] --out RUN" (--help's epilog, docs/cli.md).
    forms: tuple[str, ...]
    #: One line for --help's command list.
    help: str
    #: The module that runs it (``main(args)``), imported on use.
    module: str
    #: The function of `module` that gives its parser its description and arguments.
    arguments: str = "add_arguments"


@dataclass(frozen=True)
class Group:
    """A word that gathers commands ("bench raster", "bench fit"): its help, and the argument
    name (`dest`) and placeholder of its second word."""

    help: str
    dest: str
    metavar: str


#: The words that gather commands.
GROUPS: dict[str, Group] = {
    "bench": Group("run a benchmark", "target", "TARGET"),
    "encoder": Group("convert or inspect a SigLIP-ONNX encoder (Phase 3)", "action", "ACTION"),
}

#: Every command, in --help's order.
COMMANDS: tuple[Command, ...] = (
    Command("fit", ("fit [DATA] --out RUN", "fit --out RUN --resume | --phases 2 | --phases 3"),
            "train a deformable 4D Gaussian scene (Phase 1) and decompose its motion (Phase 2)",
            "sync4d.commands.fit"),
    Command("process", ("process VIDEO|IMAGE_DIR --out DATA",),
            "turn your own video or photos into a dataset (camera poses from COLMAP)",
            "sync4d.commands.process"),
    Command("eval", ("eval RUN", "eval RUN --queries ANNOTATIONS"),
            "PSNR / SSIM / LPIPS of a run, or its temporal queries (--queries)",
            "sync4d.commands.eval"),
    Command("render", ("render RUN [--time T... | --sweep N] [--out DIR]",),
            "render a run at chosen times", "sync4d.commands.render"),
    Command("query", ("query RUN TEXT...",),
            "ask a run's language field which object matches a text, and when",
            "sync4d.commands.query"),
    Command("export", ("export RUN --scene FILE.json [--prompt FILE.txt] [--vocab FILE]",
                       "export RUN --ply FILE.ply | --spz FILE.spz [--time T]",
                       "export RUN --sequence FILE.ply|DIR/ [--frames N]"),
            "write a run as files other tools read: scene description, LLM prompt, PLY, SPZ",
            "sync4d.commands.export"),
    Command("view", ("view RUN [--port P] [--host ADDR]",),
            "open a run in the browser: scrub time, see each object move, ask a question",
            "sync4d.commands.view"),
    Command("serve", ("serve RUN [--http [HOST:]PORT]",),
            "serve a run to AI agents over the Model Context Protocol (MCP)",
            "sync4d.commands.serve"),
    Command("sweep", ("sweep MANIFEST.toml --out SWEEP [--address auto|HOST:PORT]",),
            "fit many scenes, configs and seeds on Ray, locally or on a cluster", "sync4d.sweep"),
    Command("bench raster", ("bench raster [RUN]",), "rasterizer forward/backward timings",
            "sync4d.bench.raster"),
    Command("bench fit", ("bench fit [DATA]", "bench fit --runs RUN..."),
            "Phase 1 test PSNR against training time (Pareto curve)", "sync4d.bench.fit"),
    Command("bench phase3", ("bench phase3 RUN...",),
            "Phase 3 build time and query latency on Phase 2 runs", "sync4d.bench.phase3"),
    Command("bench step", ("bench step RUN",),
            "where a Phase 1 step's time goes, per motion model (D_theta per Gaussian or nodes)",
            "sync4d.bench.step"),
    Command("bench view", ("bench view RUN",), "the viewer's time-slider latency on a run",
            "sync4d.bench.view"),
    Command("bench serve", ("bench serve RUN",),
            "sync4d serve under agents' load: the first describe, concurrent MCP clients",
            "sync4d.bench.serve"),
    Command("encoder convert", ("encoder convert --out DIR [--model NAME]",),
            "convert a Hugging Face SigLIP model into a SigLIP-ONNX encoder directory",
            "sync4d.commands.encoder", "add_convert_arguments"),
    Command("encoder info", ("encoder info DIR",),
            "describe an encoder directory and check its files", "sync4d.commands.encoder",
            "add_info_arguments"),
    Command("completion", ("completion bash|zsh",),
            "print a shell completion script (bash or zsh)", "sync4d.commands.completion"),
)  # fmt: skip


def command_list(helps: bool = True) -> str:
    """Every command's forms, one line each, and its help below them (`helps`)."""
    lines = []
    for c in COMMANDS:
        lines += [f"  {form}" for form in c.forms] + ([f"      {c.help}"] if helps else [])
    return "\n".join(lines)


def _defaults(name: str) -> dict[str, str]:
    """The words of command `name` as parsed arguments: command="bench", target="raster"."""
    first, *rest = name.split()
    out = {"command": first}
    if rest:
        out[GROUPS[first].dest] = rest[0]
    return out


def _wanted(argv: Sequence[str]) -> str:
    """The command words `argv` starts with ("query", "bench raster"; "" for none)."""
    words = [a for a in argv if not a.startswith("-")]
    if words and words[0] in GROUPS:
        return " ".join(words[:2])
    return words[0] if words else ""


def build_parser(prog: str = "sync4d", argv: Sequence[str] | None = None
                 ) -> argparse.ArgumentParser:  # fmt: skip
    """The parser of every command in `COMMANDS`. Given the command line `argv`, only the
    command it runs gets its description and arguments (`main`: ``--help`` imports no command
    module); every command is listed either way."""
    wanted = None if argv is None else _wanted(argv)
    parser = argparse.ArgumentParser(
        prog=prog,
        description="sync4d: 4D Synchronized Fields (CPU Gaussian splatting in Rust + PyTorch).",
        epilog=f"forms (sync4d COMMAND --help: its options):\n{command_list(helps=False)}\n\n"
        f"{GRAMMAR}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"sync4d {__version__}")
    levels = {"": parser.add_subparsers(dest="command", metavar="COMMAND", required=True)}
    for cmd in COMMANDS:
        *group, leaf = cmd.name.split()
        key = " ".join(group)
        if key not in levels:  # the group's own parser, on its first command
            g = GROUPS[key]
            words = levels[""].add_parser(key, help=g.help)
            levels[key] = words.add_subparsers(dest=g.dest, metavar=g.metavar, required=True)
        sub = levels[key].add_parser(leaf, help=cmd.help)
        if wanted is None or wanted == cmd.name:
            module = _module(cmd.module)
            if module is None:  # missing from this install: `main` says so
                sub.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
            else:
                getattr(module, cmd.arguments)(sub)
        sub.set_defaults(handler=cmd.module, **_defaults(cmd.name))
    mark_paths(parser)
    return parser


def _module(name: str) -> ModuleType | None:
    """The command module `name`, imported; None when this install lacks it."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as exc:
        if exc.name is not None and name.startswith(exc.name):
            return None
        raise


def command_parsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """The parser of every command of `parser` (`build_parser`'s) by its words ("bench
    raster"), in `COMMANDS`' order."""
    out: dict[str, argparse.ArgumentParser] = {}
    for cmd in COMMANDS:
        p = parser
        for word in cmd.name.split():
            words = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
            p = words.choices[word]
        out[cmd.name] = p
    return out


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    _tolerate_undecodable_output()
    args = build_parser(_prog(), argv).parse_args(argv)
    if args.command == "completion":  # completes every command: all their arguments
        return print_script(build_parser("sync4d"), args.shell)
    module = _module(args.handler)
    if module is None:
        print(f"python -m sync4d: '{args.command}' is not available: module {args.handler} is "
              "missing from this install", file=sys.stderr)  # fmt: skip
        return 2
    if not hasattr(args, "backend"):  # e.g. query: no rendering, no torch import
        _bound_torch_threads(args)
        return _call(module, args)
    from sync4d import raster  # torch too: a command that renders

    _bound_torch_threads(args)
    backend = getattr(args, "backend", None)
    previous = raster.resolve_backend()
    if backend not in (None, "cpu"):
        try:
            args.backend = raster.set_default_backend(backend)
        except RuntimeError as e:
            print(f"python -m sync4d {args.command}: {e}", file=sys.stderr)
            return 2
        if backend == "wgpu":
            from sync4d._core import wgpu_adapter
            print(f"sync4d: backend wgpu on {wgpu_adapter()}", file=sys.stderr)
        elif raster.auto_choice():
            print(f"sync4d: {raster.auto_choice()}", file=sys.stderr)
    try:
        return _call(module, args)
    finally:
        raster.set_default_backend(previous)  # main() may be called again in-process


def _call(module: ModuleType, args: argparse.Namespace) -> int:
    """`module.main(args)`'s exit status. An OSError that reaches here (a path the system
    refuses: too long, a folder where a file goes, no permission; `WriteFailed` too) becomes
    one line naming the path, and exit 2; a `Sync4dError` that the command let through (the
    watchdog's stop on a NaN or a diverged value, say) its one message and its exit code (3
    for the watchdog's)."""
    try:
        return int(module.main(args) or 0)
    except OSError as e:
        group = GROUPS.get(args.command)
        words = " ".join([args.command] + ([getattr(args, group.dest)] if group else []))
        name = str(e.filename) if e.filename is not None else ""
        shown = f"{name[:80]}... ({len(name)} characters)" if len(name) > 100 else name
        if not name:  # not a path: a connection, a device
            print(f"{_prog()} {words}: {e}", file=sys.stderr)
            return 2
        print(f"{_prog()} {words}: {e.strerror or e}: {shown!r}; check the paths on the command "
              "line (a folder that exists and is writable, names of a sane length)",
              file=sys.stderr)  # fmt: skip
        return 2
    except Sync4dError as e:  # after OSError: a WriteFailed keeps its line naming the path
        print(f"{_prog()} {args.command}: {e}", file=sys.stderr)
        return e.exit_code


def _tolerate_undecodable_output() -> None:
    """Let stdout and stderr print the paths of any command line: argv's bytes that are not
    UTF-8 arrive as surrogate escapes, which a strict stream refuses (UnicodeEncodeError);
    stdout writes them back as the same bytes, stderr as backslash escapes (its default)."""
    for stream, errors in ((sys.stdout, "surrogateescape"), (sys.stderr, "backslashreplace")):
        if getattr(stream, "errors", None) == "strict" and hasattr(stream, "reconfigure"):
            stream.reconfigure(errors=errors)


def _bound_torch_threads(args: argparse.Namespace) -> None:
    """`--threads T`: torch's intra-op threads before the command runs anything (an op before
    `torch.set_num_threads` starts a second OpenMP pool: issue 51), where torch is loaded."""
    threads = getattr(args, "threads", None)
    if type(threads) is int and "torch" in sys.modules:  # not bench raster's list
        import torch

        torch.set_num_threads(threads)


def _prog() -> str:
    """The name the user typed: ``sync4d`` (console script) or ``python -m sync4d``."""
    return "python -m sync4d" if Path(sys.argv[0]).name == "__main__.py" else "sync4d"


__doc__ = f"{__doc__}\nCommands (from `COMMANDS`; every option: docs/cli.md):\n{command_list()}\n"

if __name__ == "__main__":
    sys.exit(main())
