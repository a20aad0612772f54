#!/usr/bin/env sh
# Train Phase 1 on the embedded synthetic scene (generated on first use, no download), then print
# the test PSNR / SSIM / LPIPS table. Output: runs/synthetic/{checkpoint.safetensors,eval.json,...}.
set -eu
PY="${PYTHON:-.venv/bin/python}"
"$PY" -m sync4d fit --out runs/synthetic --force "$@"
