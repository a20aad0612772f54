"""docs/cli.md and docs/configs.md are generated from the parser and the config dataclasses:
they must match what `scripts/gen_docs.py` writes today."""

from __future__ import annotations

import re
import subprocess
import sys

from support import ROOT


def test_generated_reference_docs_are_up_to_date() -> None:
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "gen_docs.py"), "--check"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr


def test_every_config_key_has_a_meaning() -> None:
    rows = [line for line in (ROOT / "docs" / "configs.md").read_text().splitlines()
            if line.startswith("| `")]  # fmt: skip
    assert len(rows) > 80
    cells = [[c.strip() for c in re.split(r"(?<!\\)\|", r)[1:-1]] for r in rows]
    missing = [c[0] for c in cells if not c[-1]]
    assert not missing, f"config keys without a #: comment: {missing}"
