#!/usr/bin/env sh
# Ask a run's language field which object matches each text, and when; prints a table per query
# and writes a timeline PNG into RUN/phase3/ (add --json for the answers as data).
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d query "$RUN" "the red ball while it is falling" "the blue box at rest" \
    "the fastest object" "a ball touching the ground"
