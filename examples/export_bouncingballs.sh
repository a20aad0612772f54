#!/usr/bin/env sh
# How examples/bouncingballs-prompt.txt was made (2026-12-05, 2 cores shared with other jobs): a
# D-NeRF bouncingballs run through Phases 1-3 at the dnerf config of that day (9900 + Phase 2
# iterations, 43 minutes of training: 39.82 dB), then its prompt for an LLM and scene
# description.
# DATA: the D-NeRF bouncingballs folder (not shipped with sync4d).
set -eu
DATA="${1:?usage: export_bouncingballs.sh path/to/dnerf/bouncingballs [RUN]}"
RUN="${2:-runs/bb}"
PY="${PYTHON:-python3}"
HERE="$(cd "$(dirname "$0")" && pwd)"
"$PY" -m sync4d fit "$DATA" --out "$RUN" --config dnerf --phases 1,2,3
"$PY" -m sync4d export "$RUN" --vocab "$HERE/bouncingballs-vocab.txt" \
    --query "a ball touching the floor" --scene "$RUN/scene.json" \
    --prompt "$HERE/bouncingballs-prompt.txt"
