"""Write docs/bench/export-4dgs-bouncingballs.json: docs/export.md's `.4dgs` figures, measured by
exporting a bouncingballs run with Phases 1-3 (`sync4d export RUN --4dgs FILE`, with and without
`--4dgs-keyframes K`) into a temporary folder, validating each file with fourdgs' validator,
reading it back with `fourdgs.read` and rendering the format's own object-layer state
(`Scene.state_at`) with sync4d's rasterizer:

- per file: its size, the Gaussian records, the write and read seconds, the validator's errors;
- PSNR of the file's render against the run's own render (`model.render`, D_theta) at five
  times from the first training camera;
- PSNR against the dataset's test images (every test view at its own time) of the run's render
  and of each file's render;
- the size of the PLY sequence of the same run at its stored frames (`--sequence DIR/`);
- the embedding round trip: each object's embedding read back, ranked against the others for
  its name through the field's own text encoder.

The run folder is only read (`sync4d export` writes only the files it names).

    OMP_NUM_THREADS=1 python scripts/record_export_4dgs.py RUN
"""

from __future__ import annotations

import contextlib
import datetime
import io
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from sync4d.bench.measure import machine_info
from sync4d.cli import main as cli
from sync4d.export.fourdgs import read_4dgs, render_4dgs, validate_4dgs
from sync4d.runs import load_run

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "bench" / "export-4dgs-bouncingballs.json"
TIMES = (0.0, 0.25, 0.5, 0.75, 1.0)
KEYFRAMES = (0, 10, 30)


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(-10.0 * math.log10(float(((a - b) ** 2).mean())))


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() \
        else path.stat().st_size


def main(run_dir: str) -> int:
    from sync4d.data.scene import Camera
    from sync4d.phase3.encoders.encoder import load_encoder
    from sync4d.phase3.store import load_field

    torch.set_num_threads(1)
    run = load_run(run_dir)
    model = run.model
    bg = torch.tensor(run.background, dtype=torch.float32)
    c = run.cameras[0]
    cam = Camera(viewmat=np.asarray(c["viewmat"], dtype=np.float64).reshape(4, 4), fx=c["fx"],
                 fy=c["fy"], cx=c["cx"], cy=c["cy"], width=c["width"], height=c["height"])
    scene = run.scene()
    tests = scene.test if scene is not None else []
    with torch.no_grad():
        own = {t: model.render(cam, t, background=bg, threads=1).features for t in TIMES}
        gts = [torch.as_tensor(f.load_image(tuple(run.background)), dtype=torch.float32)
               for f in tests]
        run_test = [_psnr(model.render(f.camera, f.time, background=bg, threads=1).features, g)
                    for f, g in zip(tests, gts, strict=True)]
    files = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in KEYFRAMES:
            path = Path(tmp) / f"bb-k{k}.4dgs"
            args = ["export", run_dir, "--4dgs", str(path), "--threads", "1"]
            if k:
                args += ["--4dgs-keyframes", str(k)]
            out = io.StringIO()
            start = time.perf_counter()
            with contextlib.redirect_stdout(out):
                assert cli(args) == 0
            write_s = time.perf_counter() - start
            start = time.perf_counter()
            errors = validate_4dgs(path)
            validate_s = time.perf_counter() - start
            start = time.perf_counter()
            sc = read_4dgs(path)
            read_s = time.perf_counter() - start
            per_time = [{"time": t, "psnr_vs_run_render": _psnr(
                render_4dgs(sc, cam, t, near=model.near, background=bg, threads=1), own[t])}
                for t in TIMES]  # fmt: skip
            test = [_psnr(render_4dgs(sc, f.camera, f.time, near=model.near, background=bg,
                                      threads=1), g) for f, g in zip(tests, gts, strict=True)]
            emb = {}
            if k == 0:
                field = load_field(run.path)
                enc = load_encoder(field.encoder["kind"])
                table = sc.objects.table
                rows = [e for e in table.entries if e.embedding is not None]
                mat = np.asarray([e.embedding for e in rows], dtype=np.float64)
                mat /= np.linalg.norm(mat, axis=1, keepdims=True)
                txt = np.asarray(enc.encode_texts([e.label for e in rows]), dtype=np.float64)
                txt /= np.linalg.norm(txt, axis=1, keepdims=True)
                sims = txt @ mat.T
                emb = {e.label: {"rank_of_own_object": int(1 + np.sum(sims[i] > sims[i, i])),
                                 "cosine": float(sims[i, i])} for i, e in enumerate(rows)}
            files.append({
                "keyframes": k, "residual": "none" if k == 0 else f"{k} keyframe segments",
                "bytes": path.stat().st_size, "mb": path.stat().st_size / 1e6,
                "gaussian_records": int(sc.gaussians.count), "printed": out.getvalue().strip(),
                "export_seconds": write_s, "validate_seconds": validate_s,
                "read_seconds": read_s, "validator_errors": errors, "times": per_time,
                "test_psnr_mean": float(np.mean(test)) if test else None,
                "embeddings": emb,
            })  # fmt: skip
        seq = Path(tmp) / "seq"
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli(["export", run_dir, "--sequence", f"{seq}/", "--threads", "1"]) == 0
        seq_bytes = _size(seq)
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": f"OMP_NUM_THREADS=1 python scripts/record_export_4dgs.py RUN (RUN: {run_dir}, "
                   "a copy of /tmp/s4d/bb-cfg; exports: sync4d export RUN --4dgs FILE "
                   "[--4dgs-keyframes K] and --sequence DIR/)",
        "machine": machine_info(),
        "run": {"run": run_dir, "gaussians": model.num_gaussians, "frames": len(run.times),
                "objects": {str(k): v for k, v in run.names.items()}},
        "camera": "the run's first training camera (cameras[0])",
        "test_views": len(tests),
        "run_test_psnr_mean": float(np.mean(run_test)) if run_test else None,
        "files": files,
        "ply_sequence": {"frames": len(run.times), "bytes": seq_bytes, "mb": seq_bytes / 1e6},
    }
    OUT.write_text(json.dumps(record, indent=1) + "\n")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
