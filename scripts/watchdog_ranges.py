"""Record how large trained values get: for each checkpoint, each parameter's largest magnitude,
the evidence behind the watchdog's divergence bounds (`sync4d.watchdog.DIVERGED`, 1e4; and
`DIVERGED_WORLD`, 1e6 scene scales, for positions).

    python scripts/watchdog_ranges.py RUN... --out docs/bench/watchdog-ranges.json

Each RUN is a run folder written by `sync4d fit` (its checkpoint.safetensors is read); the
record holds the date, the command, the machine, and per run the dataset it was trained on,
its iteration and every floating parameter's max |value| (optimizer moments excluded).
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

from sync4d.bench.measure import machine_info
from sync4d.runs import CHECKPOINT_NAME, RUN_FILE, read_checkpoint

#: Checkpoint entries that are not trained values (optimizer state, counters, caches).
SKIP = ("optim", "adam", "densify.", "exp_avg")


def ranges(run: Path) -> dict:
    """The run's dataset, iteration and max |value| per floating parameter."""
    tensors, meta = read_checkpoint(run / CHECKPOINT_NAME)
    info = json.loads((run / RUN_FILE).read_text()) if (run / RUN_FILE).exists() else {}
    values = {k: float(v.abs().max()) for k, v in sorted(tensors.items())
              if v.is_floating_point() and v.numel() and not any(s in k for s in SKIP)}  # fmt: skip
    return {"run": str(run), "data": info.get("data"), "iteration": meta.get("iteration"),
            "max_abs": values}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    runs = [ranges(r) for r in args.runs]
    overall: dict[str, float] = {}
    for r in runs:
        for k, v in r["max_abs"].items():
            overall[k] = max(overall.get(k, 0.0), v)
    record = {
        "date": datetime.date.today().isoformat(),
        "command": "python " + " ".join(sys.argv),
        "machine": machine_info(),
        "max_abs_over_runs": overall,
        "largest": max(overall.values()),
        "runs": runs,
    }
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"{len(runs)} runs; largest |value| {record['largest']:.3g} "
          f"({max(overall, key=overall.get)})")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
