"""``sync4d completion bash|zsh``: a shell completion script of the whole command line, from
its parser (`sync4d.cli.build_parser`) through shtab. Path arguments are marked for it here
(`mark_paths`): folders complete as folders, files as files."""

from __future__ import annotations

import argparse
import sys

__all__ = ["add_arguments", "mark_paths", "print_script"]

#: Placeholders of the arguments that name a folder; FILE... and these name a file.
FOLDERS = ("DATA", "RUN", "DIR", "RUNS")
FILES = ("ANNOTATIONS", "CONFIG", "VIDEO|IMAGE_DIR")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d completion`` (`sync4d.cli`)."""
    p.description = (
        "Print a completion script for the sync4d command. bash: sync4d completion bash > "
        "~/.local/share/bash-completion/completions/sync4d; zsh: sync4d completion zsh > "
        "~/.zfunc/_sync4d (with ~/.zfunc on $fpath)."
    )
    p.add_argument("shell", choices=("bash", "zsh"), help="the shell to complete for")


def mark_paths(parser: argparse.ArgumentParser) -> None:
    """Mark path arguments (metavars DATA, RUN, DIR, FILE...) for shtab's completion: folders
    complete as folders, files as files. Without shtab the parser is unchanged."""
    try:
        import shtab
    except ImportError:
        return
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                mark_paths(sub)
        elif action.metavar in FOLDERS:
            action.complete = shtab.DIRECTORY  # type: ignore[attr-defined]
        elif isinstance(action.metavar, str) and (
            action.metavar.startswith("FILE") or action.metavar in FILES
        ):
            action.complete = shtab.FILE  # type: ignore[attr-defined]


def print_script(parser: argparse.ArgumentParser, shell: str) -> int:
    """Print the completion script of `parser` (every command's arguments added) for `shell`;
    the exit status."""
    try:
        import shtab
    except ImportError:
        print("sync4d completion: needs the shtab package: python -m pip install shtab",
              file=sys.stderr)  # fmt: skip
        return 2
    print(shtab.complete(parser, shell=shell, root_prefix="sync4d"))
    return 0
