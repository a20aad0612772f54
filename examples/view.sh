#!/usr/bin/env sh
# Open a run in the browser (http://localhost:8080): scrub time, show or isolate objects, ask the
# language field a question and watch the answer light up. Ctrl-C (or closing the tab) stops it.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
exec "$PY" -m sync4d view "$RUN" --port "${PORT:-8080}"
