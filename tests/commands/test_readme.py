"""The README's first-run commands, run as written with a small iteration count: a new user who
follows them gets a trained embedded scene, its metrics, a language field answering a query and
a render."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from support.readme import first_run_commands, small_extra
from sync4d.cli import main
from sync4d.runs import CHECKPOINT_NAME, EVAL_FILE, PHASE1_CHECKPOINT_NAME, PHASE2_FILE

#: The full embedded scene (320 views) through both phases' set-up, evaluations and diagnostics:
#: 140 s with a study on both cores.
pytestmark = pytest.mark.slow


def test_readme_first_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SYNC4D_CACHE", str(tmp_path / "cache"))
    monkeypatch.chdir(tmp_path)
    cmds = first_run_commands()
    assert [c[0] for c in cmds] == ["fit", "fit", "fit", "query", "render"]
    for cmd in cmds:
        assert main(cmd + small_extra(cmd)) == 0, cmd
    run = tmp_path / "runs" / "first"
    for name in (CHECKPOINT_NAME, PHASE1_CHECKPOINT_NAME, EVAL_FILE, PHASE2_FILE):
        assert (run / name).is_file(), name
    assert json.loads((run / EVAL_FILE).read_text())["mean"]["psnr"] > 10.0
    assert len(json.loads((run / PHASE2_FILE).read_text())["objects"]) == 4
    assert len(list((run / "renders").glob("*.png"))) == 24
    assert list((run / "renders").glob("*.gif"))
    assert (run / "phase3" / "field.safetensors").is_file()
    assert list((run / "phase3").glob("query-*.png"))
