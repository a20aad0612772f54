"""Every number has its record (issue 53): each measured figure in README.md and docs/ comes from
a committed JSON or CSV under docs/bench/, named next to it. The convention is in
docs/bench/README.md; in short:

- a table's record is every `docs/bench/...json|csv` path (or `bench/...`, a link, a folder)
  named in the text between the previous table or heading and the table, or in a
  `<!-- record: PATH ... -->` comment there;
- a table that is not a measurement (settings, file layouts, citations) says so with
  `<!-- record: none (WHY) -->` in the same place;
- a README paragraph starting **Headline** names its records in the paragraph the same way;
- each number of a table or headline must be one of its records' values, printed rounded
  (any unit among ms/s/min, MB/GB, fraction/percent: see SCALES), or listed in the record's
  derived values. Integers 0..10 and numbers in backticks (settings, code) are not checked.
Every page is checked; none is exempt (the pages that were pending in issue 53 all pass).
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import re
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

from support import ROOT

DOCS = ROOT / "docs"
BENCH = DOCS / "bench"

# Generated from the code by scripts/gen_docs.py: option and config defaults, not measurements.
GENERATED = {"docs/cli.md", "docs/configs.md"}

OLD_BENCH = "written before `bench fit` / `bench phase3` recorded their command: it is in the page"

# Records named by checked pages that lack a field of the date / command / machine triple,
# with where the missing field is given instead.
RECORD_METADATA_GAPS: dict[str, str] = {
    "docs/bench/sweep-dnerf-1thread-x2.json": "the sweep's table; date, command: docs/sweep.md",
    "docs/bench/sweep-dnerf-2threads-x1.json": "the sweep's table; date, command: docs/sweep.md",
    "docs/bench/relational-queries.json": "a test's record; date and command in the page",
    "docs/bench/bench-fit-bouncingballs-retuned.json": OLD_BENCH,
    "docs/bench/bench-fit-bouncingballs-skips.json": OLD_BENCH,
    "docs/bench/bench-fit-bouncingballs-sparse.json": OLD_BENCH,
    "docs/bench/bench-fit-bouncingballs-static-sparsity.json": OLD_BENCH,
    "docs/bench/bench-fit-bouncingballs-static.json": OLD_BENCH,
    "docs/bench/bench-fit-bouncingballs.json": OLD_BENCH,
    "docs/bench/bench-fit-hook-retuned.json": OLD_BENCH,
    "docs/bench/bench-fit-hook-sparse.json": OLD_BENCH,
    "docs/bench/bench-fit-lego-retuned.json": OLD_BENCH,
    "docs/bench/bench-fit-nodes-bouncingballs-118.json": OLD_BENCH,
    "docs/bench/bench-fit-nodes-bouncingballs.json": OLD_BENCH,
    "docs/bench/bench-fit-nodes-hook-hellwarrior.json": OLD_BENCH,
    "docs/bench/bench-fit-nodes-lego-117.json": OLD_BENCH,
    "docs/bench/bench-fit-nodes.json": OLD_BENCH,
    "docs/bench/bench-fit-scenes.json": OLD_BENCH,
    "docs/bench/bench-fit-synthetic.json": OLD_BENCH,
    "docs/bench/bench-phase3.json": OLD_BENCH,
    "docs/bench/eval-black-nodes-full.json": OLD_BENCH,
}

TABLE_LINE = re.compile(r"^\s*\|")
HEADING = re.compile(r"^#{1,6}\s")
RECORD_PATH = re.compile(r"(?:docs/)?bench/[\w./-]*[\w/]")
RECORD_COMMENT = re.compile(r"<!--\s*record:\s*(.*?)-->", re.S)
NUMBER = re.compile(
    r"(?<![\w.])(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?:e([-+]?\d+))?([kM](?![a-zA-Z]))?"
)
# A raw value v backs a printed p when v * s rounds to p for one of these unit scales.
SCALES = (1.0, 1e3, 1e-3, 1e2, 1e-2, 60.0, 1 / 60, 1 / 1024)


@dataclass
class Block:
    page: str
    kind: str  # "table" or "headline"
    title: str
    line: int
    text: str
    context: str


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def blocks(path: Path) -> list[Block]:
    lines = path.read_text().splitlines()
    out: list[Block] = []
    context: list[str] = []
    heading = ""
    i = 0
    while i < len(lines):
        line = lines[i]
        if TABLE_LINE.match(line):
            j = i
            while j < len(lines) and TABLE_LINE.match(lines[j]):
                j += 1
            body = [r for r in lines[i + 2 : j]]  # skip the header row and the separator
            table = Block(rel(path), "table", heading, i + 1, "\n".join(body), "\n".join(context))
            out.append(table)
            context = []
            i = j
            continue
        if HEADING.match(line):
            heading = line.lstrip("#").strip()
            context = []
        else:
            context.append(line)
        if path == ROOT / "README.md" and "**Headline**" in line:
            j = i
            while j < len(lines) and lines[j].strip():
                j += 1
            para = "\n".join(lines[i:j])
            para = para[para.index("**Headline**") :]
            out.append(Block(rel(path), "headline", heading, i + 1, para, para))
        i += 1
    return out


def named_records(block: Block, base: Path) -> tuple[list[Path], bool]:
    """The record files a block names, and whether it says it is not a measurement."""
    paths: list[str] = []
    none = False
    for comment in RECORD_COMMENT.findall(block.context):
        if comment.strip().startswith("none"):
            none = True
        else:
            paths += comment.split()
    visible = RECORD_COMMENT.sub("", block.context)
    paths += RECORD_PATH.findall(visible)
    files: list[Path] = []
    for p in dict.fromkeys(paths):
        p = p.rstrip(".,;:)")
        if p.endswith("-") or not (p.endswith((".json", ".csv", "/")) or (ROOT / p).is_dir()):
            continue  # a prefix such as `docs/bench/bench-fit-` in prose, or a plot
        path = ROOT / p if p.startswith("docs/") else (base.parent / p)
        if not path.exists() and p.startswith("bench/"):
            path = BENCH / p.removeprefix("bench/")
        files.append(path.resolve())
    return files, none


def _numbers_in(text: str) -> list[float]:
    return [v for v, _ in parse_numbers(text)]


def _walk(obj: object, out: list[float]) -> None:
    if isinstance(obj, bool):
        return
    if isinstance(obj, (int, float)):
        if math.isfinite(obj):
            out.append(abs(float(obj)))
    elif isinstance(obj, str):
        out += _numbers_in(obj)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _walk(k, out)
            _walk(v, out)
    elif isinstance(obj, list):
        for v in obj:
            _walk(v, out)


@cache
def record_values(path: Path) -> tuple[float, ...]:
    files = sorted(path.rglob("*.json")) + sorted(path.rglob("*.csv")) if path.is_dir() else [path]
    out: list[float] = []
    for f in files:
        if f.suffix == ".csv":
            with f.open() as fh:
                for row in csv.reader(fh):
                    for cell in row:
                        _walk(cell, out)
        else:
            _walk(json.loads(f.read_text()), out)
    return tuple(sorted(out))


def parse_numbers(text: str) -> list[tuple[float, float]]:
    """(value, half the last printed digit) of each checked number of `text`."""
    text = re.sub(r"`[^`]*`", " ", text)  # settings and code
    text = re.sub(r"\]\([^)]*\)", "]", text)  # link targets
    text = re.sub(r"<!--.*?-->", " ", text, flags=re.S)
    found = []
    for m in NUMBER.finditer(text):
        whole, frac, exp, suffix = m.groups()
        value = float(whole.replace(",", "") + (frac or "") + (f"e{exp}" if exp else ""))
        half = 0.5 * 10.0 ** -(len(frac) - 1 if frac else 0)
        if exp:
            half *= 10.0 ** int(exp)
        if suffix:
            mult = 1e3 if suffix == "k" else 1e6
            value, half = value * mult, half * mult
        if not frac and not exp and not suffix and value <= 10:
            continue
        found.append((value, half))
    return found


def backed(value: float, half: float, values: tuple[float, ...]) -> bool:
    for s in SCALES:
        lo, hi = (value - half * 1.0000001) / s, (value + half * 1.0000001) / s
        i = bisect.bisect_left(values, lo)
        if i < len(values) and values[i] <= hi:
            return True
    return False


def all_blocks() -> list[Block]:
    return [b for p in pages() for b in blocks(p)]


def _metadata_gaps(path: Path) -> list[str]:
    files = sorted(path.rglob("*.json")) if path.is_dir() else [path]
    gaps = []
    for f in files:
        if f.suffix != ".json" or rel(f) in RECORD_METADATA_GAPS:
            continue
        data = json.loads(f.read_text())
        keys = set(data) if isinstance(data, dict) else set()
        lacking = [k for k, names in (("date", {"date", "created"}), ("command", {"command"}),
                                      ("machine", {"machine"})) if not keys & names]  # fmt: skip
        if lacking:
            gaps.append(f"{rel(f)}: no {', '.join(lacking)}")
    return gaps


def test_named_records_exist_and_hold_date_command_machine() -> None:
    missing, bare = [], []
    for block in all_blocks():
        files, _ = named_records(block, ROOT / block.page)
        for f in files:
            if not f.exists():
                missing.append(f"{block.page}:{block.line}: {rel(f)}")
            else:
                bare += _metadata_gaps(f)
    assert not missing, "records named but not committed:\n" + "\n".join(missing)
    assert not bare, "records without date, command or machine:\n" + "\n".join(sorted(set(bare)))


def _check(block: Block) -> list[str]:
    files, none = named_records(block, ROOT / block.page)
    numbers = parse_numbers(block.text)
    if none or not numbers:
        return []
    if not files:
        return [f"{block.page}:{block.line} ({block.kind} under '{block.title}'): no record named"]
    values = tuple(sorted(v for f in files if f.exists() for v in record_values(f)))
    bad = sorted({f"{v:g}" for v, h in numbers if not backed(v, h, values)})
    if bad:
        names = ", ".join(rel(f) for f in files)
        return [f"{block.page}:{block.line} ({block.kind} under '{block.title}'): "
                f"{', '.join(bad)} not in {names}"]  # fmt: skip
    return []


@pytest.mark.parametrize("page", [rel(p) for p in pages()])
def test_every_number_comes_from_its_record(page: str) -> None:
    if page in GENERATED:
        return
    problems = []
    for block in blocks(ROOT / page):
        problems += _check(block)
    assert not problems, "\n".join(problems)


def test_the_checker_rounds_and_converts_units() -> None:
    values = tuple(sorted([393.44, 20612.0, 0.9938, 52.39]))
    ok = parse_numbers("| 393 ms | 20.6 s | 99.38 % | 52.4x | 0.994 |")
    assert all(backed(v, h, values) for v, h in ok)
    wrong = parse_numbers("| 394 ms | 20.7 s | 53.1x |")
    assert not any(backed(v, h, values) for v, h in wrong)
    assert parse_numbers("`--iters 600` phase1 D_theta 3 of 8") == []
    assert [v for v, _ in parse_numbers("14,980 and 1.5e-3 and 100k")] == [14980, 0.0015, 100000]
