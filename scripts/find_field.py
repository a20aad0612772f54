"""Which fields of a record hold a printed figure: a help for writing the `cite` comments that
docs/bench/README.md asks for above each table.

    python scripts/find_field.py docs/bench/dnerf-config.json 37.36 40.72 33.2

prints, for each figure, every field path whose value rounds to it (in the units the records
check accepts), in the path syntax of the `cite` comment; list elements that carry a `scene`,
`name`, `label`, `variant`, `run` or `query` key are shown as selections (`[scene=hook]`).
"""

from __future__ import annotations

import csv
import json
import sys
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from commands.test_records import backed, field_values, parse_numbers  # noqa: E402

KEYS = ("scene", "name", "label", "variant", "run", "query", "id")


def _key(part: str) -> str:
    return f'"{part}"' if any(c in part for c in ' .[]"') else part


def walk(node: object, path: str = "") -> Iterator[tuple[str, object]]:
    if isinstance(node, dict):
        for k, v in node.items():
            yield from walk(v, f"{path}.{_key(str(k))}" if path else _key(str(k)))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            sel = f"[{i}]"
            if isinstance(v, dict):
                for key in KEYS:
                    value = v.get(key)
                    if (
                        isinstance(value, (str, int))
                        and not isinstance(value, bool)
                        and sum(isinstance(x, dict) and x.get(key) == value for x in node) == 1
                    ):
                        sel = f"[{key}={value}]"
                        break
            yield from walk(v, path + sel)
    else:
        yield path, node


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__)
        return 2
    path = Path(argv[0])
    if path.suffix == ".csv":
        with path.open() as fh:
            data: object = list(csv.DictReader(fh))
    else:
        data = json.loads(path.read_text())
    leaves = list(walk(data))
    for figure in argv[1:]:
        numbers = parse_numbers(figure) or parse_numbers(f"{figure}.")  # small integers too
        if not numbers:
            print(f"{figure}: not a checked figure")
            continue
        value, half, _ = numbers[0]
        hits = [p for p, v in leaves if backed(value, half, field_values(v))]
        print(f"{figure}: " + ("none" if not hits else ""))
        for p in hits[:12]:
            print(f"    {p}")
        if len(hits) > 12:
            print(f"    ... {len(hits) - 12} more")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
