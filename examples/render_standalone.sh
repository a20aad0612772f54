#!/usr/bin/env sh
# Render a checkpoint with the standalone Rust renderer (no Python at run time): one view at a
# time between training frames, a 48-frame time sweep, and a 36-view orbit through wgpu (a GPU,
# or lavapipe on a CPU). Train a run first, e.g. `python -m sync4d fit --out runs/synthetic`.
#   examples/render_standalone.sh runs/synthetic
set -eu
RUN="${1:-runs/synthetic}"
cargo build --release -p sync4d-render
BIN=target/release/sync4d-render
"$BIN" "$RUN" --camera test:0 --time 0.37 --out "$RUN/standalone.png"
"$BIN" "$RUN" --sweep 48 --out "$RUN/standalone-sweep"
"$BIN" "$RUN" --orbit 36 --time 0.5 --backend auto --out "$RUN/standalone-orbit"
