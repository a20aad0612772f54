#!/usr/bin/env sh
# Render a run's first test camera over a 48-frame time sweep (PNGs + GIF in RUN/renders), then
# three chosen times from the second training camera.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d render "$RUN"
"$PY" -m sync4d render "$RUN" --camera train:1 --time 0 0.5 1 --no-gif
