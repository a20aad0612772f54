#!/usr/bin/env sh
# Your own video in: `sync4d process` recovers the camera poses of a video (or a folder of
# photos) with COLMAP and writes a dataset that `sync4d fit` trains on. So that this example
# needs no download, it first renders a short video of the textured synthetic scene (48 frames,
# 256x256, a camera moving on an arc); put your own video in its place:
#   sync4d process my_video.mp4 --out data/mine && sync4d fit data/mine
# Output: data/orbit.mp4, data/orbit/{transforms.json,images/,sparse_pc.ply,colmap/},
# runs/orbit/ (a short Phase 1 fit: its test PSNR is printed, about 17 dB). About 6 minutes
# on 2 cores, most of it the fit.
set -eu
PY="${PYTHON:-python3}"
mkdir -p data
"$PY" -c "from sync4d.data.synthetic import write_orbit_video; write_orbit_video('data/orbit.mp4')"
"$PY" -m sync4d process data/orbit.mp4 --out data/orbit --force
"$PY" -m sync4d fit data/orbit --out runs/orbit --force --iters 300 --phases 1 \
    --set eval_every=0 "$@"
