#!/usr/bin/env sh
# Test PSNR against training time at several budgets (Pareto curve): writes bench-fit-NAME.json
# and bench-fit-NAME.png. Without a dataset it uses the embedded synthetic scene, e.g.
#   examples/bench_fit.sh
#   examples/bench_fit.sh path/to/dnerf/bouncingballs --config dnerf --iters 1000 2000 4000 8000
set -eu
PY="${PYTHON:-.venv/bin/python}"
"$PY" -m sync4d bench fit "$@"
