"""Write docs/bench/prompt-tokens-bouncingballs.json: the token count of the committed example
prompt (examples/bouncingballs-prompt.txt) by sync4d.export.prompt.count_tokens, with the date,
the command and the machine (docs/bench/README.md)."""

from __future__ import annotations

import datetime
import hashlib
import json
import os
import platform
import sys
from pathlib import Path

from sync4d.export.prompt import count_tokens

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    prompt = ROOT / "examples" / "bouncingballs-prompt.txt"
    text = prompt.read_text()
    tokens, tokenizer = count_tokens(text)
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "python scripts/record_prompt_tokens.py",
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
        "file": "examples/bouncingballs-prompt.txt",
        "sha256": hashlib.sha256(text.encode()).hexdigest(),
        "characters": len(text),
        "tokens": tokens,
        "tokenizer": tokenizer,
    }
    out = ROOT / "docs" / "bench" / "prompt-tokens-bouncingballs.json"
    out.write_text(json.dumps(record, indent=1) + "\n")
    print(f"{tokens} tokens ({tokenizer}) -> {out.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
