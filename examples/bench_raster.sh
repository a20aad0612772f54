#!/usr/bin/env sh
# Full rasterizer benchmark grid (N 10k/100k/1M x 256x256/800x800/960x536 x 1/2 threads, gsplat torch reference for N <= 100k); writes bench-raster.json. Extra flags pass through, e.g. --quick.
OMP_NUM_THREADS=2 "${PYTHON:-python3}" -m sync4d bench raster --out bench-raster.json "$@"
