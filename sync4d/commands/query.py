"""``python -m sync4d query RUN "text" [...]``: rank a run's objects for each text query and
say when each is active (Sec. 3.5's score, Appendix F's activation, the motion phrases), from the
field Phase 3 wrote into the run folder. Prints a table per query, writes a timeline PNG
(``RUN/phase3/query-<slug>.png``, or --plot DIR), ``--json`` prints the answers as data."""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from sync4d.errors import Sync4dError
from sync4d.options import add_encoder, add_rule
from sync4d.phase3.query import DEFAULT_SCORER, SCORER_TABLE, SCORERS, TextCache, answer
from sync4d.phase3.store import FieldError, load_field
from sync4d.report import align_table, plot_query_timeline
from sync4d.runs.names import FIELD_DIR, query_plot

__all__ = ["add_arguments", "main", "slug"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d query`` (`sync4d.cli`)."""
    p.description = (
        "Rank a run's objects for each text query and give the frames where each is active, "
        "from the Phase 3 field (fit --out RUN --phases 3). Writes a timeline PNG per query."
    )
    p.add_argument("run", metavar="RUN",
                   help="run folder with a Phase 3 field (fit --out RUN --phases 3)")
    p.add_argument("texts", nargs="+", metavar="TEXT",
                   help="one or more queries; relational ones (first, how many times, while, "
                   "before, highest, never ...) print the plan they were read as "
                   "(docs/phase3-queries.md)")
    scorers = "; ".join(f"{name}: {s.summary}" for name, s in SCORER_TABLE.items())
    p.add_argument("--scorer", choices=SCORERS, default=DEFAULT_SCORER,
                   help=f"{scorers} (default {DEFAULT_SCORER})")
    add_rule(p)
    add_encoder(p)
    p.add_argument("--json", action="store_true", help="print the answers as JSON")
    p.add_argument("--plot", default=None, metavar="DIR",
                   help="folder for the timeline PNGs (default RUN/phase3)")
    p.add_argument("--no-plot", action="store_true", help="write no timeline PNG")


def slug(text: str) -> str:
    """A file-name-safe short form of a query."""
    s = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return s[:60] or "query"


def _table(ans: dict) -> str:
    rows = []
    for i, o in enumerate(ans["objects"], 1):
        spans = ", ".join(f"{iv['start']}-{iv['end']} ({iv['t0']:.2f}-{iv['t1']:.2f})"
                          for iv in o["intervals"]) or "-"  # fmt: skip
        rows.append([str(i), o["name"], f"{o['score']:.3f}", spans])
    return align_table(["rank", "object", "score", "active frames (times)"], rows, left=(1, 3))


def main(args: argparse.Namespace) -> int:
    """Run `query` with parsed `args`; the exit status."""
    run_dir = Path(args.run)
    try:
        if not run_dir.is_dir():
            raise FieldError(f"{run_dir}: no such run folder")
        field = load_field(run_dir)
        cache = TextCache(run_dir, field, args.encoder)
        answers = []
        for text in args.texts:
            ans = answer(field, text, cache=cache, scorer=args.scorer, rule=args.rule)
            if not args.no_plot:
                out = Path(args.plot) if args.plot else run_dir / FIELD_DIR
                out.mkdir(parents=True, exist_ok=True)
                ans["plot"] = str(plot_query_timeline(ans, out / query_plot(slug(text))))
            answers.append(ans)
    except (Sync4dError, OSError) as e:  # OSError: a failed write
        print(f"query: {e}", file=sys.stderr)
        return 2
    if args.json:
        slim = [{k: v for k, v in a.items() if k not in ("timeline", "active")} | {
            "timeline": a["timeline"]} for a in answers]  # fmt: skip
        print(json.dumps(slim if len(slim) > 1 else slim[0], indent=1))
        return 0
    for ans in answers:
        vocab = " (closed-vocabulary encoder: colours and shapes)" if ans["closed_vocabulary"] \
            else ""
        print(f"\"{ans['query']}\" — {ans['scorer']} scorer, {ans['rule']} rule, encoder "
              f"{ans['encoder']}{vocab}")  # fmt: skip
        if ans.get("refusal"):
            print(f"plan: {ans['plan']} -> no object: {ans['refusal']}")
        elif ans.get("plan"):
            top = ans["objects"][0]
            spans = ", ".join(f"{iv['start']}-{iv['end']}" for iv in top["intervals"]) or "none"
            count = "" if ans.get("count") is None else f", count {ans['count']}"
            print(f"plan: {ans['plan']} -> {top['name']}, frames {spans}{count}")
        elif ans.get("fallback"):
            print(f"plan: none ({ans['fallback']})")
        if ans["motion_phrases"]:
            print("motion: " + ", ".join(
                m["predicate"] + (f" ({m['target']})" if m["target"] is not None else "")
                for m in ans["motion_phrases"]))  # fmt: skip
        print(_table(ans))
        if "plot" in ans:
            print(f"timeline: {ans['plot']}")
        print()
    return 0
