#!/usr/bin/env sh
# Phase 3's build time (observe, encode, field) and query latency (cold and cached) on finished
# Phase 2 runs; writes bench-phase3.json. The runs are not modified.
set -eu
PY="${PYTHON:-python3}"
"$PY" -m sync4d bench phase3 "${@:-runs/synthetic}" --threads 2
