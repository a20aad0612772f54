"""``sync4d bench serve RUN``: `sync4d serve` under agents' load (docs/mcp.md, "Load").

Two measurements, both through the official MCP SDK's client, against the server run as its
own process (``python -m sync4d serve``), as agents meet it:

* **The first call.** `--starts` times the server is started over stdio and asked `describe`
  at once: from the process start to the ``initialize`` answer, from that answer to the
  description, and the second `describe`. The first start uses an empty description cache
  (``$SYNC4D_SERVE_CACHE`` in a temporary folder: the description is built while the client
  connects), the later ones find it kept (`sync4d.serve.cache`).
* **The load.** The server over streamable HTTP (a free loopback port) and `--clients`
  concurrent clients, each its own MCP session, each making `--calls` calls in turn: a mix of
  `query` (a text naming an object, or one with a motion state), a relational `query` ("the
  ball that lands first"), `track`, `events` and `render`, in equal shares, shuffled per
  client, the arguments drawn from the run's own objects and cameras (seeded). Every answer is
  checked for its shape (an error result, an exception or a malformed answer is an error);
  the latency of each call is timed at the client, from the request to the answer read.
  Before the clock starts, one client asks `describe`, every query text once and one render
  (not timed: the run loaded, the texts encoded), so the load measures the steady state.

Prints a table (p50 and p95 per tool and overall, nearest rank) and writes a JSON record with
the date, the command and the machine; exits 1 when any call failed. The run folder is only
read.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime as _dt
import json
import math
import os
import platform
import random
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from sync4d.options import add_threads, positive_int
from sync4d.report import align_table

__all__ = ["DEFAULT_RELATIONAL", "KINDS", "add_arguments", "bench_serve", "main", "percentile"]

#: The kinds of call each client makes, in equal shares.
KINDS = ("query", "relational", "track", "events", "render")
#: Relational questions asked by default (bouncingballs' kind: objects that land and bounce).
DEFAULT_RELATIONAL = ("the ball that lands first", "which ball lands last",
                      "the second ball to land", "the ball with the longest contact")  # fmt: skip
#: Seconds a client waits for one answer.
CALL_TIMEOUT_S = 300.0


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench serve``."""
    p.description = (
        "Start `sync4d serve RUN` and time it as agents meet it: the first describe after a "
        "start over stdio, then concurrent MCP clients over streamable HTTP making a mix of "
        "query, relational query, track, events and render calls; prints p50/p95 per tool "
        "and writes a JSON."
    )
    p.add_argument("run", metavar="RUN", help="run folder with its language field (fit "
                   "--phases 3)")  # fmt: skip
    p.add_argument("--clients", type=positive_int, default=16, metavar="N",
                   help="concurrent MCP clients over HTTP (default 16)")
    p.add_argument("--calls", type=positive_int, default=20, metavar="N",
                   help="calls each client makes (default 20)")
    p.add_argument("--starts", type=int, default=3, metavar="N",
                   help="stdio starts timed for the first describe, the first with an empty "
                   "description cache (default 3; 0: none)")  # fmt: skip
    p.add_argument("--queries", nargs="+", default=None, metavar="TEXT",
                   help="the query texts (default: 'the NAME' and 'the NAME while it is "
                   "falling' for each object)")  # fmt: skip
    p.add_argument("--relational", nargs="+", default=None, metavar="TEXT",
                   help="the relational questions (default: "
                   + "; ".join(f"'{q}'" for q in DEFAULT_RELATIONAL) + ")")
    p.add_argument("--seed", type=int, default=0, help="seed of the calls' order and "
                   "arguments (default 0)")  # fmt: skip
    p.add_argument("--server-tree", default=None, metavar="DIR",
                   help="run the server from the sync4d package in DIR (DIR/sync4d: another "
                   "checkout, e.g. the last release, for a before/after comparison)")
    p.add_argument("--note", default=None, metavar="TEXT",
                   help="a note kept in the record (e.g. that other work shared the machine)")
    p.add_argument("--out", default="bench-serve.json", metavar="FILE.json",
                   help="results JSON (default bench-serve.json)")
    add_threads(p, "the server's torch and rasterizer")


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------

def percentile(values: list[float], q: float) -> float:
    """The nearest-rank `q`-th percentile (0 < q <= 100) of `values` (not empty)."""
    xs = sorted(values)
    return xs[max(0, math.ceil(q / 100.0 * len(xs)) - 1)]


def _summary(ms: list[float], errors: int) -> dict[str, float | int]:
    """n, errors, p50, p95 and max (ms) of latencies `ms`."""
    if not ms:
        return {"n": 0, "errors": errors}
    return {"n": len(ms), "errors": errors, "p50_ms": percentile(ms, 50),
            "p95_ms": percentile(ms, 95), "max_ms": max(ms)}  # fmt: skip


# --------------------------------------------------------------------------------------------
# The server as a process
# --------------------------------------------------------------------------------------------

def _env(cache: Path, threads: int | None, tree: Path | None = None) -> dict[str, str]:
    """The server's environment: the temporary description cache (`sync4d.serve.cache`; the
    rest of sync4d's cache, the encoders', is the user's), the thread counts, and the other
    sync4d `tree` first on the path (the server also starts in it)."""
    env = {"SYNC4D_SERVE_CACHE": str(cache)}
    if threads:
        env |= {"OMP_NUM_THREADS": str(threads), "RAYON_NUM_THREADS": str(threads)}
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    return env


def _serve_args(run: Path, threads: int | None) -> list[str]:
    return ["-m", "sync4d", "serve", str(run), *(["--threads", str(threads)] if threads else [])]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rss_mb(pid: int) -> float | None:
    """Resident memory of process `pid` in MiB (Linux's /proc), None elsewhere."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


async def _first_describe(run: Path, threads: int | None, cache: Path,
                          tree: Path | None = None) -> dict[str, float]:  # fmt: skip
    """One stdio start: seconds to the ``initialize`` answer, from it to the first `describe`,
    from the start to it, and the second `describe`'s."""
    from mcp import Client
    from mcp.client.stdio import StdioServerParameters

    params = StdioServerParameters(command=sys.executable, args=_serve_args(run, threads),
                                   env=_env(cache, threads, tree),
                                   cwd=str(tree) if tree else None)  # fmt: skip
    t0 = time.perf_counter()
    async with Client(params, read_timeout_seconds=CALL_TIMEOUT_S) as client:
        t1 = time.perf_counter()
        first = await client.call_tool("describe", {})
        t2 = time.perf_counter()
        await client.call_tool("describe", {})
        t3 = time.perf_counter()
    if first.is_error:
        raise RuntimeError(f"describe answered an error: {first.content[0]}")
    return {"initialize_s": t1 - t0, "describe_after_initialize_s": t2 - t1,
            "describe_from_start_s": t2 - t0, "second_describe_s": t3 - t2}  # fmt: skip


# --------------------------------------------------------------------------------------------
# The load
# --------------------------------------------------------------------------------------------

#: A planned call: its kind (of `KINDS`), the tool and its arguments.
Call = tuple[str, str, dict]


def plan_calls(kinds: int, calls: int, rng: random.Random, names: list[str], tests: int,
               queries: list[str], relational: list[str]) -> list[Call]:  # fmt: skip
    """One client's `calls` calls as (kind, tool, arguments): the `KINDS` (the first `kinds`)
    in equal shares, shuffled; objects from `names`, cameras among `tests` test cameras."""
    order = [KINDS[i % kinds] for i in range(calls)]
    rng.shuffle(order)
    out = []
    for kind in order:
        a, b = sorted(round(rng.uniform(0.0, 1.0), 3) for _ in range(2))
        if kind == "query":
            out.append((kind, "query", {"text": rng.choice(queries)}))
        elif kind == "relational":
            out.append((kind, "query", {"text": rng.choice(relational)}))
        elif kind == "track":
            out.append((kind, "track", {"object": rng.choice(names), "t0": a, "t1": b}))
        elif kind == "events":
            args: dict[str, Any] = {"t0": a, "t1": b}
            if rng.random() < 0.5:
                args["object"] = rng.choice(names)
            out.append((kind, "events", args))
        else:
            cam = f"test:{rng.randrange(tests)}" if tests else None
            out.append((kind, "render", {"t": round(rng.uniform(0.0, 1.0), 3), "camera": cam}))
    return out


def check_answer(kind: str, result: Any, names: list[str]) -> str | None:
    """Why `result` (a `CallToolResult`) is not a well-formed answer of `kind`, or None."""
    if result.is_error:
        text = result.content[0].text if result.content else ""
        return f"error result: {text}"
    sc = result.structured_content
    if kind in ("query", "relational"):
        if not isinstance(sc, dict) or not sc.get("objects") or "answer" not in sc:
            return "a query answer without 'objects' and 'answer'"
        ans = sc["answer"]
        if ans is not None and (ans.get("name") not in names
                                or not isinstance(ans.get("intervals"), list)):  # fmt: skip
            return f"a query answer naming no object of the run: {ans!r}"[:200]
        if ans is None and not sc.get("refusal"):
            return "a query answer with neither an object nor a refusal"
    elif kind == "track":
        if not isinstance(sc, dict) or sc.get("object", {}).get("name") not in names:
            return "a track without its object"
        frames = sc.get("frames")
        if not frames or any(len(f.get("position", ())) != 3 for f in frames):
            return "a track without frames of 3-D positions"
    elif kind == "events":
        if not isinstance(sc, dict) or not isinstance(sc.get("events"), list) \
                or not isinstance(sc.get("segments"), list):  # fmt: skip
            return "an events answer without 'events' and 'segments' lists"
    elif kind == "render":
        parts = result.content
        if len(parts) != 2 or parts[0].type != "image" or parts[0].mime_type != "image/png":
            return "a render without its PNG"
        info = json.loads(parts[1].text)
        if not (info.get("width", 0) > 0 and info.get("height", 0) > 0):
            return "a render without its size"
    return None


async def _client(url: str, plan: list[Call], names: list[str],
                  start: asyncio.Event) -> list[dict]:  # fmt: skip
    """One MCP session over `url` making the calls of `plan` in turn once `start` is set;
    each call's kind, latency (ms) and problem (None: a good answer)."""
    from mcp import Client

    rows = []
    async with Client(url, read_timeout_seconds=CALL_TIMEOUT_S) as client:
        await start.wait()
        for kind, tool, args in plan:
            t0 = time.perf_counter()
            try:
                result = await client.call_tool(tool, args)
                ms = 1000.0 * (time.perf_counter() - t0)
                problem = check_answer(kind, result, names)
            except Exception as e:  # noqa: BLE001 - a failed call is counted, not raised
                ms = 1000.0 * (time.perf_counter() - t0)
                problem = f"{type(e).__name__}: {e}"
            rows.append({"kind": kind, "tool": tool, "args": args, "ms": ms,
                         "problem": problem})  # fmt: skip
    return rows


async def _until(connect: Callable[[], Awaitable[Any]], proc: subprocess.Popen,
                 seconds: float = 300.0) -> Any:
    """`connect()`'s answer once the server listens (it prints its address just before)."""
    deadline = time.monotonic() + seconds
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited with status {proc.returncode}")
        try:
            return await connect()
        except Exception:  # noqa: BLE001 - not listening yet
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


async def _load(url: str, proc: subprocess.Popen, clients: int, calls: int, seed: int,
                queries: list[str] | None, relational: list[str]) -> dict:  # fmt: skip
    """The load on the server at `url` (see the module notes)."""
    from mcp import Client

    async def describe() -> dict:
        async with Client(url, read_timeout_seconds=CALL_TIMEOUT_S) as c:
            r = await c.call_tool("describe", {})
        if r.is_error:
            raise RuntimeError(f"describe answered an error: {r.content[0].text}")
        return dict(r.structured_content or {})

    t_wait = time.perf_counter()
    d = await _until(describe, proc)
    ready_s = time.perf_counter() - t_wait
    names = [o["name"] for o in d["objects"]]
    tests = int(d["cameras"].get("test", 0))
    texts = queries or [t for n in names for t in (f"the {n}", f"the {n} while it is falling")]
    # warm-up, not timed: the run (torch) loaded and every text encoded once, so the load
    # measures the steady state (the first calls are the first-describe measurement's)
    t_warm = time.perf_counter()
    async with Client(url, read_timeout_seconds=CALL_TIMEOUT_S) as c:
        for text in [*texts, *relational]:
            await c.call_tool("query", {"text": text})
        await c.call_tool("render", {"t": 0.5})
    warmup_s = time.perf_counter() - t_warm
    rng = random.Random(seed)
    plans = [plan_calls(len(KINDS), calls, rng, names, tests, texts, relational)
             for _ in range(clients)]  # fmt: skip
    rss0 = _rss_mb(proc.pid)
    start = asyncio.Event()
    tasks = [asyncio.create_task(_client(url, plan, names, start)) for plan in plans]
    await asyncio.sleep(0)  # let the sessions open before the clock starts
    t0 = time.perf_counter()
    start.set()
    results = await asyncio.gather(*tasks, return_exceptions=True)
    wall = time.perf_counter() - t0
    rows: list[dict] = []
    for i, r in enumerate(results):
        if isinstance(r, BaseException):  # the session itself failed: every call counts
            rows += [{"kind": k, "tool": tool, "args": a, "ms": float("nan"),
                      "problem": f"client {i}: {type(r).__name__}: {r}"}
                     for k, tool, a in plans[i]]  # fmt: skip
        else:
            rows += r
    per_tool = {}
    for kind in KINDS:
        mine = [r for r in rows if r["kind"] == kind]
        per_tool[kind] = _summary([r["ms"] for r in mine if r["problem"] is None],
                                  sum(r["problem"] is not None for r in mine))  # fmt: skip
    good = [r["ms"] for r in rows if r["problem"] is None]
    errors = [r for r in rows if r["problem"] is not None]
    return {
        "ready_s": ready_s, "warmup_s": warmup_s, "objects": names, "test_cameras": tests,
        "queries": texts, "relational": relational, "per_tool": per_tool,
        "overall": _summary(good, len(errors)), "errors": len(errors),
        "error_examples": [{"tool": r["tool"], "args": r["args"], "problem": r["problem"]}
                           for r in errors[:10]],
        "wall_s": wall, "calls_per_s": len(rows) / wall if wall > 0 else None,
        "server_rss_mb": {"before": rss0, "after": _rss_mb(proc.pid)},
    }  # fmt: skip


def bench_serve(run: Path, clients: int, calls: int, starts: int, threads: int | None,
                seed: int = 0, queries: list[str] | None = None,
                relational: list[str] | None = None, tree: Path | None = None) -> dict:  # fmt: skip
    """Both measurements of the module notes on run folder `run`, as a dict; `tree`: a folder
    holding another sync4d package to serve with."""
    run = run.resolve()  # the server may start in `tree`
    out: dict[str, Any] = {"run": str(run), "threads": threads, "clients": clients,
                           "calls": calls, "seed": seed,
                           "server_tree": str(tree) if tree else None}  # fmt: skip
    with tempfile.TemporaryDirectory(prefix="sync4d-bench-serve-") as tmp:
        cache = Path(tmp)
        firsts = [asyncio.run(_first_describe(run, threads, cache, tree)) for _ in range(starts)]
        if firsts:
            kept = firsts[1:]
            out["first_describe"] = {
                "built": firsts[0], "kept": kept,
                "kept_median": {k: statistics.median(f[k] for f in kept)
                                for k in firsts[0]} if kept else None,
            }  # fmt: skip
        port = _free_port()
        log = cache / "serve.log"
        with log.open("w") as err:
            proc = subprocess.Popen(
                [sys.executable, *_serve_args(run, threads), "--http", f"127.0.0.1:{port}"],
                env={**os.environ, **_env(cache, threads, tree)}, stdout=subprocess.DEVNULL,
                stderr=err, cwd=tree,
            )  # fmt: skip
        try:
            url = f"http://127.0.0.1:{port}/mcp"
            out["load"] = asyncio.run(_load(url, proc, clients, calls, seed, queries,
                                            list(relational or DEFAULT_RELATIONAL)))  # fmt: skip
        except RuntimeError as e:
            tail = log.read_text(errors="replace").strip().splitlines()[-3:]
            raise RuntimeError(f"{e} ({' / '.join(tail) or 'no output'})") from None
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    return out


def _machine() -> dict[str, Any]:
    """What ran it: host, platform, processor, CPUs and the load average at the start."""
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {"node": platform.node(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
            "load_average": list(load) if load else None}  # fmt: skip


def _command() -> str:
    """The command line that ran this, as typed."""
    return " ".join(["sync4d", *sys.argv[1:]])


def main(args: argparse.Namespace) -> int:
    """Run `bench serve` with parsed `args`; the exit status (1 when a call failed)."""
    run = Path(args.run)
    if not run.is_dir():
        print(f"bench serve: {run}: no such run folder; give a run folder written by "
              "`sync4d fit DATA --out RUN --phases 3`", file=sys.stderr)  # fmt: skip
        return 2
    if args.starts < 0:
        print(f"bench serve: --starts {args.starts}: give 0 or more starts", file=sys.stderr)
        return 2
    machine = _machine()
    tree = Path(args.server_tree).resolve() if args.server_tree else None
    if tree is not None and not (tree / "sync4d" / "__init__.py").is_file():
        print(f"bench serve: --server-tree {tree}: no sync4d package there; give the folder "
              "that holds sync4d/", file=sys.stderr)  # fmt: skip
        return 2
    try:
        res = bench_serve(run, args.clients, args.calls, args.starts, args.threads, args.seed,
                          args.queries, args.relational, tree)  # fmt: skip
    except (RuntimeError, OSError) as e:
        print(f"bench serve: {e}", file=sys.stderr)
        return 2
    record = {"date": _dt.datetime.now().isoformat(timespec="seconds"),
              "command": _command(), "machine": machine, "note": args.note,
              **res}  # fmt: skip
    out = Path(args.out)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print_table(record)
    print(f"wrote {out}")
    return 1 if record["load"]["errors"] else 0


def print_table(record: dict) -> None:
    """The record's table: the first describe, then p50/p95 per tool and overall."""
    first = record.get("first_describe")
    if first:
        b, k = first["built"], first["kept_median"]
        print(f"first describe over stdio: {b['describe_after_initialize_s']:.2f} s after "
              f"initialize ({b['describe_from_start_s']:.2f} s from start) with the "
              "description built at start"
              + (f"; {k['describe_after_initialize_s']:.2f} s ({k['describe_from_start_s']:.2f} "
                 f"s from start) with it kept, median of {len(first['kept'])}" if k else ""))
    load = record["load"]
    rows = []
    for name, r in [*load["per_tool"].items(), ("overall", load["overall"])]:
        if r["n"]:
            rows.append([name, str(r["n"]), str(r["errors"]), f"{r['p50_ms']:.0f}",
                         f"{r['p95_ms']:.0f}", f"{r['max_ms']:.0f}"])  # fmt: skip
        else:
            rows.append([name, "0", str(r["errors"]), "-", "-", "-"])
    print(f"{record['clients']} clients x {record['calls']} calls over streamable HTTP on "
          f"{record['run']}: {load['wall_s']:.1f} s, {load['calls_per_s']:.1f} calls/s, "
          f"{load['errors']} errors")  # fmt: skip
    print(align_table(["tool", "n", "errors", "p50 ms", "p95 ms", "max ms"], rows, left=(0,)))
    for e in load["error_examples"]:
        print(f"  error: {e['tool']} {json.dumps(e['args'])}: {e['problem']}")
