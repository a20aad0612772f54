"""Add the derived values a results page prints to the records they come from (issue 53,
docs/bench/README.md): each is computed here from the record's own raw values and written under
the record's "derived" key with the rule that made it, so a ratio in a table has a record too.

    python scripts/record_derived.py    # rewrites the "derived" key of the records below
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "docs" / "bench"

# bench fit records whose tables print a speed-up against the first variant.
FIT_SPEEDUP = [
    "bench-fit-bouncingballs-skips.json",
    "bench-fit-bouncingballs-static-sparsity.json",
    "bench-fit-bouncingballs-sparse.json",
    "bench-fit-hook-sparse.json",
]


def fit_speedups(record: dict) -> dict:
    results = record["results"]
    base = results[0]["train_seconds"]
    return {
        "rule": "speed_up[i] = results[0].train_seconds / results[i].train_seconds; "
        "psnr_change_db[i] = results[i].psnr - results[0].psnr",
        "script": "scripts/record_derived.py",
        "speed_up": [base / r["train_seconds"] for r in results],
        "psnr_change_db": [r["psnr"] - results[0]["psnr"] for r in results],
    }


def raster_run_pairs(record: dict) -> dict:
    default = [r for r in record["results"] if r.get("variant", "default") == "default"]
    evaluated = sum(r["counters"]["evaluated"] for r in default)
    blended = sum(r["counters"]["blended"] for r in default)
    return {
        "rule": "evaluated_per_blended = sum of counters.evaluated / sum of counters.blended "
        "over the default variant's frames",
        "script": "scripts/record_derived.py",
        "evaluated_per_blended": evaluated / blended,
    }


def raster_run_counts(record: dict) -> dict:
    """raster_run_pairs plus the mean evaluated and blended pairs per frame (skips.md's
    Rasterizer table: a run's counts over its test frames)."""
    default = [r for r in record["results"] if r.get("variant", "default") == "default"]
    out = raster_run_pairs(record)
    out["rule"] += ("; evaluated_mean, blended_mean = mean over those frames of "
                    "counters.evaluated, counters.blended")  # fmt: skip
    out["evaluated_mean"] = sum(r["counters"]["evaluated"] for r in default) / len(default)
    out["blended_mean"] = sum(r["counters"]["blended"] for r in default) / len(default)
    return out


def sigkill_delay_range(record: dict) -> dict:
    """The range of the kills' delays after a save started (run-contract.md's SIGKILL row)."""
    delays = record["delay_after_save_start_ms"]
    return {
        "rule": "delay_ms_min, delay_ms_max = min, max of delay_after_save_start_ms",
        "script": "scripts/record_derived.py",
        "delay_ms_min": min(delays),
        "delay_ms_max": max(delays),
    }


def raster_run_before_after() -> dict:
    """Mean over 3 test frames x 2 rounds of the median forward and forward+backward times of
    each build, and the change after/before, per scene (skips.md's masked-stores table)."""
    folder = BENCH / "raster-run"
    values: dict = {}
    sources = []
    machine = None
    for scene in ("bb", "hook"):
        means = {}
        for phase in ("before", "after"):
            fwd, fb = [], []
            for k in (1, 2):
                path = folder / f"{scene}-{phase}-{k}.json"
                record = json.loads(path.read_text())
                machine = machine or record["machine"]
                sources.append(path.name)
                for r in record["results"]:
                    if r.get("variant", "default") == "default":
                        fwd.append(r["forward"]["median_ms"])
                        fb.append(r["forward_backward"]["median_ms"])
            means[phase] = (sum(fwd) / len(fwd), sum(fb) / len(fb))
        (bf, bfb), (af, afb) = means["before"], means["after"]
        values[scene] = {
            "forward_ms": {"before": bf, "after": af, "change_percent": 100 * (af / bf - 1)},
            "forward_backward_ms": {"before": bfb, "after": afb,
                                    "change_percent": 100 * (afb / bfb - 1)},
        }  # fmt: skip
    return {
        "date": _date(),
        "command": "python scripts/record_derived.py",
        "machine": machine,
        "sources": sources,
        "rule": "mean over the default variant's frames of both rounds of each build of "
        "forward.median_ms and forward_backward.median_ms; change = after / before - 1",
        "derived": values,
    }


def phase3_claims_hidden_right(record: dict) -> dict:
    """docs/results/phase3.md's kinematic-claim table prints hidden frames right as a count."""

    def counts(entries: dict, hidden: int) -> dict:
        return {name: {rule: round(v[rule]["hidden_accuracy"] * hidden)
                       for rule in ("half-peak", "mean") if v[rule]["hidden_accuracy"] is not None}
                for name, v in entries.items() if isinstance(v, dict)}  # fmt: skip

    return {
        "rule": "hidden_frames_right[i] (table, in its order) and sweep[set][field][rule] = "
        "round(hidden_accuracy * hidden_frames) of that field and rule",
        "script": "scripts/record_derived.py",
        "hidden_frames_right": [
            {"field": name} | c
            for name, c in counts(record["table"], record["hidden_frames"]).items()
        ],
        "sweep": {name: counts(s, s["hidden_frames"]) for name, s in record["sweep"].items()},
    }


def phase3_paraphrases_right(record: dict) -> dict:
    """docs/results/phase3.md's paraphrase table prints the objects ranked right as a count."""
    return {
        "rule": "object_right[k] = the number of queries of lexicon_words / paraphrases whose "
        "`right` is true",
        "script": "scripts/record_derived.py",
        "object_right": {
            k: sum(bool(q["right"]) for q in record[k]) for k in ("lexicon_words", "paraphrases")
        },
    }


def _date() -> str:
    import datetime

    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


def write(path: Path, derive) -> None:
    record = json.loads(path.read_text())
    record["derived"] = derive(record)
    path.write_text(json.dumps(record, indent=2) + "\n")
    print(f"{path.relative_to(ROOT)}: {record['derived']}")


def main() -> int:
    for name in FIT_SPEEDUP:
        write(BENCH / name, fit_speedups)
    for path in sorted((BENCH / "raster-run").glob("*-[12].json")):
        write(path, raster_run_counts)
    write(BENCH / "run-contract-sigkill.json", sigkill_delay_range)
    write(BENCH / "phase3-claims.json", phase3_claims_hidden_right)
    write(BENCH / "phase3-paraphrases.json", phase3_paraphrases_right)
    out = BENCH / "raster-run" / "derived.json"
    out.write_text(json.dumps(raster_run_before_after(), indent=2) + "\n")
    print(f"{out.relative_to(ROOT)} written")
    return 0


if __name__ == "__main__":
    sys.exit(main())
