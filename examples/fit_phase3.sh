#!/usr/bin/env sh
# Build the language field (Phase 3) of a finished Phase 2 run -> RUN/phase3/.
# ENCODER: a SigLIP-ONNX folder (examples/encoder_convert.sh) or "offline" (the default:
# closed-vocabulary, colours and shapes).
set -eu
RUN="${1:-runs/synthetic}"
ENCODER="${ENCODER:-offline}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d fit --out "$RUN" --phases 3 --encoder "$ENCODER"
