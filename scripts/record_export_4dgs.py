"""Write docs/bench/export-4dgs-bouncingballs.json: docs/export.md's `.4dgs` figures, measured by
exporting a bouncingballs run with Phases 1-3 into a temporary folder (`sync4d export RUN --4dgs
FILE` with `--4dgs-residual` and `--4dgs-tolerance` variants, and two ablations through
`write_4dgs`: M_phi's poses as stored, colours clipped without the SH refit), validating each
file with fourdgs' validator, reading it back with `fourdgs.read` and rendering the format's own
object-layer state (`Scene.state_at`) with sync4d's rasterizer:

- per file: its size, the Gaussian records, how many Gaussians hold a residual, the write and
  read seconds, the validator's errors;
- per test view (each at its own time): PSNR against the dataset's image on the run's white
  background and on black (the peers' protocol), of the run's own render (`model.render`,
  D_theta) and of the file's; the file's PSNR against the run's render; renders clamped to
  [0, 1] as `sync4d eval` scores;
- the five times: the test views nearest t = 0, 0.25, 0.5, 0.75 and 1, and how many of them
  (and of all test views) the file is at most 1 dB below the run on each background;
- the size of the PLY sequence of the same run at its stored frames (`--sequence DIR/`);
- the embedding round trip: each object's embedding read back, ranked against the others for
  its name through the field's own text encoder.

The run folder is only read (`sync4d export` writes only the files it names).

    OMP_NUM_THREADS=1 python scripts/record_export_4dgs.py RUN --masks   # bouncingballs
    OMP_NUM_THREADS=1 python scripts/record_export_4dgs.py RUN --views 20 \
        --out docs/bench/export-4dgs-basketball.json
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import json
import math
import re
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
FIVE = (0.0, 0.25, 0.5, 0.75, 1.0)
#: (id, name, command-line options, write_4dgs keywords for an ablation instead of the command)
VARIANTS: tuple[tuple[str, str, list[str], dict], ...] = (
    ("none", "tracks alone, still background", ["--4dgs-residual", "none"], {}),
    ("background", "tracks alone move the objects, background residual",
     ["--4dgs-residual", "background"], {}),
    *((f"all-{t}", f"residual, tolerance {t} px", ["--4dgs-tolerance", str(t)], {})
      for t in (1.0, 0.5, 0.25, 0.1, 0.05)),
    ("stored-poses", "residual, tolerance 0.25 px, M_phi's poses as stored", [],
     {"refine": False}),
    ("clipped", "residual, tolerance 0.25 px, colours clipped (no SH refit)", [],
     {"fit_colours": False}),
)  # fmt: skip
BACKGROUNDS = {"white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0)}


def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.clamp(0.0, 1.0), b.clamp(0.0, 1.0)
    return float(-10.0 * math.log10(max(float(((a - b) ** 2).mean()), 1e-20)))


def _size(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() \
        else path.stat().st_size


def _views(run, tests, render) -> list[dict]:
    """Per test view: its time and, per background, PSNR of `render(frame, bg)` against the
    image (and the image itself, kept out of the record)."""
    out = []
    for f in tests:
        row: dict = {"time": float(f.time)}
        for name, colour in BACKGROUNDS.items():
            gt = torch.as_tensor(f.load_image(colour), dtype=torch.float32)
            img = render(f, torch.tensor(colour, dtype=torch.float32))
            row[name] = {"psnr": _psnr(img, gt), "_image": img}
        out.append(row)
    return out


def _summary(views: list[dict], run_views: list[dict], five: list[int]) -> dict:
    """The file's views against the run's: PSNR means, the diff per view, the five times."""
    out: dict = {}
    for name in BACKGROUNDS:
        diff = [v[name]["psnr"] - r[name]["psnr"] for v, r in zip(views, run_views, strict=True)]
        out[name] = {
            "psnr_mean": float(np.mean([v[name]["psnr"] for v in views])),
            "diff_mean": float(np.mean(diff)), "diff_min": float(np.min(diff)),
            "within_1db": int(sum(d >= -1.0 for d in diff)), "views": len(diff),
            "five_times": [{"time": views[i]["time"], "diff": diff[i]} for i in five],
            "five_within_1db": int(sum(diff[i] >= -1.0 for i in five)),
            "vs_run_psnr_mean": float(np.mean([_psnr(v[name]["_image"], r[name]["_image"])
                                               for v, r in zip(views, run_views, strict=True)])),
        }  # fmt: skip
    return out


def _mask_axis_ratios(run, bins: tuple[float, ...] = (0.0, 0.2, 0.4, 0.5, 0.55, 0.6, 0.65,
                                                          0.7, 0.8, 1.01)) -> dict:  # fmt: skip
    """Whether the dataset's balls squash: per object and time bin, the median over the training
    frames of the ratio of the major to the minor axis of the object's instance mask (second
    moments; a sphere's projection is near 1, a ball squashed at a bounce wider)."""
    scene = run.scene()
    rows = []
    for f in scene.train:
        mask = f.load_mask()
        if mask is None:
            return {}
        row = [float(f.time)]
        for k in sorted(run.names):
            if k == 0:
                continue
            ys, xs = np.nonzero(np.asarray(mask) == k)
            if len(xs) < 50:
                row.append(float("nan"))
                continue
            ev = np.linalg.eigvalsh(np.cov(np.stack([xs, ys])))
            row.append(float(np.sqrt(ev[1] / ev[0])))
        rows.append(row)
    arr = np.asarray(rows)
    out = {}
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = (arr[:, 0] >= lo) & (arr[:, 0] < hi)
        out[f"{lo}-{hi}"] = {"frames": int(sel.sum()), **{
            run.names[k]: float(np.nanmedian(arr[sel, i + 1]))
            for i, k in enumerate(k for k in sorted(run.names) if k)}}
    return out


def _source(run_dir: str) -> object:
    """How the run was trained (the `fit` invocations in its run.json)."""
    try:
        return json.loads((Path(run_dir) / "run.json").read_text()).get("command")
    except (OSError, ValueError):
        return None


def _strip(views: list[dict]) -> list[dict]:
    return [{"time": v["time"], **{n: {"psnr": v[n]["psnr"]} for n in BACKGROUNDS}}
            for v in views]  # fmt: skip


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a run folder with Phase 2 (and 3 for the embeddings)")
    ap.add_argument("--out", type=Path, default=OUT, help=f"the record (default {OUT})")
    ap.add_argument("--views", type=int, default=0,
                    help="score N test views, evenly picked (default: all)")
    ap.add_argument("--masks", action="store_true",
                    help="also the instance masks' axis ratios by time (balls that squash)")
    args = ap.parse_args(argv)
    return record(args.run, args.out, args.views, args.masks)


def record(run_dir: str, out_path: Path, views: int, masks: bool) -> int:
    from sync4d.export.fourdgs import write_4dgs
    from sync4d.phase3.encoders.encoder import load_encoder
    from sync4d.phase3.store import load_field

    torch.set_num_threads(1)
    run = load_run(run_dir)
    model = run.model
    scene = run.scene()
    tests = list(scene.test) if scene is not None else []
    if views and len(tests) > views:
        tests = [tests[i] for i in np.unique(np.linspace(0, len(tests) - 1, views).astype(int))]
    if not tests:
        print(f"{run_dir}: the run's dataset has no test views to score against", file=sys.stderr)
        return 2
    five = sorted({int(np.argmin([abs(f.time - t) for f in tests])) for t in FIVE})
    with torch.no_grad():
        run_views = _views(run, tests, lambda f, bg: model.render(
            f.camera, f.time, background=bg, threads=1).features)
    files = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (key, name, flags, kw) in enumerate(VARIANTS):
            path = Path(tmp) / f"bb-{i}.4dgs"
            out = io.StringIO()
            start = time.perf_counter()
            if kw:
                rep = write_4dgs(path, run, **kw)
                printed = f"write_4dgs(path, run, {', '.join(f'{k}={v}' for k, v in kw.items())})"
                residual = rep.residual_gaussians
            else:
                with contextlib.redirect_stdout(out):
                    assert cli(["export", run_dir, "--4dgs", str(path), "--threads", "1",
                                *flags]) == 0  # fmt: skip
                printed = out.getvalue().strip()
                found = re.search(r"residual on ([\d,]+) Gaussians", printed)
                residual = int(found.group(1).replace(",", "")) if found else 0
            write_s = time.perf_counter() - start
            start = time.perf_counter()
            errors = validate_4dgs(path)
            validate_s = time.perf_counter() - start
            start = time.perf_counter()
            sc = read_4dgs(path)
            read_s = time.perf_counter() - start
            views = _views(run, tests, lambda f, bg, sc=sc: render_4dgs(
                sc, f.camera, f.time, near=model.near, background=bg, threads=1))
            records = int(sc.gaussians.count)
            emb = {}
            if i == 0 and (run.path / "phase3").is_dir():  # embeddings: a run with Phase 3
                field = load_field(run.path)
                enc = load_encoder(field.encoder["kind"])
                rows = [e for e in sc.objects.table.entries if e.embedding is not None]
                mat = np.asarray([e.embedding for e in rows], dtype=np.float64)
                mat /= np.linalg.norm(mat, axis=1, keepdims=True)
                txt = np.asarray(enc.encode_texts([e.label for e in rows]), dtype=np.float64)
                txt /= np.linalg.norm(txt, axis=1, keepdims=True)
                sims = txt @ mat.T
                emb = {e.label: {"rank_of_own_object": int(1 + np.sum(sims[j] > sims[j, j])),
                                 "cosine": float(sims[j, j])} for j, e in enumerate(rows)}
            files.append({
                "id": key, "variant": name, "options": flags, "write_4dgs": kw,
                "bytes": path.stat().st_size, "mb": path.stat().st_size / 1e6,
                "gaussian_records": records, "residual_gaussians": residual,
                "printed": printed,
                "export_seconds": write_s, "validate_seconds": validate_s,
                "read_seconds": read_s, "validator_errors": errors,
                "summary": _summary(views, run_views, five), "views": _strip(views),
                "embeddings": emb,
            })  # fmt: skip
            s = files[-1]["summary"]
            print(f"{name}: {files[-1]['mb']:.2f} MB, white {s['white']['diff_mean']:+.2f} dB "
                  f"(five within 1 dB: {s['white']['five_within_1db']}), black "
                  f"{s['black']['diff_mean']:+.2f}", flush=True)
        seq = Path(tmp) / "seq"
        with contextlib.redirect_stdout(io.StringIO()):
            assert cli(["export", run_dir, "--sequence", f"{seq}/", "--threads", "1"]) == 0
        seq_bytes = _size(seq)
    rec = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "OMP_NUM_THREADS=1 python scripts/record_export_4dgs.py "
                   + " ".join(sys.argv[1:]) + " (exports: sync4d export RUN --4dgs FILE "
                   "[--4dgs-residual R] [--4dgs-tolerance T], write_4dgs for the ablations, "
                   "and --sequence DIR/)",
        "machine": machine_info(),
        "run": {"run": run_dir, "fit": _source(run_dir), "gaussians": model.num_gaussians,
                "frames": len(run.times),
                "objects": {str(k): v for k, v in run.names.items()},
                "train_background": run.settings["config"]["phase1"].get("train_background"),
                "resolution": f"{tests[0].camera.width}x{tests[0].camera.height}",
                "phase1_iterations": run.settings["config"]["phase1"]["iterations"]},
        "test_views": len(tests),
        "five_times": {"asked": list(FIVE), "views": [tests[i].time for i in five]},
        "run_views": _strip(run_views),
        "run_psnr_mean": {n: float(np.mean([v[n]["psnr"] for v in run_views]))
                          for n in BACKGROUNDS},
        "files": files,
        **({"mask_axis_ratio_by_time": _mask_axis_ratios(run)} if masks else {}),
        "ply_sequence": {"frames": len(run.times), "bytes": seq_bytes, "mb": seq_bytes / 1e6},
    }
    out_path.write_text(json.dumps(rec, indent=1) + "\n")
    print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
