#!/usr/bin/env sh
# Phase 2 (object motion) on a run whose Phase 1 is done: `fit` runs both phases by default;
# --phases 2 redoes Phase 2 alone from RUN/phase1.safetensors, here with the affine M_phi and
# without the rigid-share hinge (an ablation), e.g.
#   examples/fit_phase2.sh runs/synthetic
# then read RUN/phase2.json (rigid share, residuals, shuffle test) and RUN/eval.json.
set -eu
PY="${PYTHON:-python3}"
RUN="${1:-runs/synthetic}"
shift || true
"$PY" -m sync4d fit --out "$RUN" --phases 2 --set phase2.motion.kind=affine \
    --set phase2.hinge=false "$@"
