"""``python -m sync4d bench phase3 RUN [RUN ...]``: Phase 3's cost on finished Phase 2 runs.

For each run, with the Phase 3 settings the run recorded (built through
`sync4d.pipeline.phase3`, as `fit` builds it; `--encoder` replaces the encoder): the encoder's
load time, the field's build time split into its steps (observe: crops, visibility, residuals
and gaps; encode: the crops through the image encoder; field: kinematics, ridge, blend and
EMA) and the latency of text queries, cold (the query's texts encoded) and warm (read from the
text cache, as a repeated query is). The run folders are not touched: the field and its text
cache live in a temporary folder. Writes a JSON and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.options import add_backend, add_threads, encoder_help, positive_int
from sync4d.report import align_table

__all__ = ["DEFAULT_QUERIES", "add_arguments", "bench_run", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench phase3`` (`sync4d.cli`)."""
    p.description = (
        "Build each run's language field in a temporary folder (the run is not touched) and "
        "time its steps and text queries, cold and cached; writes a JSON."
    )
    p.add_argument("runs", nargs="+", metavar="RUN", help="Phase 2 run folders")
    p.add_argument("--encoder", default=None, metavar="DIR",
                   help=encoder_help(default=True))
    p.add_argument("--queries", nargs="+", default=None, metavar="TEXT",
                   help="the queries to time (default: five identity, state and motion "
                   "queries)")  # fmt: skip
    p.add_argument("--repeat", type=positive_int, default=3, metavar="N",
                   help="timings per query (the median is reported; default 3)")
    p.add_argument("--out", default=None, metavar="FILE.json",
                   help="results JSON (default bench-phase3.json)")
    add_threads(p)
    add_backend(p)

#: Queries timed by default (identity, state and motion phrases).
DEFAULT_QUERIES = ("red ball", "the ball that is falling", "a ball touching the plate",
                   "the fastest ball", "the blue box while it is sliding")  # fmt: skip


def bench_run(run_dir: Path, encoder_spec: str | None, queries: list[str], repeat: int,
              threads: int | None) -> dict:  # fmt: skip
    """Timings of one run (see the module notes) as a dict."""
    import torch

    from sync4d.phase3 import load_encoder
    from sync4d.phase3.query import TextCache, answer
    from sync4d.pipeline.phase3 import build_phase3, phase3_config

    if threads:
        torch.set_num_threads(threads)
    cfg3 = phase3_config(run_dir)
    if encoder_spec is not None:
        cfg3 = dataclasses.replace(cfg3, encoder=encoder_spec)
    t0 = time.perf_counter()
    encoder = load_encoder(cfg3.encoder or None)
    load_s = time.perf_counter() - t0
    built = build_phase3(run_dir, cfg3, threads=threads, save=False, encoder=encoder)
    field, run_gaussians = built.field, built.gaussians
    cold, warm = [], []
    with tempfile.TemporaryDirectory(prefix="sync4d-bench-phase3-") as tmp:
        (Path(tmp) / "phase3").mkdir()
        for _ in range(repeat):
            for q in queries:
                fresh = TextCache(tmp, field, encoder)
                fresh.texts.clear()
                t1 = time.perf_counter()
                answer(field, q, cache=fresh)
                cold.append(time.perf_counter() - t1)
                t2 = time.perf_counter()
                answer(field, q, cache=TextCache(tmp, field, encoder))
                warm.append(time.perf_counter() - t2)
    return {
        "run": str(run_dir), "encoder": encoder.describe(), "objects": len(field.labels),
        "frames": len(field.times), "gaussians": run_gaussians,
        "encoder_load_s": load_s, **{k: v for k, v in field.timings.items()},
        "query_cold_ms": 1e3 * statistics.median(cold),
        "query_warm_ms": 1e3 * statistics.median(warm), "queries": queries, "repeat": repeat,
    }  # fmt: skip


def main(args: argparse.Namespace) -> int:
    """Run `bench phase3` with parsed `args`; the exit status."""
    queries = list(args.queries or DEFAULT_QUERIES)
    rows = []
    for run_dir in args.runs:
        try:
            rows.append(bench_run(Path(run_dir), args.encoder, queries, args.repeat,
                                  args.threads))  # fmt: skip
        except Sync4dError as e:
            print(f"bench phase3: {e}", file=sys.stderr)
            return e.exit_code
    out = Path(args.out or "bench-phase3.json")
    doc = {"date": _dt.datetime.now().isoformat(timespec="seconds"),
           "command": [sys.executable, *sys.argv],
           "machine": {"platform": platform.platform(), "threads": args.threads},
           "results": rows}  # fmt: skip
    out.write_text(json.dumps(doc, indent=1) + "\n")
    table = [[Path(r["run"]).name, f"{r['objects']}x{r['frames']}", str(int(r["crops"])),
              f"{r['encoder_load_s']:.2f}", f"{r['observe_s']:.1f}", f"{r['encode_s']:.1f}",
              f"{r['field_s']:.2f}", f"{r['total_s']:.1f}", f"{r['query_cold_ms']:.0f}",
              f"{r['query_warm_ms']:.1f}"] for r in rows]  # fmt: skip
    print(align_table(["run", "objects x frames", "crops", "load s", "observe s", "encode s",
                       "field s", "build s", "query cold ms", "query warm ms"], table))
    print(f"wrote {out}")
    return 0
