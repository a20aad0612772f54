#!/usr/bin/env sh
# Time the viewer's answer to the time slider on a run: slider moves to new and to cached times
# (from the change to the splats sent) and one query; prints a table, writes bench-view.json.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d bench view "$RUN" --moves 30 --out bench-view.json
