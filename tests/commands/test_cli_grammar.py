"""The command line's table of commands, its registries and its grammar: every name comes from
one registry, each command's module adds its own arguments, and the spellings from before 0.1.0
are refused (CHANGELOG.md)."""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from support import ROOT
from sync4d import cli
from sync4d.cli import COMMANDS, GRAMMAR, build_parser, command_parsers, main
from sync4d.phase3.activation import DEFAULT_RULE, RULES, activate
from sync4d.phase3.config import Phase3Config
from sync4d.phase3.encoders.encoder import ENCODERS, describe_specs
from sync4d.phase3.query import DEFAULT_SCORER, SCORER_TABLE, SCORERS
from sync4d.runs.names import RUN_FILE
from sync4d.settings import allowed


def _option(parser: argparse.ArgumentParser, flag: str) -> argparse.Action:
    return next(a for a in parser._actions if flag in a.option_strings)


def test_every_command_is_a_row_with_a_module() -> None:
    parsers = command_parsers(build_parser())
    assert list(parsers) == [c.name for c in COMMANDS]
    for c in COMMANDS:
        assert c.forms and all(f.startswith(c.name) for f in c.forms), c
        assert importlib.util.find_spec(c.module) is not None, c.module
        module = importlib.import_module(c.module)
        assert callable(getattr(module, c.arguments)), c  # the command owns its arguments
        assert c.name == "completion" or callable(module.main), c
        assert parsers[c.name].description, c  # set by its arguments function
    for c in COMMANDS:  # the module docstring lists every form
        assert all(f in cli.__doc__ for f in c.forms)


def test_choices_and_help_come_from_the_registries() -> None:
    assert SCORERS == ("full", "paper", "static", "no-kinematics", "motion",
                       "names")  # eval's table order
    assert DEFAULT_SCORER == "full" and tuple(SCORER_TABLE) == SCORERS
    assert [n for n, s in SCORER_TABLE.items() if s.needs_names] == ["names"]
    assert tuple(RULES) == ("half-peak", "mean") and DEFAULT_RULE == "half-peak"
    parsers = command_parsers(build_parser())
    query, ev = parsers["query"], parsers["eval"]
    assert tuple(_option(query, "--scorer").choices) == SCORERS
    assert _option(query, "--scorer").default == DEFAULT_SCORER
    assert tuple(_option(ev, "--scorer").choices) == SCORERS
    for p in (query, ev):
        rule = _option(p, "--rule")
        assert tuple(rule.choices) == tuple(RULES)
        assert all(r.summary in rule.help for r in RULES.values())
    assert all(s.summary in _option(query, "--scorer").help for s in SCORER_TABLE.values())
    for name in ("fit", "query", "bench phase3"):
        assert describe_specs(summaries=True) in _option(parsers[name], "--encoder").help
    fields = {f.name: f for f in dataclasses.fields(Phase3Config)}
    assert allowed(fields["activation"]).choices == tuple(RULES)
    assert Phase3Config().activation == DEFAULT_RULE
    encoder = allowed(fields["encoder"])
    assert all(encoder.problem(e.word) is None for e in ENCODERS.values() if e.word)
    assert {e.kind for e in ENCODERS.values()} == {"offline", "siglip"}


def test_rules_answer_as_before() -> None:
    s = [0.1, 0.5, 0.3, 0.9, 0.2]
    assert activate(s).tolist() == [False, True, False, True, False]
    assert activate(s, "mean").tolist() == [False, True, False, True, False]
    assert activate([-3.0, -1.0, -2.5]).tolist() == [False, True, False]
    assert activate([0.2, 0.2]).tolist() == [True, True]
    with pytest.raises(ValueError, match="unknown activation rule"):
        activate(s, "peak")


def test_query_stays_light() -> None:
    code = ("import sys, sync4d.phase3.query, sync4d.phase3.config; "
            "assert 'torch' not in sys.modules, 'torch'")  # fmt: skip
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_main_adds_only_the_arguments_of_its_command() -> None:
    """`main` builds the parser of the command it runs: --help imports no registry, and the
    command parses as with the whole parser."""
    for argv in (["query", "R", "a ball", "--scorer", "paper", "--rule", "mean"],
                 ["bench", "raster", "R", "--frames", "2"], ["encoder", "convert", "--out", "d"],
                 ["eval", "R", "--queries", "q.json", "--scorer", "full", "names"]):  # fmt: skip
        assert build_parser(argv=argv).parse_args(argv) == build_parser().parse_args(argv)
    code = ("import sys; from sync4d.cli import build_parser; "
            "build_parser(argv=['--help']).format_help(); "
            "assert 'numpy' not in sys.modules and 'sync4d.phase3' not in sys.modules")  # fmt: skip
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_the_grammar_is_in_help_and_docs() -> None:
    text = build_parser().format_help()
    assert GRAMMAR in text
    docs = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert GRAMMAR in docs and "## `encoder convert`" in docs


def test_the_spellings_before_0_1_0_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The shims of the renames before 0.1.0 are gone (CHANGELOG.md): each old spelling is an
    argparse error (exit 2) naming it, and appears nowhere a user looks."""
    old = (["encoder", "export", "--out", "d"], ["bench", "raster", "--run", "R"],
           ["render", "R", "--times", "0.5"], ["render", "R", "--frames", "4"])  # fmt: skip
    for argv in old:
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2, argv
        err = capsys.readouterr().err
        assert "invalid choice: 'export'" in err or f"unrecognized arguments: {argv[-2]}" in err
    docs = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert "encoder export" not in docs and "--times" not in docs and "--run " not in docs
    assert main(["completion", "bash"]) == 0
    bash = capsys.readouterr().out
    assert "_shtab_sync4d_encoder_subparsers=(convert info)" in bash
    # `fit --out RUN --phases 3`, the one spelling of extending a run (`fit RUN` names DATA)
    run = tmp_path / "run"
    run.mkdir()
    (run / RUN_FILE).write_text("{}")
    assert main(["fit", "--out", str(run), "--phases", "3"]) == 2
    assert "needs a Phase 2 checkpoint" in capsys.readouterr().err


def test_bench_raster_takes_its_run_first(capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    for argv in (["R", "--frames", "2"], ["--frames", "2", "R"]):
        args = parser.parse_args(["bench", "raster", *argv])
        assert (args.run, args.frames) == ("R", 2)
    assert capsys.readouterr().err == ""
    assert parser.parse_args(["bench", "raster", "--quick"]).run is None
