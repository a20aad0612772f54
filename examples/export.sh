#!/usr/bin/env sh
# Write a run as files other tools read (docs/export.md): the scene description (JSON + an
# embeddings side file), a text summary for an LLM, the canonical Gaussians and the scene at
# t = 0.5 as 3DGS PLY, an SPZ, and the scene over time: a folder of PLYs that SuperSplat
# imports as a sequence (drop the folder; times in sequence.json beside it) and a delta-frame
# PLY (brush 0.3 and earlier play it).
# The scene description and the prompt need the run's language field:
#   python3 -m sync4d fit --out "$RUN" --phases 3
set -eu
RUN="${1:-runs/synthetic}"
OUT="${2:-$RUN/export}"
PY="${PYTHON:-python3}"
mkdir -p "$OUT"
printf 'a red ball\na blue ball\na green ball\na red object\na blue box\n' > "$OUT/vocab.txt"
"$PY" -m sync4d export "$RUN" --scene "$OUT/scene.json" --prompt "$OUT/prompt.txt" \
    --vocab "$OUT/vocab.txt" --query "a ball touching the ground"
"$PY" -m sync4d export "$RUN" --ply "$OUT/canonical.ply"
"$PY" -m sync4d export "$RUN" --ply "$OUT/t0.5.ply" --spz "$OUT/t0.5.spz" --time 0.5
"$PY" -m sync4d export "$RUN" --sequence "$OUT/sequence/"
"$PY" -m sync4d export "$RUN" --sequence "$OUT/sequence.ply"
# The open .4dgs container (an optional writer: pip install 'sync4d[4dgs]'): objects, their
# tracks and Phase 3's embeddings, D_theta's residual where a track alone is a pixel off (the
# default is a quarter); one instant as glTF. Then the objects moved by their tracks alone.
if "$PY" -c "import fourdgs" 2>/dev/null; then
    "$PY" -m sync4d export "$RUN" --4dgs "$OUT/scene.4dgs" --4dgs-tolerance 1 \
        --4dgs-snapshot "$OUT/t0.5.glb" --time 0.5
    "$PY" -m sync4d export "$RUN" --4dgs "$OUT/rigid.4dgs" --4dgs-residual background
else
    echo "skipped --4dgs: its writer is not installed (pip install 'sync4d[4dgs]')"
fi
