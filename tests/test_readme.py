"""The README's first-run commands, run as written with a small iteration count: a new user who
follows them gets a trained embedded scene, its metrics, a language field answering a query and
a render."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest

from sync4d.cli import main
from sync4d.runs import CHECKPOINT_NAME, EVAL_FILE, PHASE1_CHECKPOINT_NAME, PHASE2_FILE

#: The full embedded scene (320 views) through both phases' set-up, evaluations and diagnostics:
#: 140 s with a study on both cores.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
#: What the test adds to each `fit`: a tiny schedule (the commands themselves stay verbatim).
SMALL = ["--iters", "30", "--threads", "2", "--set", "eval_every=0",
         "--set", "phase2.iterations=4", "--set", "phase2.motion.refine_steps=1",
         "--set", "phase2.motion.refine_texture_rounds=0"]  # fmt: skip


def _first_run_commands() -> list[list[str]]:
    """The `python -m sync4d ...` lines of the README's "A first run" code block."""
    text = (ROOT / "README.md").read_text()
    section = text.split("## A first run", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S)
    assert block, "README: no sh block under 'A first run'"
    cmds = []
    for line in block.group(1).splitlines():
        words = shlex.split(line, comments=True)
        if words:
            assert words[:3] == ["python", "-m", "sync4d"], line
            cmds.append(words[3:])
    return cmds


def test_readme_first_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SYNC4D_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    cmds = _first_run_commands()
    assert [c[0] for c in cmds] == ["fit", "fit", "fit", "query", "render"]
    for cmd in cmds:
        if cmd[0] == "fit" and cmd[-2:] != ["--phases", "3"]:
            extra = SMALL
        elif cmd[0] == "query":
            extra = []
        else:
            extra = ["--threads", "2"]
        assert main(cmd + extra) == 0, cmd
    run = tmp_path / "runs" / "first"
    for name in (CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, EVAL_FILE, PHASE2_FILE):
        assert (run / name).is_file(), name
    assert json.loads((run / EVAL_FILE).read_text())["mean"]["psnr"] > 10.0
    assert len(json.loads((run / PHASE2_FILE).read_text())["objects"]) == 4
    assert len(list((run / "renders").glob("*.png"))) == 24
    assert list((run / "renders").glob("*.gif"))
    assert (run / "phase3" / "field.safetensors").is_file()
    assert list((run / "phase3").glob("query-*.png"))
