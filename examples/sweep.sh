#!/usr/bin/env sh
# Fit the D-NeRF scenes of examples/sweep_dnerf.toml on Ray (local: every core; a cluster:
# ADDRESS=auto or HOST:PORT), then print the table; a second run continues where it stopped.
set -eu
OUT="${1:-sweeps/dnerf}"
PY="${PYTHON:-python3}"
HERE="$(cd "$(dirname "$0")" && pwd)"
if [ -n "${ADDRESS:-}" ]; then
    exec "$PY" -m sync4d sweep "$HERE/sweep_dnerf.toml" --out "$OUT" --address "$ADDRESS"
fi
exec "$PY" -m sync4d sweep "$HERE/sweep_dnerf.toml" --out "$OUT"
