"""``sync4d bench view RUN``: how fast the viewer answers the time slider.

Serves the run on a viser server (a free loopback port) and moves the time, as the slider
does, to `--moves` times drawn uniformly in [0, 1]: each move deforms the Gaussians (D_theta),
builds the covariances and colours, and sends every object's splats (viser serialises them
for the page, which it does whether or not a browser is connected; the socket write to a
browser is not included). Timed from the change to the splats sent: a new time (nothing
cached), and the same times again (served from the viewer's per-time cache). Also times
asking a query. Prints a table and writes a JSON with the date, machine and threads.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import platform
import socket
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from sync4d.errors import Sync4dError
from sync4d.options import add_threads, positive_int
from sync4d.report import align_table

__all__ = ["add_arguments", "bench_view", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench view`` (`sync4d.cli`)."""
    p.description = (
        "Serve a run in the viewer and time slider moves to new and to cached times (from the "
        "change to the splats sent) and a query; prints a table and writes a JSON."
    )
    p.add_argument("run", metavar="RUN", help="run folder")
    p.add_argument("--moves", type=positive_int, default=30, metavar="N",
                   help="slider moves to time (default 30)")
    p.add_argument("--query", default="the red ball", metavar="TEXT",
                   help="a query to time too, when the run has a field (default: the red ball)")
    p.add_argument("--out", default="bench-view.json", metavar="FILE.json",
                   help="results JSON (default bench-view.json)")
    add_threads(p, "torch")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _stats(xs: list[float]) -> dict:
    ms = sorted(1000.0 * x for x in xs)
    return {"n": len(ms), "median_ms": statistics.median(ms),
            "p90_ms": ms[min(len(ms) - 1, int(0.9 * len(ms)))], "max_ms": ms[-1]}  # fmt: skip


def bench_view(run_dir: Path, moves: int, query: str | None, threads: int | None) -> dict:
    """Slider latencies (uncached and cached) and a query's latency on `run_dir`."""
    import torch
    import viser

    from sync4d.viewer.app import Viewer
    from sync4d.viewer.state import ViewerState

    if threads:
        torch.set_num_threads(threads)
    t0 = time.perf_counter()
    state = ViewerState(run_dir)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    try:
        viewer = Viewer(server, state, threads=threads)
        open_s = time.perf_counter() - t0
        times = np.random.default_rng(0).uniform(0.0, 1.0, moves)
        cold, warm = [], []
        for t in times:
            viewer.t = float(t)
            cold.append(viewer.update())
        for t in times:
            viewer.t = float(t)
            warm.append(viewer.update())
        ask = None
        if query and state.field is not None:
            t1 = time.perf_counter()
            state.ask(query)
            ask = time.perf_counter() - t1
        viewer.stop()
    finally:
        server.stop()
    return {
        "run": str(run_dir), "gaussians": state.run.model.num_gaussians,
        "objects": len(state.objects), "open_s": open_s,
        "new_time": _stats(cold), "cached_time": _stats(warm),
        "query": query, "query_s": ask,
    }  # fmt: skip


def main(args: argparse.Namespace) -> int:
    """Run `bench view` with parsed `args`; the exit status."""
    try:
        res = bench_view(Path(args.run), args.moves, args.query, args.threads)
    except Sync4dError as e:
        print(f"bench view: {e}", file=sys.stderr)
        return e.exit_code
    except ImportError as e:
        print(f"bench view: {e}", file=sys.stderr)
        return 2
    rows = [[name, str(r["n"]), f"{r['median_ms']:.1f}", f"{r['p90_ms']:.1f}",
             f"{r['max_ms']:.1f}"] for name, r in (("new time", res["new_time"]),
                                                   ("cached time", res["cached_time"]))]
    print(f"bench view: {res['run']} ({res['gaussians']:,} Gaussians, {res['objects']} "
          f"objects), viewer ready in {res['open_s']:.2f} s")  # fmt: skip
    print(align_table(["slider move", "n", "median ms", "p90 ms", "max ms"], rows, left=(0,)))
    if res["query_s"] is not None:
        print(f"query \"{res['query']}\": {1000 * res['query_s']:.0f} ms")
    record = {"date": _dt.datetime.now().isoformat(timespec="seconds"),
              "command": " ".join(["sync4d", *sys.argv[1:]]), "machine": platform.node(),
              "processor": platform.processor() or platform.machine(),
              "threads": args.threads, **res}  # fmt: skip
    out = Path(args.out)
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {out}")
    return 0
