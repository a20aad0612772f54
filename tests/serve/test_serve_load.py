"""`sync4d serve` under agents' load, on the oracle run of the embedded scene: the load
benchmark run small (concurrent SDK clients over streamable HTTP, every answer well formed, no
error, the run folder untouched), the description kept between starts and invalidated with
the field, renders that fail answered as one-sentence tool errors, and the caches that grow
per call (query texts, renders, kept descriptions) held to their bounds. Behaviour only: no
wall-clock time is asserted."""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
from pathlib import Path

import pytest
from mcp import Client

from support.encoders import ColourEncoder
from support.oracle import oracle_run_folder
from support.render import nan_render
from sync4d import watchdog
from sync4d.bench import serve as bench
from sync4d.phase1.gaussians import DeformableGaussians
from sync4d.phase3.query import TextCache
from sync4d.phase3.store import load_field
from sync4d.serve import cache as kept
from sync4d.serve import tools as serve_tools
from sync4d.serve.server import build_server
from sync4d.serve.tools import RunTools

QUERIES = ("the red ball", "the blue box while it is falling")
RELATIONAL = ("the ball that lands first", "which object lands last")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """The oracle run with its field (colour encoder), the benchmark's texts cached: the
    server, another process, cannot load the test encoder for a new text."""
    return oracle_run_folder(tmp_path_factory.mktemp("serve-load"), QUERIES + RELATIONAL)


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    """Kept descriptions go to this test's folder, not the user's cache."""
    monkeypatch.setenv("SYNC4D_SERVE_CACHE", str(tmp_path / "cache"))


def _files(run: Path) -> dict[str, bytes]:
    return {str(p.relative_to(run)): p.read_bytes() for p in sorted(run.rglob("*"))
            if p.is_file() and p.name != ".lock"}  # fmt: skip


def _one_sentence(text: str) -> str:
    """The sentence after the SDK's prefix; asserts it is one line and one sentence."""
    assert "\n" not in text and ". " not in text, text
    return text


def test_the_load_benchmark_small(run_dir, tmp_path, monkeypatch):
    """4 clients x 5 calls over streamable HTTP and two timed stdio starts: zero errors, every
    tool in the record with its latencies, the record's date, command and machine."""
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    before = _files(run_dir)
    out = tmp_path / "serve.json"
    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args([str(run_dir), "--clients", "4", "--calls", "5", "--starts", "2",
                              "--threads", "1", "--queries", *QUERIES, "--relational",
                              *RELATIONAL, "--out", str(out)])  # fmt: skip
    assert bench.main(args) == 0
    rec = json.loads(out.read_text())
    assert {"date", "command", "machine"} <= set(rec) and rec["machine"]["cpus"]
    load = rec["load"]
    assert load["errors"] == 0 and load["error_examples"] == [], load["error_examples"]
    assert load["objects"] == ["red ball", "blue box", "green pillar"]
    assert set(load["per_tool"]) == set(bench.KINDS)
    assert load["overall"]["n"] == 20 and sum(r["n"] for r in load["per_tool"].values()) == 20
    for r in [*load["per_tool"].values(), load["overall"]]:
        assert r["n"] > 0 and r["errors"] == 0
        assert 0 < r["p50_ms"] <= r["p95_ms"] <= r["max_ms"]
    first = rec["first_describe"]
    assert len(first["kept"]) == 1 and first["kept_median"] is not None
    for times in (first["built"], first["kept"][0]):
        assert set(times) == {"initialize_s", "describe_after_initialize_s",
                              "describe_from_start_s", "second_describe_s"}  # fmt: skip
        assert times["describe_from_start_s"] > times["initialize_s"] > 0
    assert _files(run_dir) == before  # serve is read-only: no texts.json, no description


def test_the_plan_mixes_every_tool_in_equal_shares():
    import random

    names = ["red ball", "blue box"]
    plan = bench.plan_calls(5, 20, random.Random(0), names, 2, list(QUERIES), list(RELATIONAL))
    kinds = [k for k, _, _ in plan]
    assert sorted(kinds) == sorted(bench.KINDS * 4) and kinds != list(bench.KINDS * 4)
    for kind, tool, args in plan:
        if tool == "track":
            assert args["object"] in names and 0 <= args["t0"] <= args["t1"] <= 1
        if kind == "render":
            assert args["camera"] in ("test:0", "test:1")
        if kind == "relational":
            assert args["text"] in RELATIONAL
    assert bench.percentile([3.0, 1.0, 2.0, 4.0], 50) == 2.0
    assert bench.percentile([3.0, 1.0, 2.0, 4.0], 95) == 4.0


def test_the_description_is_kept_between_starts_and_follows_the_field(run_dir, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(run_dir, run)
    first = RunTools(run)
    d = first.describe()
    assert first.scene_source == "built"
    again = RunTools(run)
    assert again.describe() == d and again.scene_source == "kept"
    assert again._run is None  # read back: no torch, no checkpoint
    assert again.scene_json() == first.scene_json() and again.prompt() == first.prompt()
    assert again.scene() == first.scene()  # read back into the same model
    # an entry the model refuses (another format, a damaged file) is built again
    kept.write_description(kept.description_key(run), '{"objects": []}', "prompt")
    damaged = RunTools(run)
    assert damaged.scene_json() == first.scene_json() and damaged.scene_source == "built"
    # a rebuilt field (a new field.json) is another entry: the description is built again
    meta = run / "phase3" / "field.json"
    st = meta.stat()
    os.utime(meta, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    rebuilt = RunTools(run)
    rebuilt.describe()
    assert rebuilt.scene_source == "built"


def test_kept_descriptions_are_bounded(tmp_path, monkeypatch):
    monkeypatch.setattr(kept, "KEPT_DESCRIPTIONS", 3)
    for i in range(6):
        kept.write_description(f"key{i}", "{}", "prompt")
        os.utime(kept._folder() / f"key{i}.json", ns=(i * 10**9, i * 10**9))
    kept.write_description("key6", "{}", "prompt")
    names = sorted(p.stem for p in kept._folder().glob("*.json"))
    assert len(names) == 3 and "key6" in names and "key0" not in names
    assert kept.read_description("key6") == ("{}", "prompt")
    assert kept.read_description("key0") is None


def test_many_distinct_queries_stay_within_the_bound(run_dir, monkeypatch):
    """Distinct texts evict the least recently used beyond `TEXT_CACHE_SIZE`; nothing is
    written to the run; renders are bounded by `RENDER_CACHE_SIZE` too."""
    # a query reads about 85 texts (its own and the motion phrases'), each new one 4 more
    monkeypatch.setattr(serve_tools, "TEXT_CACHE_SIZE", 100)
    monkeypatch.setattr(serve_tools, "RENDER_CACHE_SIZE", 3)
    texts = run_dir / "phase3" / "texts.json"
    before = texts.read_bytes()
    tools = RunTools(run_dir, encoder=ColourEncoder())
    for i in range(40):
        ans = tools.query(f"the red ball number {i}")
        assert ans["answer"]["name"] == "red ball"
        assert tools._cache is not None and len(tools._cache.texts) <= 100
    assert tools._cache.encoded > 100  # more texts went through than the bound holds
    kept_texts = list(tools._cache.texts)  # the most recent are kept, the oldest dropped
    assert any(t.endswith("number 39") for t in kept_texts)
    assert not any(t.endswith("number 0") for t in kept_texts)
    assert texts.read_bytes() == before
    pngs = [tools.render(t / 10)[0] for t in range(6)]
    assert len(tools._renders) == 3
    assert tools.render(0.5)[0] == pngs[5]  # a repeated render: the kept image


def test_the_text_cache_bound_keeps_the_recently_used(run_dir, tmp_path):
    field = load_field(run_dir)
    shutil.copytree(run_dir / "phase3", tmp_path / "phase3")
    cache = TextCache(tmp_path, field, ColourEncoder(), limit=3, persist=False)
    assert len(cache.texts) <= 3
    cache.get(["red a", "red b", "red c"])
    cache.get(["red a"])  # used again: now the most recent
    cache.get(["red d"])
    assert list(cache.texts) == ["red c", "red a", "red d"]
    with pytest.raises(ValueError, match="limit"):
        TextCache(tmp_path, field, ColourEncoder(), limit=0)
    assert (tmp_path / "phase3" / "texts.json").read_bytes() == (
        run_dir / "phase3" / "texts.json").read_bytes()  # fmt: skip


def test_a_failed_render_is_a_one_sentence_tool_error(run_dir, monkeypatch):
    """The watchdog's stop in a render, NaN pixels and the rasterizer's refusal reach the MCP
    client as error results of one sentence; the server answers the next render."""
    tools = RunTools(run_dir, threads=1)
    real = DeformableGaussians.render

    async def session() -> list:
        async with Client(build_server(tools), read_timeout_seconds=120) as c:
            out = []
            with watchdog.injected("Rendering", None, "input:means"):
                out.append(await c.call_tool("render", {"t": 0.5}))
            monkeypatch.setattr(DeformableGaussians, "render", nan_render(real))
            out.append(await c.call_tool("render", {"t": 0.25, "camera": "train:1"}))

            def refuse(*args, **kwargs):
                raise ValueError("means: contains NaN or inf")

            monkeypatch.setattr(DeformableGaussians, "render", refuse)
            out.append(await c.call_tool("render", {"t": 0.75}))
            monkeypatch.setattr(DeformableGaussians, "render", real)
            out.append(await c.call_tool("render", {"t": 0.5}))
            return out

    stopped, nan, refused, ok = asyncio.run(session())
    texts = []
    for r in (stopped, nan, refused):
        assert r.is_error and len(r.content) == 1 and r.content[0].type == "text"
        texts.append(_one_sentence(r.content[0].text))
    assert "t = 0.5" in texts[0] and "stopped" in texts[0] and "NaN or inf" in texts[0]
    assert "means" in texts[0] and "fit --out RUN --force" in texts[0]
    assert "t = 0.25" in texts[1] and "NaN or inf pixels" in texts[1]
    assert "t = 0.75" in texts[2] and "contains NaN or inf" in texts[2]
    assert "sync4d render RUN" in texts[2]
    assert not ok.is_error and ok.content[0].type == "image"


def test_bench_serve_refuses_a_bad_run_or_option(run_dir, tmp_path, capsys):
    """`bench serve`'s own refusals: one line each, exit 2, nothing served."""
    from sync4d.cli import main

    assert main(["bench", "serve", str(tmp_path / "nope")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    assert main(["bench", "serve", str(run_dir), "--starts", "-1"]) == 2
    assert "give 0 or more starts" in capsys.readouterr().err
    assert main(["bench", "serve", str(run_dir), "--server-tree", str(tmp_path)]) == 2
    assert "no sync4d package there" in capsys.readouterr().err
