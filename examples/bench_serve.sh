#!/usr/bin/env sh
# Time `sync4d serve` as agents meet it on a run with a language field (fit --phases 1,2,3): the
# first `describe` over stdio, then 16 concurrent MCP clients over streamable HTTP, 20 calls
# each (query, relational question, track, events, render); prints p50 / p95 per tool and
# writes bench-serve.json. Exits 1 when any call failed.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d bench serve "$RUN" --clients 16 --calls 20 --threads 1 --out bench-serve.json
