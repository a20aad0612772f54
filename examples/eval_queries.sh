#!/usr/bin/env sh
# Evaluate temporal queries (Acc, vIoU, tIoU; Appendix F) on a run's language field. QUERIES is
# our query JSON (docs/phase3-queries.md), a 4D LangSplat annotations folder, or for a run of
# the embedded scene its ground_truth.json (the default here).
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
QUERIES="${2:-$("$PY" -c 'from sync4d.data.synthetic import default_scene_dir as d; print(d() / "ground_truth.json")')}"
"$PY" -m sync4d eval "$RUN" --queries "$QUERIES"
