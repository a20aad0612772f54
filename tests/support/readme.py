"""The README's command blocks, read the way a user reads them: the tests run these lines, so
the README cannot drift from what works."""

from __future__ import annotations

import re
import shlex

from support import ROOT

README = ROOT / "README.md"


def first_sh_block(after: str) -> list[str]:
    """Non-empty lines of the first ```sh block after the text `after` in the README."""
    text = README.read_text(encoding="utf-8")
    assert after in text, f"README: no {after!r}"
    block = re.search(r"```sh\n(.*?)```", text.split(after, 1)[1], re.S)
    assert block, f"README: no sh block after {after!r}"
    return [line for line in block.group(1).splitlines() if line.strip()]


def user_install_lines() -> list[str]:
    """The shell lines of the README's user install block (under "**As a user**")."""
    return first_sh_block("**As a user**")


def first_run_commands() -> list[list[str]]:
    """The `sync4d ...` commands of the README's "A first run" block, without the `sync4d`
    word (comments dropped)."""
    text = README.read_text(encoding="utf-8")
    section = text.split("## A first run", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block, "README: no sh block under 'A first run'"
    cmds = []
    for line in block.group(1).splitlines():
        words = shlex.split(line, comments=True)
        if words:
            assert words[0] == "sync4d", line
            cmds.append(words[1:])
    return cmds


#: What the tests add to each first-run `fit` (Phases 1-2): a tiny schedule; the commands
#: themselves stay verbatim.
# `--iters` scales Phase 2's schedule with it (30 iterations, its terms' starts within them); a
# shorter phase2.iterations alone would leave M_phi's start after its end, which the config
# refuses.
SMALL_FIT = ["--iters", "30", "--threads", "2", "--set", "eval_every=0",
             "--set", "phase2.motion.refine_steps=1",
             "--set", "phase2.motion.refine_texture_rounds=0"]  # fmt: skip


def small_extra(cmd: list[str]) -> list[str]:
    """The options a test appends to first-run command `cmd` to keep it small."""
    if cmd[0] == "fit" and cmd[-2:] != ["--phases", "3"]:
        return SMALL_FIT
    if cmd[0] == "query":
        return []
    return ["--threads", "2"]
