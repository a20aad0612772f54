"""Measure the relational question sets on runs and record the numbers for the docs.

    python examples/relational/bench.py RUN QUESTIONS.json --label NAME \
        [--out docs/bench/relational-queries.json]

runs `sync4d eval RUN --queries QUESTIONS.json` (`evaluate_relational`) and writes (or
updates, under `--label`) an entry of the JSON with the date, the command, the machine, the
run's settings, and every row (question, plan, object, intervals, tIoU) beside the per-form
means, so each number in docs/phase3-queries.md can be traced to it.

``--oracle-embedded DIR`` first builds an oracle run of the embedded scene in DIR (Gaussians
on the true objects moved by the true motion, M_phi fitted, the offline encoder's field: the
test suite's `support.oracle`, so a developer checkout only) and measures that.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def oracle_embedded(out: Path) -> Path:
    sys.path.insert(0, str(ROOT / "tests"))
    from support.oracle import oracle_phase2_run
    from sync4d.phase3.build import build_field
    from sync4d.phase3.config import Phase3Config
    from sync4d.phase3.encoders.encoder import load_encoder

    out.mkdir(parents=True, exist_ok=True)
    run, _ = oracle_phase2_run(out, save=True)
    field = build_field(run, Phase3Config(), load_encoder("offline"), threads=1)
    field.save(run.path)
    return run.path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", nargs="?")
    ap.add_argument("questions")
    ap.add_argument("--label", required=True)
    ap.add_argument("--out", default=str(ROOT / "docs" / "bench" / "relational-queries.json"))
    ap.add_argument("--oracle-embedded", metavar="DIR")
    ap.add_argument("--note", default="")
    args = ap.parse_args()
    from sync4d.phase3.evaluation.relational_eval import evaluate_relational

    run = oracle_embedded(Path(args.oracle_embedded)) if args.oracle_embedded \
        else Path(args.run)  # fmt: skip
    summary = evaluate_relational(run, args.questions)
    rows = json.loads(Path(summary["rows_file"]).read_text())
    settings = {}
    try:
        meta = json.loads((run / "run.json").read_text())
        settings = {k: meta.get(k) for k in ("data", "command", "threads")
                    if k in meta}  # fmt: skip
    except (OSError, ValueError):
        pass
    try:  # the run's own test metrics, when it was evaluated
        settings["test_metrics"] = json.loads((run / "eval.json").read_text())["mean"]
    except (OSError, ValueError, KeyError):
        pass
    field = json.loads((run / "phase3" / "field.json").read_text())
    entry = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": " ".join(["python", *sys.argv]),
        "eval_command": f"sync4d eval {run} --queries {args.questions}",
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count(), "python": platform.python_version()},
        "run": str(run), "run_settings": settings, "note": args.note,
        "encoder": field.get("encoder", {}).get("kind"), "frames": None,
        "questions_file": args.questions, "forms": summary["forms"], "all": summary["all"],
        "rows": rows["rows"],
    }  # fmt: skip
    from sync4d.phase3.store import load_field

    entry["frames"] = len(load_field(run).times)
    out = Path(args.out)
    doc = json.loads(out.read_text()) if out.is_file() else {"entries": {}}
    doc["entries"][args.label] = entry
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(json.dumps({"label": args.label, "forms": summary["forms"], "all": summary["all"]},
                     indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
