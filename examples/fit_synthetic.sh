#!/usr/bin/env sh
# Train Phase 1 and Phase 2 on the embedded synthetic scene (generated on first use, no
# download), then print the test PSNR / SSIM / LPIPS table and the Phase 2 diagnostics.
# Output: runs/synthetic/{checkpoint.safetensors,phase1.safetensors,eval.json,phase2.json,
# renders/test/*.png}.
set -eu
PY="${PYTHON:-python3}"
"$PY" -m sync4d fit --out runs/synthetic --force "$@"
