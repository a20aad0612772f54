#!/usr/bin/env sh
# Convert SigLIP to ONNX for Phase 3 (needs internet once, and the export extra:
# pip install 'sync4d[export]'). Then: fit --out RUN --phases 3 --encoder encoders/siglip, or
# export SYNC4D_ENCODER=encoders/siglip.
set -eu
OUT="${1:-encoders/siglip}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d encoder convert --model google/siglip-base-patch16-224 --out "$OUT"
"$PY" -m sync4d encoder info "$OUT"
