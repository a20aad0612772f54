#!/usr/bin/env sh
# Test PSNR against training time at several budgets (Pareto curve): writes bench-fit-NAME.json
# and bench-fit-NAME.png. Without a dataset it uses the embedded synthetic scene, e.g.
#   examples/bench_fit.sh
#   examples/bench_fit.sh path/to/dnerf/bouncingballs --config dnerf --iters 1000 2000 4000 8000
# With --runs it trains nothing and tabulates finished fit runs (one per scene, say), copying
# each one's worst test view beside the JSON:
#   examples/bench_fit.sh --runs runs/hook runs/lego --out scenes.json
set -eu
PY="${PYTHON:-python3}"
"$PY" -m sync4d bench fit "$@"
