"""Write docs/bench/run-contract.json: the measurements of docs/results/run-contract.md other
than the SIGKILL test's (that test writes its own record, docs/bench/run-contract-sigkill.json),
with the date, the command and the machine (docs/bench/README.md):

- `fit --iters 30 --threads 2` on the embedded scene: wall seconds of the command and the
  training seconds it records (`--iters` bounds both phases);
- `load_scene` (the loader, then every image and mask header checked by `check_scene`) on
  D-NeRF bouncingballs and the Panoptic capture: seconds, frames, masks;
- the pose tolerance: max over every frame of max |R^T R - I| for each D-NeRF scene (all
  splits) and the Panoptic capture's w2c, and for the D-NeRF rotations rounded to 6, 4 and 3
  decimals, each against `sync4d.data.scene.POSE_TOLERANCE`.

    OMP_NUM_THREADS=1 RAYON_NUM_THREADS=1 python scripts/record_run_contract.py [DATA]

DATA: the folder holding dnerf/ and panoptic/ (default: ../shared/data, else shared/data).
"""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sync4d.bench.measure import machine_info
from sync4d.data import load_scene
from sync4d.data.scene import POSE_TOLERANCE, check_scene

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "bench" / "run-contract.json"
DNERF_SCENES = ("bouncingballs", "hellwarrior", "hook", "lego")


def fit_iters30() -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "iters30"
        argv = [sys.executable, "-m", "sync4d", "fit", "--out", str(out), "--iters", "30",
                "--threads", "2"]  # fmt: skip
        t0 = time.perf_counter()
        subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        rows = [json.loads(ln) for ln in (out / "metrics.jsonl").read_text().splitlines()]
        timed = [r for r in rows if "train_seconds" in r]
        return {
            "command": "python -m sync4d fit --out RUN --iters 30 --threads 2 (embedded scene)",
            "wall_seconds": wall,
            "train_seconds": timed[-1]["train_seconds"],
            "last_phase": timed[-1].get("phase"),
            "last_iteration": timed[-1].get("iteration"),
        }


def load_timing(path: Path) -> dict:
    t0 = time.perf_counter()
    scene = load_scene(path)
    seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    check_scene(scene)
    check_seconds = time.perf_counter() - t0
    frames = scene.train + scene.test
    return {
        "path": str(path),
        "load_scene_seconds": seconds,
        "check_scene_seconds": check_seconds,
        "frames": len(frames),
        "train": len(scene.train),
        "test": len(scene.test),
        "masks": sum(f.mask_path is not None for f in frames),
    }


def deviation(r: np.ndarray) -> float:
    return float(np.abs(r.T @ r - np.eye(3)).max())


def dnerf_rotations(scene: Path) -> list[np.ndarray]:
    out = []
    for split in ("train", "val", "test"):
        f = scene / f"transforms_{split}.json"
        if f.exists():
            for frame in json.loads(f.read_text())["frames"]:
                out.append(np.asarray(frame["transform_matrix"], dtype=np.float64)[:3, :3])
    return out


def panoptic_rotations(scene: Path) -> list[np.ndarray]:
    out = []
    for name in ("train_meta.json", "test_meta.json"):
        meta = json.loads((scene / name).read_text())
        for per_time in meta["w2c"]:
            out += [np.asarray(m, dtype=np.float64)[:3, :3] for m in per_time]
    return out


def poses(data: Path, panoptic: Path) -> dict:
    result: dict = {"tolerance": POSE_TOLERANCE, "max_deviation": {}, "frames": {}}
    every = []
    for name in DNERF_SCENES:
        rots = dnerf_rotations(data / "dnerf" / name)
        every += rots
        result["max_deviation"][f"dnerf/{name}"] = max(deviation(r) for r in rots)
        result["frames"][f"dnerf/{name}"] = len(rots)
    rots = panoptic_rotations(panoptic)
    result["max_deviation"][f"panoptic/{panoptic.name}"] = max(deviation(r) for r in rots)
    result["frames"][f"panoptic/{panoptic.name}"] = len(rots)
    rounded = {}
    for decimals in (6, 4, 3):
        dev = max(deviation(np.round(r, decimals)) for r in every)
        rounded[str(decimals)] = {"max_deviation": dev, "accepted": dev <= POSE_TOLERANCE}
    result["dnerf_rounded"] = rounded
    return result


def main() -> int:
    if len(sys.argv) > 1:
        data = Path(sys.argv[1])
    else:
        data = next((p for p in (ROOT.parent / "shared" / "data", ROOT / "shared" / "data")
                     if p.is_dir()), None)  # fmt: skip
        if data is None:
            print("no shared data: pass the folder holding dnerf/ and panoptic/", file=sys.stderr)
            return 2
    panoptic = sorted((data / "panoptic").iterdir())[0]
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": "OMP_NUM_THREADS=1 RAYON_NUM_THREADS=1 python scripts/record_run_contract.py",
        "machine": {**machine_info(), "note": "2 cores shared with other jobs"},
        "iters30": fit_iters30(),
        "load_scene": {
            "dnerf/bouncingballs": load_timing(data / "dnerf" / "bouncingballs"),
            f"panoptic/{panoptic.name}": load_timing(panoptic),
        },
        "poses": poses(data, panoptic),
    }
    OUT.write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
