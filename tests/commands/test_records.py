"""Every figure names the field it comes from (issues 53 and 62): each measured number of a table
or README headline is compared with one field of one committed record under docs/bench/, named
beside it. The convention is in docs/bench/README.md; in short, a `cite` comment just above a
table (or inside a headline paragraph) says where each figure is read:

    <!-- cite docs/bench/dnerf-config.json
    rows: results[scene=bouncingballs] results[scene=lego]
    PSNR black: backgrounds.on.black.psnr
    train min: train_seconds
    worst view on black: worst_view.psnr
    -->

- the first line names the records, `NAME=PATH` to give one a name, the first one unnamed is
  the default (`PATH` alone);
- `rows:` gives each body row's base field in order (`NAME:path` for another record, `-` for a
  row with no measured figures); a row base may be empty where the columns give whole paths;
- `COLUMN: path ...` gives, for the column with that header, one field per checked number in
  a cell, read from the row's base (`-`: a number that is not a measurement, such as an
  iteration count that names the run); `{}` in a path stands for the row base, `{n}` for the
  row's position (0 first), and a path starting with `$` is read from the record's root;
- `@ROW COLUMN: path ...` (ROW counted from 1) overrides one cell;
- in a README headline, `FIGURE: path` (the figure as printed) names each figure's field;
- entries may also be separated by `;` on one line (the README keeps its headlines short).

A path is a dotted list of keys (`"a key"` quoted when it holds a dot or a space), each with
optional `[N]` list indices or `[key=value]` selections (the element of a list whose `key` is
`value`; `[k=v,j=w]` where both hold); a CSV record reads as a list of rows keyed by its
header. A figure is backed when the field's value (a number, or a number inside a string)
printed to the figure's digits equals it, in one of the units it converts to (ms / s / min,
fraction / percent, MiB / GiB). Tables that are not measurements say
`<!-- record: none (WHY) -->`. Integers 0..10 and numbers in backticks (settings, code) are not
checked. docs/cli.md and docs/configs.md are generated from the code. Every other page is
checked; none is exempt.
"""

from __future__ import annotations

import csv
import json
import math
import re
from dataclasses import dataclass, field
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
COMMENT = re.compile(r"<!--\s*(cite|record:)(.*?)-->", re.S)
NUMBER = re.compile(
    r"(?<![\w.])(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?:e([-+]?\d+))?([kM](?![a-zA-Z]))?"
)
# A field's value v backs a printed p when v * s rounds to p for one of these unit scales.
SCALES = (1.0, 1e3, 1e-3, 1e2, 1e-2, 60.0, 1 / 60, 1 / 1024)
TOKEN = re.compile(r'(?:"[^"]*"|\[[^\]]*\]|\S)+')  # a path: spaces only inside "" or []
PATH_PART = re.compile(r'\.?(?:"([^"]*)"|([^.\[\]"]+))|\[([^\]=]*?)(?:=([^\]]*))?\]')


@dataclass
class Block:
    page: str
    kind: str  # "table" or "headline"
    title: str
    line: int
    header: list[str]
    rows: list[list[str]]  # a table's body cells; a headline is one row of one cell
    context: str


@dataclass
class Citation:
    records: dict[str, Path] = field(default_factory=dict)  # name ("" the default) -> file
    rows: list[str] | None = None
    columns: dict[str, list[str]] = field(default_factory=dict)
    cells: dict[tuple[int, str], list[str]] = field(default_factory=dict)
    none: bool = False
    problems: list[str] = field(default_factory=list)


def pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix() if path.is_relative_to(ROOT) else str(path)


def cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def blocks(path: Path) -> list[Block]:
    """The tables of a page and the README's headline paragraphs, with the text above each."""
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
            body = [cells(r) for r in lines[i + 2 : j]]  # skip the separator
            out.append(Block(rel(path), "table", heading, i + 1, cells(line), body,
                             "\n".join(context)))  # fmt: skip
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
            out.append(Block(rel(path), "headline", heading, i + 1, ["figure"], [[para]], para))
        i += 1
    return out


def _record_path(token: str, page: Path) -> Path:
    token = token.strip()
    if token.startswith("docs/"):
        return (ROOT / token).resolve()
    found = (page.parent / token).resolve()
    if not found.exists() and token.startswith("bench/"):
        found = (BENCH / token.removeprefix("bench/")).resolve()
    return found


def citation(block: Block) -> Citation:
    """The block's `cite` (or `record: none`) comment, parsed."""
    cite = Citation()
    page = ROOT / block.page
    found = [(kind, body) for kind, body in COMMENT.findall(block.context)]
    for kind, body in found:
        if kind == "record:":
            if body.strip().startswith("none"):
                cite.none = True
            else:
                cite.problems.append("a `record:` comment names no fields: write a `cite` one")
            continue
        lines = body.strip("\n").splitlines() or [""]
        head, *first = lines[0].split(";")
        entries: list[str] = [e.strip() for e in first if e.strip()]
        for line in lines[1:]:
            if entries and line[:1].isspace() and not re.match(r"\s*\S[^:]*:\s", line):
                entries[-1] += " " + line.strip()
            else:
                entries += [e.strip() for e in line.split(";") if e.strip()]
        for token in TOKEN.findall(head):
            name, _, target = token.rpartition("=") if "=" in token else ("", "", token)
            cite.records[name] = _record_path(target, page)
        for entry in entries:
            key, sep, value = entry.partition(": ")
            if not sep:
                key, value = entry.rstrip(":"), ""
            paths = TOKEN.findall(value)
            if key == "rows":
                cite.rows = paths
            elif m := re.fullmatch(r"@(\d+)\s+(.+)", key):
                cite.cells[(int(m.group(1)) - 1, m.group(2).strip())] = paths
            else:
                cite.columns[key.strip()] = paths
    return cite


Part = str | int | tuple[tuple[str, ...], ...]


def split_path(path: str) -> list[Part]:
    """`a.b[2][k=v,j=w]."c d"` -> ["a", "b", 2, (("k", "v"), ("j", "w")), "c d"]."""
    parts: list[Part] = []
    pos = 0
    while pos < len(path):
        m = PATH_PART.match(path, pos)
        if not m or m.end() == pos:
            raise ValueError(f"cannot read the field path {path!r} at {path[pos:]!r}")
        quoted, plain, index, value = m.groups()
        if quoted is not None or plain is not None:
            parts.append(quoted if quoted is not None else plain)
        elif value is not None:  # [k=v] or [k1=v1,k2=v2]: every pair must hold
            pairs = f"{index}={value}".split(",")
            parts.append(tuple(tuple(x.strip() for x in p.split("=", 1)) for p in pairs))
        else:
            parts.append(int(index))
        pos = m.end()
    return parts


def resolve(data: object, path: str) -> object:
    """The value at `path` in `data`; KeyError naming the first part that is not there."""
    node = data
    for part in split_path(path):
        if isinstance(part, int):
            if not isinstance(node, list) or not -len(node) <= part < len(node):
                raise KeyError(f"no [{part}]")
            node = node[part]
        elif isinstance(part, tuple):
            hits = [x for x in node if isinstance(x, dict) and
                    all(str(x.get(k)) == want for k, want in part)] \
                if isinstance(node, list) else []  # fmt: skip
            if len(hits) != 1:
                where = ",".join(f"{k}={want}" for k, want in part)
                raise KeyError(f"{len(hits)} elements with {where}")
            node = hits[0]
        else:
            if not isinstance(node, dict) or part not in node:
                raise KeyError(f"no {part!r}")
            node = node[part]
    return node


@cache
def load(path: Path) -> object:
    if path.suffix == ".csv":
        with path.open() as fh:
            return list(csv.DictReader(fh))
    return json.loads(path.read_text())


def parse_numbers(text: str) -> list[tuple[float, float, str]]:
    """(value, half the last printed digit, as printed) of each checked number of `text`."""
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
        found.append((value, half, m.group(0)))
    return found


def field_values(value: object) -> list[float]:
    if isinstance(value, bool):
        return []
    if isinstance(value, (int, float)):
        return [abs(float(value))] if math.isfinite(value) else []
    if isinstance(value, str):
        return [v for v, _, _ in parse_numbers(value)] + (
            [abs(float(value))] if re.fullmatch(r"-?\d+(\.\d+)?(e[-+]?\d+)?", value) else [])
    return []


def backed(value: float, half: float, values: list[float]) -> bool:
    for v in values:
        for s in SCALES:
            if abs(v * s - value) <= half * 1.0000001:
                return True
    return False


def _field(cite: Citation, token: str, base: str, n: int) -> tuple[Path | None, str]:
    """The record and the path inside it that a column's path names for one row."""
    name, path = "", token
    m = re.match(r"([\w-]+):(.*)", token)
    if m and m.group(1) in cite.records:
        name, path = m.groups()
    bname, bpath = "", base
    m = re.match(r"([\w-]+):(.*)", base)
    if m and m.group(1) in cite.records:
        bname, bpath = m.groups()
    path = path.replace("{n}", str(n))
    if path.startswith("$"):
        return cite.records.get(name), path[1:].lstrip(".")
    if "{}" in path:
        return cite.records.get(bname or name), path.replace("{}", bpath)
    joined = f"{bpath}.{path}" if bpath and path else bpath or path
    return cite.records.get(bname or name), joined


def check(block: Block) -> list[str]:
    """What is wrong with the block's figures: one line each."""
    where = f"{block.page}:{block.line} ({block.kind} under '{block.title}')"
    cite = citation(block)
    figures = [(r, c, parse_numbers(text)) for r, row in enumerate(block.rows)
               for c, text in enumerate(row)]  # fmt: skip
    if cite.none or not any(nums for _, _, nums in figures):
        return []
    if cite.problems:
        return [f"{where}: {p}" for p in cite.problems]
    if not cite.records:
        return [f"{where}: no `cite` comment names its records and fields"]
    problems = []
    for name, path in cite.records.items():
        if not path.exists():
            problems.append(f"{where}: record {rel(path)} "
                            f"{'(' + name + ') ' if name else ''}is not committed")  # fmt: skip
    if problems:
        return problems
    headline = block.kind == "headline"
    if not headline and cite.rows is not None and len(cite.rows) != len(block.rows):
        return [f"{where}: `rows:` names {len(cite.rows)} rows, the table has {len(block.rows)}"]
    for r, c, nums in figures:
        if not nums:
            continue
        column = block.header[c] if c < len(block.header) else f"#{c + 1}"
        base = "" if headline or cite.rows is None else cite.rows[r]
        if base == "-":
            problems.append(f"{where}: row {r + 1} is marked `-` but prints {nums[0][2]}")
            continue
        for k, (value, half, printed) in enumerate(nums):
            if headline:
                tokens = cite.columns.get(printed)
                token = tokens[0] if tokens else None
                label = printed
            else:
                tokens = cite.cells.get((r, column), cite.columns.get(column))
                label = f"row {r + 1} '{block.rows[r][0]}', column '{column}'"
                if tokens is not None and len(tokens) != len(nums):
                    problems.append(f"{where}: {label} prints {len(nums)} figures, its "
                                    f"citation names {len(tokens)} fields")  # fmt: skip
                    break
                token = tokens[k] if tokens else None
            if token is None:
                problems.append(f"{where}: {label}: {printed} names no field")
                continue
            if token == "-":
                continue
            record, path = _field(cite, token, base, r)
            if record is None:
                problems.append(f"{where}: {label}: no record named for {token!r}")
                continue
            try:
                value_at = resolve(load(record), path)
            except (KeyError, ValueError) as e:
                problems.append(f"{where}: {label}: {rel(record)} has no field {path} "
                                f"({str(e).strip(chr(34))})")  # fmt: skip
                continue
            if not backed(value, half, field_values(value_at)):
                problems.append(f"{where}: {label}: {printed} is not {rel(record)} {path} "
                                f"= {value_at!r}"[:300])  # fmt: skip
    return problems


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


def test_named_records_hold_date_command_machine() -> None:
    bare: list[str] = []
    for block in all_blocks():
        for path in citation(block).records.values():
            if path.exists():
                bare += _metadata_gaps(path)
    assert not bare, "records without date, command or machine:\n" + "\n".join(sorted(set(bare)))


@pytest.mark.parametrize("page", [rel(p) for p in pages()])
def test_every_figure_is_the_field_it_cites(page: str) -> None:
    if page in GENERATED:
        return
    problems = []
    for block in blocks(ROOT / page):
        problems += check(block)
    assert not problems, "\n".join(problems)


def _block(text: str, page: str = "docs/results/x.md") -> Block:
    lines = text.strip().splitlines()
    start = next(i for i, s in enumerate(lines) if TABLE_LINE.match(s))
    return Block(page, "table", "t", 1, cells(lines[start]),
                 [cells(s) for s in lines[start + 2 :]], "\n".join(lines[:start]))  # fmt: skip


def test_the_check_reads_the_named_field_alone(tmp_path: Path) -> None:
    record = tmp_path / "r.json"
    record.write_text(json.dumps({"runs": [{"scene": "hook", "psnr": 34.09, "secs": 1506.0},
                                           {"scene": "lego", "psnr": 34.9, "secs": 2490.0}],
                                  "derived": {"gain": [0.0, 0.81]}}))  # fmt: skip
    table = f"""<!-- cite {record}
rows: runs[scene=hook] runs[scene=lego]
PSNR: psnr
min: secs
gain: $derived.gain[{{n}}]
-->
| scene | PSNR | min | gain |
|---|---:|---:|---:|
| hook | 34.09 | 25.1 | 0 |
| lego | 34.90 | 41.5 | 0.81 |
"""
    assert check(_block(table)) == []
    # 34.9 is in the record, but not in hook's field: the loose check accepted it.
    wrong = table.replace("| hook | 34.09", "| hook | 34.9")
    assert len(problems := check(_block(wrong))) == 1 and "34.9 is not" in problems[0]
    # a column with figures and no field, and a path that is not in the record
    assert "names no field" in check(_block(table.replace("min: secs\n", "")))[0]
    assert "has no field" in check(_block(table.replace("min: secs", "min: seconds")))[0]
    assert "rows" in check(_block(table.replace(" runs[scene=lego]", "")))[0]


def test_the_checker_rounds_and_converts_units() -> None:
    values = [393.44, 20612.0, 0.9938, 52.39]
    ok = parse_numbers("| 393 ms | 20.6 s | 99.38 % | 52.4x | 0.994 |")
    assert all(backed(v, h, values) for v, h, _ in ok)
    wrong = parse_numbers("| 394 ms | 20.7 s | 53.1x |")
    assert not any(backed(v, h, values) for v, h, _ in wrong)
    assert parse_numbers("`--iters 600` phase1 D_theta 3 of 8") == []
    assert [v for v, _, _ in parse_numbers("14,980 and 1.5e-3 and 100k")] == [14980, 0.0015, 1e5]
    assert split_path('a.b[2][k=v]."c d"') == ["a", "b", 2, (("k", "v"),), "c d"]
    assert split_path("r[n=1, t=2]") == ["r", (("n", "1"), ("t", "2"))]
    assert TOKEN.findall('a[name=red ball].x "b c".d') == ["a[name=red ball].x", '"b c".d']
