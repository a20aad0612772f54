"""A record of runs' periodic test evaluations (`fit`'s ``eval_every``, on the first
``eval_frames`` test views, the run's own background), read from each run's metrics log:
early A/B comparisons of configs that share a schedule, where a run was stopped once its
evaluations had answered (docs/results/dnerf.md: which of lego's two changes cost it).

    python scripts/record_periodic_evals.py RUN [RUN ...] --out docs/bench/NAME.json \\
        [--note TEXT]
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
from pathlib import Path

from sync4d.bench.measure import machine_info
from sync4d.pipeline.record import read_record
from sync4d.runs.names import METRICS_FILE


def periodic(run_dir: Path) -> dict:
    """The run's settings and its periodic evaluations (iteration, seconds, metrics)."""
    record = read_record(run_dir)
    evals = []
    for line in (run_dir / METRICS_FILE).read_text().splitlines():
        try:
            rec = json.loads(line)
        except ValueError:
            continue  # a line cut short when the run was stopped
        if isinstance(rec.get("test"), dict):
            evals.append({"iteration": rec["iteration"], "train_seconds": rec["train_seconds"],
                          **rec["test"]})  # fmt: skip
    calls = record.get("command", {}).get("invocations") or [{}]
    return {"run": str(run_dir), "scene": record.get("scene"), "settings": calls[0],
            "train_background": record["config"]["phase1"].get("train_background", "fixed"),
            "time_frequency": record["config"]["phase1"]["deform"].get("time_frequency"),
            "evaluations": evals}  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--note", default="")
    a = p.parse_args()
    rec = {"benchmark": "periodic evaluations (scripts/record_periodic_evals.py)",
           "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
           "machine": machine_info(), "note": a.note,
           "runs": [periodic(r) for r in a.runs]}  # fmt: skip
    a.out.write_text(json.dumps(rec, indent=1) + "\n")
    for r in rec["runs"]:
        print(f"{r['run']}: {r['train_background']}, time_frequency {r['time_frequency']}: "
              + ", ".join(f"@{e['iteration']} {e['psnr']:.2f}" for e in r["evaluations"]))


if __name__ == "__main__":
    main()
