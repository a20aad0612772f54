"""Every argument, any bytes (issue 53): each command's text, number and path arguments, read
from the parser itself (a new command or option is covered without touching this file), get
what a shell can pass: empty, huge, negative, NaN, inf, unicode (RTL, emoji, combining marks)
and bytes that are not valid UTF-8 (as Python hands them over: surrogate escapes), one argument
at a time on a command line that works otherwise, against a small run (the oracle run). Each
ends in a normal answer or one clear message (usage or `COMMAND: ...` on stderr) with a
non-zero exit, never a traceback.

Commands that start long work (fit, sweep, view, serve, bench, process, encoder convert) run
their argument checks for real and stop where the work would start (`STOPS`: the first call of
the work raises `Started`); render stops before rendering more than a few frames."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import json
import os
import subprocess
import sys
import traceback
from pathlib import Path

import pytest

from support.datasets import write_blender
from support.oracle import oracle_run_folder
from support.ports import free_port
from sync4d.cli import COMMANDS, build_parser, command_parsers, main

#: Invalid UTF-8 as a shell passes it, decoded as Python decodes argv (surrogate escapes).
BAD_BYTES = os.fsdecode(b"run-\xff\xfe-\xc3(")
#: What a shell can pass as one argument.
VALUES = (
    "",
    "0",
    "-1",
    "1e308",
    "-1e308",
    str(10**30),
    "nan",
    "inf",
    "-inf",
    "x" * 100_000,
    "\u202eevil\u202c txt",  # right-to-left override
    "🎈 ball 🟥",
    "e\u0301\u0302\u0303 a\u0308",  # combining marks
    BAD_BYTES,
    "a,b=c:d",
    ".",
    "/dev/null",
)
#: Argument actions that take no value (flags) or are not arguments.
NO_VALUE = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._HelpAction,
            argparse._VersionAction, argparse._SubParsersAction, argparse._CountAction,
            argparse._StoreConstAction)  # fmt: skip


class Started(BaseException):
    """The long work of a command was reached: its arguments were accepted."""


def _stop(*args, **kwargs):
    raise Started


def _stop_long_renders(real):
    def render_times(model, camera, times, *args, **kwargs):
        if len(times) > 4:
            raise Started
        return real(model, camera, times, *args, **kwargs)

    return render_times


#: Where each long command's work starts (module attribute replaced by `_stop`).
STOPS = {
    "fit": ("sync4d.pipeline.request.fit_request",),
    "process": ("sync4d.data.process.process_capture",
                "sync4d.commands.process.process_capture"),
    "eval": ("sync4d.pipeline.evaluate.evaluate_run",),
    "view": ("sync4d.viewer.state.ViewerState",),
    "serve": ("sync4d.serve.server.serve",),
    "sweep": ("sync4d.sweep.run_sweep",),
    "bench raster": ("sync4d.bench.raster._step_units", "sync4d.bench.raster_run.main"),
    "bench fit": ("sync4d.bench.fit.run_grid", "sync4d.bench.fit._tabulate_runs"),
    "bench phase3": ("sync4d.bench.phase3.bench_run",),
    "bench step": ("sync4d.bench.step.bench_step",),
    "bench view": ("sync4d.bench.view.bench_view",),
    "bench serve": ("sync4d.bench.serve.bench_serve",),
    "encoder convert": ("sync4d.phase3.encoders.siglip.export_pretrained",),
}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    """The small things the base command lines name: the oracle run (with its field), a tiny
    Blender dataset, a sweep manifest, a query file, a free port."""
    tmp = tmp_path_factory.mktemp("arguments")
    run = oracle_run_folder(tmp / "oracle", queries=("red", "blue"))
    write_blender(tmp / "tiny", n=4, size=24)
    (tmp / "photos").mkdir()
    manifest = tmp / "sweep.toml"
    manifest.write_text(f'[[job]]\ndata = "{tmp / "tiny"}"\niters = 1\nphases = "1"\n')
    return {"run": str(run), "data": str(tmp / "tiny"), "manifest": str(manifest),
            "photos": str(tmp / "photos"), "tmp": str(tmp), "port": str(free_port())}


def _bases(w: dict[str, str]) -> dict[str, tuple[list[str], dict[str, list[str]]]]:
    """A command line of each command that works (positional values by dest, then options),
    before one of its arguments is replaced."""
    run, data, out = w["run"], w["data"], str(Path(w["tmp"]) / "out")
    return {
        "fit": ([data], {"--out": [out], "--iters": ["1"], "--threads": ["1"]}),
        "process": ([w["photos"]], {"--out": [out]}),
        "eval": ([run], {"--threads": ["1"]}),
        "render": ([run], {"--sweep": ["2"], "--out": [out], "--threads": ["1"]}),
        "query": ([run, "red"], {"--no-plot": []}),
        "export": ([run], {"--ply": [str(Path(w["tmp"]) / "o.ply")], "--threads": ["1"]}),
        "view": ([run], {"--port": [w["port"]], "--threads": ["1"]}),
        "serve": ([run], {"--threads": ["1"]}),
        "sweep": ([w["manifest"]], {"--out": [out], "--cpus": ["1"]}),
        "bench raster": ([], {"--quick": [], "--no-reference": [], "--no-wgpu": [],
                              "--out": [str(Path(w["tmp"]) / "b.json")]}),
        "bench fit": ([data], {"--iters": ["1"], "--out": [str(Path(w["tmp"]) / "f.json")]}),
        "bench phase3": ([run], {"--out": [str(Path(w["tmp"]) / "p.json")]}),
        "bench step": ([run], {"--out": [str(Path(w["tmp"]) / "s.json")]}),
        "bench view": ([run], {"--out": [str(Path(w["tmp"]) / "v.json")]}),
        "bench serve": ([run], {"--starts": ["0"], "--out": [str(Path(w["tmp"]) / "sv.json")]}),
        "encoder convert": ([], {"--out": [str(Path(w["tmp"]) / "enc")]}),
        "encoder info": ([str(Path(w["tmp"]) / "enc")], {}),
        "completion": (["bash"], {}),
    }


def _arguments(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    """The arguments of a command's parser that take a value."""
    return [a for a in parser._actions if not isinstance(a, NO_VALUE)]


def _line(words: str, positionals: list[str], options: dict[str, list[str]]) -> list[str]:
    """The command line: words, options (--flag=value), then '--' and the positionals."""
    argv = words.split()
    for flag, vals in options.items():
        argv += [f"{flag}={vals[0]}"] if len(vals) == 1 else [flag, *vals]
    return [*argv, "--", *positionals] if positionals else argv


def _argv(words: str, positionals: list[str], options: dict[str, list[str]],
          action: argparse.Action, value: str, parser: argparse.ArgumentParser) -> list[str]:
    """The command line with `action`'s value replaced by `value`: options as --flag=value (a
    value that starts with '-' reaches the argument's type), positionals after '--'."""
    pos_actions = [a for a in _arguments(parser) if not a.option_strings]
    pos = list(positionals)
    opts = dict(options)
    if action.option_strings:
        for flag in action.option_strings:
            opts.pop(flag, None)
        for other in parser._actions:  # another option stored in the same dest
            if other.dest == action.dest:
                for flag in other.option_strings:
                    opts.pop(flag, None)
        opts[action.option_strings[0]] = [value]
    else:
        i = pos_actions.index(action)
        pos = (pos + [""] * len(pos_actions))[:max(len(pos), i + 1)]
        pos[i] = value
    return _line(words, pos, opts)


def _run(argv: list[str]) -> tuple[int | str, str, str]:
    """`main(argv)` in this process: (exit status, "started" or "raised", stdout, stderr); an
    exception that escapes `main` is "raised", its traceback on stderr."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code: int | str = main(argv)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
        except Started:
            code = "started"
        except Exception:  # noqa: BLE001 - the failure this test looks for
            code = "raised"
            err.write(f"\nTraceback (escaped main):\n{traceback.format_exc()[-1500:]}")
    return code, out.getvalue(), err.getvalue()


def _clear(code: int | str, err: str, words: str) -> bool:
    """One clear message: usage / `error:` from argparse, or `COMMAND: ...` from the command."""
    if code in (0, "started"):
        return True
    first = words.split()[0]
    text = err.strip()
    return bool(text) and "Traceback" not in text and (
        "error:" in text or any(ln.startswith((f"{first}", f"{words}", "sync4d", "python -m"))
                                for ln in text.splitlines()))  # fmt: skip


#: Commands whose base command line is refused here (no encoder directory to inspect).
BASE_REFUSED = {"encoder info"}
PARSERS = command_parsers(build_parser())


@pytest.mark.parametrize("words", list(PARSERS))
def test_every_argument_takes_any_value(words, world, monkeypatch, tmp_path):
    """One argument at a time, each value of `VALUES`: an answer, or a clear message and a
    non-zero exit; never a traceback."""
    monkeypatch.chdir(tmp_path)  # relative paths ("", ".") write here
    monkeypatch.setenv("SYNC4D_ENCODER", "")
    # Import every module first: a module imported while another is patched would bind the
    # stand-in (`from ... import name`), and undoing the patch would restore the stand-in.
    targets = [(importlib.import_module(t.rsplit(".", 1)[0]), t.rsplit(".", 1)[1])
               for t in STOPS.get(words, ())]  # fmt: skip
    for module, name in targets:
        monkeypatch.setattr(module, name, _stop)
    if words == "render":
        from sync4d.commands import render

        monkeypatch.setattr(render, "render_times", _stop_long_renders(render.render_times))
    bases = _bases(world)
    assert words in bases, f"add a working command line of `{words}` to _bases"
    positionals, options = bases[words]
    sub = PARSERS[words]
    code, out, err = _run(_line(words, positionals, options))
    assert code in (0, "started") or words in BASE_REFUSED, (
        f"the base command line of {words} fails:\n{err[-2000:]}")
    bad = []
    for action in _arguments(sub):
        for value in VALUES:
            argv = _argv(words, positionals, options, action, value, sub)
            code, out, err = _run(argv)
            if not _clear(code, err, words) or "Traceback" in err + out:
                bad.append(f"{action.dest}={value[:40]!r}: exit {code}: {err[-400:]}")
    assert not bad, f"{words}: unclear answers:\n" + "\n".join(bad)


def test_every_command_has_a_base_command_line(world):
    assert set(_bases(world)) >= {c.name for c in COMMANDS}


@pytest.mark.slow  # a process each (torch's import): about 10 s apiece on 2 busy cores
@pytest.mark.parametrize("argv", [
    ["query", "{run}", os.fsencode(BAD_BYTES), "--no-plot"],
    ["render", "{run}", "--sweep", "2", "--out", b"{tmp}/out-\xff\xfe"],
    ["export", "{run}", "--ply", b"{tmp}/\xff.ply"],
    ["eval", b"{tmp}/no-\xff-run"],
    ["fit", b"\xff\xfe", "--out", b"{tmp}/fit-\xc3(", "--iters", "1"],
])  # fmt: skip
def test_bytes_that_are_not_text_through_a_real_process(argv, world):
    """The same through a process of its own, the bytes in argv as a shell passes them: the
    streams of a real process (strict UTF-8 stdout) take them too."""
    def fill(a):
        if isinstance(a, bytes):
            return a.replace(b"{run}", os.fsencode(world["run"])).replace(
                b"{tmp}", os.fsencode(world["tmp"]))
        return a.format(**world)

    env = {**os.environ, "PYTHONIOENCODING": "", "LC_ALL": "C.UTF-8", "OMP_NUM_THREADS": "1",
           "SYNC4D_ENCODER": ""}  # fmt: skip
    proc = subprocess.run([sys.executable, "-m", "sync4d", *map(fill, argv)], cwd=world["tmp"],
                          capture_output=True, env=env, timeout=300)  # fmt: skip
    err = proc.stderr.decode("utf-8", "replace")
    assert "Traceback" not in err, err[-3000:]
    assert proc.returncode == 0 or err.strip(), err


@pytest.fixture(scope="module")
def offline_run(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The oracle run with its field built by the default encoder (offline: MiniLM's
    tokenizer and text model read every new text)."""
    return str(oracle_run_folder(tmp_path_factory.mktemp("offline") / "oracle",
                                 encoder="offline"))  # fmt: skip


@pytest.mark.parametrize("value", VALUES)
def test_any_text_through_the_default_encoder(value, offline_run, tmp_path):
    """A query of any text on a field of the default encoder (the stub of the test above fails
    before a tokenizer is reached): an answer, or one sentence and a non-zero exit; the same
    text in a relational question file for `eval --queries`."""
    code, out, err = _run(["query", offline_run, "--no-plot", "--", value])
    assert _clear(code, err, "query") and "Traceback" not in err + out, err[-1500:]
    questions = tmp_path / "questions.json"
    questions.write_text(json.dumps({
        "version": 1, "kind": "relational", "questions": [
            {"question": value, "form": "relation", "object": "red ball", "times": []}]}))
    code, out, err = _run(["eval", offline_run, "--queries", str(questions)])
    assert _clear(code, err, "eval") and "Traceback" not in err + out, err[-1500:]
    if value.strip():  # a vocabulary entry of the same text, through export
        vocab = tmp_path / "vocab.json"
        vocab.write_text(json.dumps([value]))
        code, out, err = _run(["export", offline_run, "--vocab", str(vocab), "--scene",
                               str(tmp_path / "scene.json"), "--threads", "1"])  # fmt: skip
        assert _clear(code, err, "export") and "Traceback" not in err + out, err[-1500:]


#: Text an MCP client can send that a shell cannot: a lone surrogate (JSON "\ud800"), a NUL.
PROTOCOL_TEXTS = ("\ud800 ball", "red\x00ball", "\udcff")


@pytest.mark.parametrize("value", VALUES + PROTOCOL_TEXTS)
def test_any_text_through_the_query_box_and_the_mcp_tool(value, offline_run):
    """The viewer's query box and the MCP `query` tool on the default encoder's field: an
    answer, or one sentence (QueryError in the viewer, ToolProblem in the tool), never an
    exception of the tokenizer."""
    from sync4d.phase3.texts import QueryError
    from sync4d.serve.tools import RunTools, ToolProblem
    from sync4d.viewer.state import ViewerState

    state = ViewerState(offline_run)
    try:
        ans = state.ask(value)
        assert ans["objects"] and ans["top_label"] == ans["objects"][0]["label"]
    except QueryError as e:
        assert str(e) and "\n" not in str(e).strip(), str(e)
    tools = RunTools(offline_run)
    try:
        ans = tools.query(value)
        assert ans["objects"]
    except ToolProblem as e:
        assert str(e) and "\n" not in str(e).strip(), str(e)
