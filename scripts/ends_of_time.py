"""Why the first and last instants are a D-NeRF run's worst test views: the measurements of
docs/results/ends-of-time.md, from finished runs (nothing is trained).

For each run, on black (the peers' protocol) and at the run's resolution:

* ``test``: each test view's PSNR and time, the share of its squared error in its worst 1 %
  of pixels (an edge or a rim rather than the whole object), and what the training data gives
  it: training frames within +-0.05 of its time, the angle (degrees) from its camera to the
  nearest of their cameras, its camera's elevation and the share of training cameras lower
  (a grazing view few training views resemble);
* ``train_bins``: the training views' own PSNR in five time bins, and ``train_ends`` that of
  the three first, three middle and three last training frames (the ends' own frames: does
  the model fit them, or fail to generalise from them?);
* ``shifted``: the first and last test views (and a middle one for reference) rendered at
  their time moved towards the middle by 0.0025 to 0.04: a model whose state at the very end
  is off scores better a little inside;
* ``encoding``: how many of D_theta's time-encoding values the first and last instants share
  (`DeformConfig.time_frequency`).

    python scripts/ends_of_time.py RUN [RUN ...] --out docs/bench/ends-of-time.json [--threads 1]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
from pathlib import Path

import numpy as np
import torch

from sync4d.bench.measure import machine_info
from sync4d.metrics import psnr
from sync4d.phase1.deform import time_encoding
from sync4d.pipeline.evaluate import render_frame
from sync4d.runs import load_run

BLACK = (0.0, 0.0, 0.0)
SHIFTS = (0.0, 0.0025, 0.005, 0.01, 0.02, 0.04)
WINDOW = 0.05


def _view_dir(frame) -> np.ndarray:
    """The camera centre's direction from the origin (D-NeRF's cameras look at it)."""
    centre = np.asarray(frame.camera.center, np.float64)
    return centre / np.linalg.norm(centre)


def _score(model, frame, time: float, threads: int, detail: bool = False):
    """PSNR on black of `frame` rendered at `time`; with `detail`, also the share of the
    squared error in the image's worst 1 % of pixels."""
    target = torch.from_numpy(frame.load_image(BLACK))
    pred = render_frame(model, dataclasses.replace(frame, time=time), BLACK, threads)
    value = float(psnr(pred, target))
    if not detail:
        return value
    err = ((pred.clamp(0, 1) - target) ** 2).mean(-1).flatten().sort(descending=True).values
    return value, float(err[: max(1, err.numel() // 100)].sum() / err.sum().clamp_min(1e-30))


def _elevation(frame) -> float:
    """Degrees of the camera centre above the world's xy plane, seen from the origin (D-NeRF's
    z is up)."""
    d = _view_dir(frame)
    return float(np.degrees(np.arcsin(np.clip(d[2], -1.0, 1.0))))


def measure(run_dir: Path, threads: int) -> dict:
    run = load_run(run_dir)
    scene = run.scene()
    model = run.model
    train_t = np.array([f.time for f in scene.train])
    train_dirs = np.stack([_view_dir(f) for f in scene.train])
    train_elev = np.array([_elevation(f) for f in scene.train])
    test = []
    for f in sorted(scene.test, key=lambda f: f.time):
        near = np.abs(train_t - f.time) <= WINDOW + 1e-9
        cos = np.clip(train_dirs[near] @ _view_dir(f), -1.0, 1.0)
        value, top = _score(model, f, f.time, threads, detail=True)
        elev = _elevation(f)
        test.append({"name": f.name, "time": f.time, "psnr": value,
                     "error_share_worst_1pct_pixels": top,
                     "train_within_window": int(near.sum()),
                     "nearest_camera_deg": float(np.degrees(np.arccos(cos.max()))),
                     "elevation_deg": elev,
                     "train_below_elevation": float((train_elev < elev).mean())})  # fmt: skip
    edges = np.linspace(0.0, 1.0, 6)
    bins = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        fr = [f for f in scene.train if lo <= f.time < hi or (hi == 1.0 and f.time == 1.0)]
        scores = [_score(model, f, f.time, threads) for f in fr[:: max(1, len(fr) // 8)]]
        bins.append({"from": float(lo), "to": float(hi), "frames": len(scores),
                     "psnr": float(np.mean(scores))})  # fmt: skip
    by_time = sorted(scene.train, key=lambda f: f.time)
    middle = len(by_time) // 2
    train_ends = {
        where: [{"name": f.name, "time": f.time, "psnr": _score(model, f, f.time, threads)}
                for f in frames]
        for where, frames in (("first", by_time[:3]), ("middle", by_time[middle - 1:middle + 2]),
                              ("last", by_time[-3:]))
    }  # fmt: skip
    shifted = {}
    mid = min(scene.test, key=lambda f: abs(f.time - 0.5))
    for f, sign in ((min(scene.test, key=lambda f: f.time), 1.0),
                    (max(scene.test, key=lambda f: f.time), -1.0), (mid, 1.0)):  # fmt: skip
        shifted[f.name] = {"time": f.time, "psnr_at_shift": {
            f"{s:g}": _score(model, f, f.time + sign * s, threads) for s in SHIFTS}}  # fmt: skip
    dcfg = model.deform.config
    ends = time_encoding(torch.tensor([0.0, 1.0], dtype=torch.float64), dcfg.bands,
                         dcfg.time_frequency)  # fmt: skip
    shared = int(torch.isclose(ends[0], ends[1], atol=1e-9).sum())
    mean = float(np.mean([t["psnr"] for t in test]))
    worst = min(test, key=lambda t: t["psnr"])
    return {
        "run": str(run_dir),
        "scene": scene.name,
        "background": "black",
        "resolution": [scene.test[0].camera.width, scene.test[0].camera.height],
        "iterations": run.meta.get("iteration"),
        "mean_psnr": mean,
        "worst": {"name": worst["name"], "time": worst["time"], "psnr": worst["psnr"],
                  "below_mean_db": mean - worst["psnr"]},  # fmt: skip
        "test": test,
        "train_bins": bins,
        "train_ends": train_ends,
        "shifted": shifted,
        "encoding": {"time_frequency": dcfg.time_frequency, "bands": dcfg.bands,
                     "values": int(ends.shape[1]), "shared_by_t0_and_t1": shared},  # fmt: skip
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--threads", type=int, default=1)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    rec = {
        "benchmark": "ends of time (scripts/ends_of_time.py)",
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "window": WINDOW,
        "runs": [measure(r, a.threads) for r in a.runs],
    }
    a.out.write_text(json.dumps(rec, indent=1) + "\n")
    for r in rec["runs"]:
        t = r["test"]
        print(f"{r['scene']}: mean {r['mean_psnr']:.2f} dB on black, worst {r['worst']['name']} "
              f"t={r['worst']['time']:.2f} {r['worst']['psnr']:.2f} dB; ends "
              f"{t[0]['psnr']:.2f} / {t[-1]['psnr']:.2f} dB with {t[0]['train_within_window']} "
              f"/ {t[-1]['train_within_window']} training frames within +-{WINDOW} "
              f"(interior {t[len(t) // 2]['train_within_window']}); train bins "
              + " ".join(f"{b['psnr']:.2f}" for b in r["train_bins"]))
        print("  train views: " + "; ".join(
            f"{w} " + " ".join(f"t={f['time']:.3f}:{f['psnr']:.2f}" for f in fs)
            for w, fs in r["train_ends"].items()))
        for name, s in r["shifted"].items():
            print(f"  {name} t={s['time']:.2f}: " + " ".join(
                f"{k}:{v:.2f}" for k, v in s["psnr_at_shift"].items()))
        for v in (t[0], t[-1], min(t, key=lambda v: v["psnr"])):
            print(f"  {v['name']} t={v['time']:.2f}: {v['psnr']:.2f} dB, "
                  f"{v['error_share_worst_1pct_pixels']:.0%} of its error in 1 % of pixels, "
                  f"elevation {v['elevation_deg']:.1f} deg ({v['train_below_elevation']:.0%} of "
                  f"training cameras lower), nearest camera within +-{WINDOW}: "
                  f"{v['nearest_camera_deg']:.0f} deg")
        print(f"  encoding: t=0 and t=1 share {r['encoding']['shared_by_t0_and_t1']} of "
              f"{r['encoding']['values']} values (time_frequency "
              f"{r['encoding']['time_frequency']:.4g})")


if __name__ == "__main__":
    main()
