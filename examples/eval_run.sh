#!/usr/bin/env sh
# Evaluate a run on its test split (PSNR, SSIM, LPIPS-Alex per frame and mean) -> RUN/eval.json.
set -eu
RUN="${1:-runs/synthetic}"
PY="${PYTHON:-python3}"
"$PY" -m sync4d eval "$RUN"
