"""`sync4d serve` as an agent meets it: the server started as a subprocess and driven by the
official MCP SDK's own client, over stdio (as a desktop client starts it) and over HTTP
(streamable HTTP and SSE), on the oracle run of the embedded scene (true motion, so the answers
can be checked against the truth): the tools listed with their schemas, a query answered right,
the description, a track, the events and a render checked, the resources equal to what
`export` writes, and one clear error result for each argument a caller can get wrong."""

from __future__ import annotations

import asyncio
import dataclasses
import io
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcp import Client, ClientSession
from mcp.client.sse import sse_client
from mcp.client.stdio import StdioServerParameters
from PIL import Image

from support import ROOT
from support.oracle import oracle_run_folder
from support.ports import free_port
from sync4d.cli import main
from sync4d.commands.serve import parse_address
from sync4d.data import synthetic as syn
from sync4d.phase3.query import query as run_query

QUERIES = ("the red ball", "the blue box")
TOOLS = {"describe", "query", "track", "events", "render"}
ENV = {"OMP_NUM_THREADS": "1", "RAYON_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """The oracle Phase 2 run with its field (colour encoder; the queries' texts cached)."""
    return oracle_run_folder(tmp_path_factory.mktemp("serve"), QUERIES)


def _stdio(run: Path, *extra: str) -> Client:
    """A client of `python -m sync4d serve RUN [extra]` over stdio."""
    env = {**ENV, "SYNC4D_SERVE_CACHE": os.environ["SYNC4D_SERVE_CACHE"]}  # conftest.py
    params = StdioServerParameters(command=sys.executable,
                                   args=["-m", "sync4d", "serve", str(run), "--threads", "1",
                                         *extra], env=env)  # fmt: skip
    return Client(params, read_timeout_seconds=120)


def _error(result) -> str:
    assert result.is_error, result
    return result.content[0].text


def test_the_sdk_client_lists_the_tools_and_gets_right_answers(run_dir, tmp_path):
    async def session() -> dict:
        out: dict = {}
        async with _stdio(run_dir) as c:
            out["tools"] = {t.name: t for t in (await c.list_tools()).tools}
            call = c.call_tool
            out["red"] = await call("query", {"text": "the red ball"})
            out["blue"] = await call("query", {"text": "the blue box", "scorer": "static",
                                               "timeline": True})  # fmt: skip
            out["describe"] = await call("describe", {})
            out["full"] = await call("describe", {"full": True})
            out["track"] = await call("track", {"object": "red ball", "t0": 0.2, "t1": 0.3})
            out["one"] = await call("track", {"object": 2, "t0": 0.51, "t1": 0.52})
            out["events"] = await call("events", {"object": "the red ball"})
            out["contacts"] = await call("events", {"kind": "contact", "t0": 0.8})
            out["render"] = await call("render", {"t": 0.5})
            out["render_train"] = await call("render", {"t": 0.5, "camera": "train:1"})
            out["render_int"] = await call("render", {"t": 0.5, "camera": 0})
            out["resources"] = (await c.list_resources()).resources
            out["scene"] = (await c.read_resource("sync4d://scene.json")).contents[0].text
            out["prompt"] = (await c.read_resource("sync4d://prompt.txt")).contents[0].text
            out["errors"] = [
                await call("track", {"object": "purple cat"}),
                await call("track", {"object": "red ball", "t0": 0.7, "t1": 0.2}),
                await call("render", {"t": 1.5}),
                await call("render", {"t": 0.5, "camera": "test:99"}),
                await call("events", {"kind": "jumping"}),
                await call("query", {"text": "the red ball", "scorer": "best"}),
                await call("query", {"text": "  "}),
            ]
        return out

    out = asyncio.run(session())
    tools = out["tools"]
    assert set(tools) == TOOLS
    for name in TOOLS - {"render"}:  # typed results: an output schema for each
        assert tools[name].output_schema["type"] == "object", name
    assert "object" in tools["track"].input_schema["required"]
    assert set(tools["query"].output_schema["required"]) >= {"query", "answer", "objects"}
    scorer = tools["query"].input_schema["properties"]["scorer"]
    assert "full" in json.dumps(scorer) and "static" in json.dumps(scorer)

    # query: the answer `sync4d query` gives, and the right one
    red = out["red"].structured_content
    assert not out["red"].is_error and red["answer"]["name"] == "red ball"
    same = run_query(run_dir, "the red ball")
    assert [o["name"] for o in red["objects"]] == [o["name"] for o in same["objects"]]
    assert red["answer"]["intervals"] == same["objects"][0]["intervals"]
    blue = out["blue"].structured_content
    assert blue["answer"]["name"] == "blue box" and blue["scorer"] == "static"
    assert len(blue["timeline"]["times"]) == len(blue["timeline"]["blue box"]) == 21

    # describe: the objects, frames, what they do, the prompt
    d = out["describe"].structured_content
    assert [o["name"] for o in d["objects"]] == ["red ball", "blue box", "green pillar"]
    assert d["frames"] == {"count": 21, "t0": 0.0, "t1": 1.0} and d["scene"] is None
    assert d["cameras"]["test"] > 0 and d["resources"] == ["sync4d://scene.json",
                                                           "sync4d://prompt.txt"]  # fmt: skip
    assert d["prompt"] == out["prompt"] and "red ball (id 1)" in d["prompt"]
    ball = d["objects"][0]
    assert {s["state"] for s in ball["segments"]} >= {"moving", "rising", "falling"}
    pillar = d["objects"][2]
    assert [s["state"] for s in pillar["segments"]] == ["at rest"]
    assert len(out["full"].structured_content["scene"]["tracks"]) == 3

    # track: every stored frame in [0.2, 0.3], where the ball truly is (oracle motion)
    tr = out["track"].structured_content
    assert tr["object"] == {"id": 1, "name": "red ball"} and tr["note"] is None
    assert [f["t"] for f in tr["frames"]] == pytest.approx([0.2, 0.25, 0.3])
    for f in tr["frames"]:
        truth = syn.object_poses(f["t"])[1][1]
        assert np.allclose(f["position"], truth, atol=0.05), (f["t"], f["position"], truth)
        assert f["speed"] == pytest.approx(np.linalg.norm(f["velocity"]))
        assert f["speed"] > 0.2 and len(f["rotation"]) == 4
        assert np.all(np.asarray(f["box_min"]) < np.asarray(f["box_max"]))
    one = out["one"].structured_content  # no stored frame inside: the nearest one, said so
    assert one["object"]["name"] == "blue box" and len(one["frames"]) == 1
    assert one["frames"][0]["t"] == pytest.approx(0.5) and "nearest frame" in one["note"]

    # events: the ball's (the ground is object 0, "background"); segments of the ball alone
    ev = out["events"].structured_content
    assert ev["events"] and all(1 in e["objects"] for e in ev["events"])
    assert any(e["kind"] == "contact" and e["names"] == ["red ball", "background"]
               for e in ev["events"])  # fmt: skip
    assert ev["segments"] and {s["name"] for s in ev["segments"]} == {"red ball"}
    rising = next(s for s in ev["segments"] if s["state"] == "rising")
    assert syn.object_poses(rising["t1"])[1][1][2] > syn.object_poses(rising["t0"])[1][1][2]
    late = out["contacts"].structured_content
    assert late["events"] and all(e["kind"] == "contact" and e["t1"] >= 0.8
                                  for e in late["events"])  # fmt: skip
    assert late["segments"] == []  # "contact" is no motion state

    # render: a PNG of the camera's size, with the scene in it; another camera, another image
    img, info = out["render"].content
    assert img.type == "image" and img.mime_type == "image/png"
    meta = json.loads(info.text)
    assert meta["split"] == "test" and meta["t"] == 0.5
    import base64

    pixels = np.asarray(Image.open(io.BytesIO(base64.b64decode(img.data))).convert("RGB"))
    assert pixels.shape == (meta["height"], meta["width"], 3) and pixels.std() > 5
    other = out["render_train"].content[0]
    assert json.loads(out["render_train"].content[1].text)["split"] == "train"
    assert other.data != img.data
    assert out["render_int"].content[0].data == img.data  # camera 0: the first test camera

    # resources: what `sync4d export --scene --prompt` writes, byte for byte
    assert {str(r.uri) for r in out["resources"]} == {"sync4d://scene.json",
                                                      "sync4d://prompt.txt"}  # fmt: skip
    assert main(["export", str(run_dir), "--scene", str(tmp_path / "scene.json"), "--prompt",
                 str(tmp_path / "prompt.txt"), "--threads", "1"]) == 0  # fmt: skip
    assert out["scene"] == (tmp_path / "scene.json").read_text()
    assert out["prompt"] == (tmp_path / "prompt.txt").read_text()

    # one clear error result per mistake
    messages = [_error(r) for r in out["errors"]]
    assert "unknown object 'purple cat'" in messages[0] and "1 (red ball)" in messages[0]
    assert "t0 = 0.7 is after t1 = 0.2" in messages[1]
    assert "t = 1.5 is out of range" in messages[2]
    assert "camera 'test:99'" in messages[3] and "test and" in messages[3]
    assert "unknown kind 'jumping'" in messages[4] and "contact" in messages[4]
    assert "best" in messages[5] and "'paper'" in messages[5]  # the schema's choices
    assert "empty query" in messages[6]


def test_a_run_without_a_field_says_which_command_builds_it(run_dir, tmp_path):
    bare = tmp_path / "bare"
    shutil.copytree(run_dir, bare, ignore=shutil.ignore_patterns("phase3"))

    async def session():
        async with _stdio(bare) as c:
            try:
                await c.read_resource("sync4d://scene.json")
                refused = ""
            except Exception as e:  # noqa: BLE001 - the SDK's protocol error
                refused = str(e)
            return (await c.call_tool("query", {"text": "the red ball"}),
                    await c.call_tool("describe", {}),
                    await c.call_tool("render", {"t": 0.25}), refused)  # fmt: skip

    q, d, r, refused = asyncio.run(session())
    for msg in (_error(q), _error(d), refused):
        assert "no language field" in msg and f"fit --out {bare} --phases 3" in msg
    assert not r.is_error and r.content[0].type == "image"  # renders need no field


@pytest.mark.parametrize("sse", [False, True], ids=["streamable-http", "sse"])
def test_serve_over_http(run_dir, sse):
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "sync4d", "serve", str(run_dir), "--http", str(port),
         *(["--sse"] if sse else [])],
        env={**os.environ, **ENV}, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        url = f"http://127.0.0.1:{port}/{'sse' if sse else 'mcp'}"
        assert url in line, (line, proc.stderr.read() if proc.poll() is not None else "")

        async def ask(session) -> tuple[set[str], object]:
            names = {t.name for t in (await session.list_tools()).tools}
            return names, await session.call_tool("query", {"text": "the red ball"})

        async def connect():
            if not sse:
                async with Client(url, read_timeout_seconds=120) as c:
                    return await ask(c)
            async with sse_client(url) as (read, write), ClientSession(read, write) as c:
                await c.initialize()
                return await ask(c)

        async def session():
            for _ in range(100):  # the address is printed just before uvicorn listens
                try:
                    return await connect()
                except Exception:  # noqa: BLE001 - not listening yet
                    await asyncio.sleep(0.2)
            raise AssertionError("the HTTP server never answered")

        names, ans = asyncio.run(session())
        assert names == TOOLS and ans.structured_content["answer"]["name"] == "red ball"
    finally:
        proc.terminate()
        assert proc.wait(timeout=30) == 0  # SIGTERM stops it as Ctrl-C does
    assert "serve: stopped" in proc.stderr.read()


def test_refusals_before_serving(run_dir, tmp_path, capsys):
    assert main(["serve", str(tmp_path / "nope")]) == 2
    assert "no such run folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["serve", str(tmp_path / "empty")]) == 2
    assert "no checkpoint.safetensors" in capsys.readouterr().err
    assert main(["serve", str(run_dir), "--sse"]) == 2
    assert "add --http" in capsys.readouterr().err
    assert main(["serve", str(run_dir), "--http", "local:host"]) == 2
    assert "PORT or HOST:PORT" in capsys.readouterr().err
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["serve", str(run_dir), "--http", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"port {port} on 127.0.0.1 is in use" in err and "--http" in err


def test_describe_names_the_4dgs_file(run_dir, tmp_path, capsys):
    """`serve RUN --4dgs FILE`: `describe` (over stdio, as an agent asks it) names the .4dgs
    file exported from the run; one of another checkpoint, or no .4dgs, is refused at start."""
    pytest.importorskip("fourdgs", reason="needs fourdgs (pip install 'sync4d[4dgs]')")
    out = tmp_path / "run.4dgs"
    assert main(["export", str(run_dir), "--4dgs", str(out), "--threads", "1"]) == 0
    capsys.readouterr()

    async def session() -> dict:
        async with _stdio(run_dir, "--4dgs", str(out)) as c:
            return (await c.call_tool("describe", {})).structured_content

    files = asyncio.run(session())["files"]
    assert len(files) == 1 and files[0]["format"] == "4dgs"
    assert files[0]["path"] == str(out.resolve()) and files[0]["bytes"] == out.stat().st_size
    assert files[0]["objects"] == ["background", "red ball", "blue box", "green pillar"]
    assert files[0]["tracks"] == 3 and files[0]["embeddings"] == "test-colour"
    done = subprocess.run(  # the example, as a user runs it with FOURDGS set
        ["sh", str(ROOT / "examples" / "serve.sh"), str(run_dir), "the red ball"],
        capture_output=True, text=True, cwd=tmp_path, timeout=300,
        env={**os.environ, **ENV, "PYTHON": sys.executable, "FOURDGS": str(out)})  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert f"file: {out.resolve()} (4dgs" in done.stdout
    other = tmp_path / "other"
    shutil.copytree(run_dir, other)
    with open(other / "checkpoint.safetensors", "ab") as f:  # another checkpoint's bytes
        f.write(b" ")
    assert main(["serve", str(other), "--4dgs", str(out)]) == 2
    assert "written from another checkpoint" in capsys.readouterr().err
    (tmp_path / "not.4dgs").write_bytes(b"PLY junk")
    assert main(["serve", str(run_dir), "--4dgs", str(tmp_path / "not.4dgs")]) == 2
    assert "not a readable .4dgs file" in capsys.readouterr().err
    assert main(["serve", str(run_dir), "--4dgs", str(tmp_path / "missing.4dgs")]) == 2
    assert "no such file; write it with `sync4d export RUN --4dgs" in capsys.readouterr().err
    from sync4d.export.fourdgs import write_4dgs
    from sync4d.runs import load_run

    run = load_run(run_dir)  # a .4dgs with no checkpoint hash: not written by `export` on a run
    foreign = write_4dgs(tmp_path / "foreign.4dgs", dataclasses.replace(
        run, checkpoint=tmp_path / "nowhere.safetensors"))  # fmt: skip
    assert main(["serve", str(run_dir), "--4dgs", str(foreign.path)]) == 2
    assert "not written by sync4d export" in capsys.readouterr().err


def test_addresses():
    assert parse_address("8000") == ("127.0.0.1", 8000)
    assert parse_address("0.0.0.0:9000") == ("0.0.0.0", 9000)
    assert parse_address("[::1]:9000") == ("::1", 9000)
    for bad in ("0", "70000", "host:", "x"):
        with pytest.raises(ValueError, match="PORT or HOST:PORT"):
            parse_address(bad)


def test_startup_and_queries_import_no_torch(run_dir):
    """The server starts and answers queries without torch (renders and the description
    load it on first use)."""
    code = ("import sys\n"
            "import sync4d.commands.serve, sync4d.serve.server\n"
            "from sync4d.serve import RunTools, build_server\n"
            f"tools = RunTools({str(run_dir)!r})\n"
            "build_server(tools)\n"
            "assert tools.query('the red ball')['answer']['name'] == 'red ball'\n"
            "assert 'torch' not in sys.modules, 'torch imported'\n")  # fmt: skip
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env={**os.environ, **ENV}, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr


def test_the_example_drives_the_server(run_dir, tmp_path):
    """examples/serve.sh: the SDK's client over stdio, as a user runs it."""
    done = subprocess.run(
        ["sh", str(ROOT / "examples" / "serve.sh"), str(run_dir), "the red ball"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
        env={**os.environ, **ENV, "PYTHON": sys.executable},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "tools: describe, query, track, events, render" in done.stdout
    assert "query 'the red ball': red ball" in done.stdout and "contact" in done.stdout
    assert Image.open(tmp_path / "serve-render.png").size == (48, 48)
