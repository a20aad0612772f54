#!/usr/bin/env sh
# Train Phase 1 on a D-NeRF scene at 400x400 with the CPU config, e.g.
#   examples/fit_dnerf.sh path/to/dnerf/bouncingballs
# Ctrl-C saves a checkpoint; run the same command with --resume to continue.
set -eu
DATA="${1:?usage: fit_dnerf.sh DNERF_SCENE_DIR [fit options]}"
shift
PY="${PYTHON:-python3}"
"$PY" -m sync4d fit "$DATA" --out "runs/$(basename "$DATA")" --config dnerf "$@"
