"""Fingerprints of everything a small run writes and answers, to show that a restructure
changes nothing (issue 63's acceptance: bit-identical before and after).

    python scripts/fingerprint_runs.py --out /tmp/before.json          # on the old code
    python scripts/fingerprint_runs.py --out /tmp/after.json --against /tmp/before.json

It writes the embedded scene, fits it for 60 iterations through Phases 1-3 once per motion
model (`gaussians`, `nodes`) at one thread, then asks `query` (a state and a relational
question, `--json`), `export` (scene description, prompt, PLY at t = 0.5, SPZ) and `render`
(one view), and hashes: every tensor of every safetensors file (name, dtype, shape, bytes),
every PNG's pixels, every JSON and JSONL document with its clock readings removed (keys that
hold dates, durations, process ids, memory or machine facts, and the checkpoint file's
hash, whose header holds the training time: VOLATILE), and every other
file's bytes. Text has the work folder's path replaced by ``WORK``, so two invocations may
use different folders. `--against` prints each fingerprint that differs and exits 1 when any
does.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

VOLATILE = re.compile(
    r"(^|_)(date|created|seconds|secs|elapsed|wall|pid|host|hostname|machine|platform|"
    r"duration|started|finished|timestamp|rss|mib|eta|rate|per_s|ms|s|when|cpu|cpus|"
    r"threads_info|python|versions?|it_s|time|sha256)($|_)|_s$|_ms$",
    re.I,
)
MOTIONS = ("gaussians", "nodes")
QUESTIONS = ("the red ball rising", "the ball that lands first")


def _clean(value: object) -> object:
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in sorted(value.items()) if not VOLATILE.search(str(k))}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    return value


def _digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def fingerprint_file(path: Path, out: dict[str, str], name: str, work: Path,
                     keep: Path | None = None) -> None:  # fmt: skip
    """Add `path`'s fingerprints to `out` under `name`; text has the `work` folder's path
    replaced by ``WORK``, and with `keep` the text hashed is also written there."""

    def text(s: str) -> bytes:
        s = s.replace(str(work), "WORK")
        s = re.sub(r"checkpoint [0-9a-f]{12}", "checkpoint HASH", s)  # its header holds clocks
        if keep is not None:
            (keep / name.replace("/", "__")).write_text(s)
        return s.encode()

    if path.suffix == ".safetensors":
        import safetensors.numpy

        for key, arr in sorted(safetensors.numpy.load_file(str(path)).items()):
            a = np.ascontiguousarray(arr)
            out[f"{name}:{key}"] = _digest(f"{a.dtype}{a.shape}".encode() + a.tobytes())
    elif path.suffix == ".png":
        from PIL import Image

        with Image.open(path) as im:
            out[name] = _digest(f"{im.mode}{im.size}".encode() + im.tobytes())
    elif path.suffix == ".json":
        doc = _clean(json.loads(path.read_text()))
        out[name] = _digest(text(json.dumps(doc, sort_keys=True, indent=1)))
    elif path.suffix == ".jsonl":
        lines = [_clean(json.loads(s)) for s in path.read_text().splitlines() if s.strip()]
        out[name] = _digest(text(json.dumps(lines, sort_keys=True, indent=1)))
    elif path.suffix == ".txt":
        out[name] = _digest(text(path.read_text()))
    elif path.name != ".lock":
        out[name] = _digest(path.read_bytes())


def _sync4d(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "RAYON_NUM_THREADS": "1", "SYNC4D_ENCODER": ""}
    done = subprocess.run([sys.executable, "-m", "sync4d", *args], env=env, capture_output=True,
                          text=True, timeout=1800)  # fmt: skip
    if done.returncode != 0:
        raise SystemExit(f"sync4d {' '.join(args)} failed:\n{done.stderr[-3000:]}")
    return done


def fingerprints(work: Path, keep: Path | None = None) -> dict[str, str]:
    from sync4d.data import synthetic as syn

    scene = syn.write_synthetic_scene(work / "scene")
    out: dict[str, str] = {}
    for motion in MOTIONS:
        run = work / f"run-{motion}"
        shutil.rmtree(run, ignore_errors=True)
        _sync4d("fit", str(scene), "--config", "synthetic", "--out", str(run), "--iters", "60",
                "--threads", "1", "--phases", "1,2,3", "--encoder", "offline",
                "--set", f"phase1.motion={motion}")  # fmt: skip
        answers = _sync4d("query", str(run), *QUESTIONS, "--json", "--no-plot").stdout
        answers = json.dumps(_clean(json.loads(answers)), indent=1).replace(str(work), "WORK")
        out[f"{motion}/query"] = _digest(answers.encode())
        files = run / "out"
        files.mkdir()
        _sync4d("export", str(run), "--scene", str(files / "scene.json"), "--prompt",
                str(files / "prompt.txt"), "--ply", str(files / "t05.ply"), "--time", "0.5",
                "--threads", "1")  # fmt: skip
        _sync4d("export", str(run), "--spz", str(files / "t05.spz"), "--time", "0.5")
        _sync4d("render", str(run), "--time", "0.5", "--out", str(files / "render"), "--no-gif")
        for path in sorted(p for p in run.rglob("*") if p.is_file()):
            fingerprint_file(path, out, f"{motion}/{path.relative_to(run).as_posix()}", work, keep)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="where to write the fingerprints (JSON)")
    ap.add_argument("--work", default="/tmp/sync4d-fingerprints", help="scene and run folders")
    ap.add_argument("--against", help="fingerprints to compare with (JSON)")
    ap.add_argument("--keep", help="a folder to write the hashed text into (to diff)")
    args = ap.parse_args(argv)
    keep = Path(args.keep) if args.keep else None
    if keep is not None:
        keep.mkdir(parents=True, exist_ok=True)
    prints = fingerprints(Path(args.work).resolve(), keep)
    Path(args.out).write_text(json.dumps(prints, indent=1, sort_keys=True) + "\n")
    print(f"{len(prints)} fingerprints -> {args.out}")
    if not args.against:
        return 0
    before = json.loads(Path(args.against).read_text())
    differ = sorted(k for k in before.keys() | prints.keys() if before.get(k) != prints.get(k))
    for k in differ:
        print(f"differs: {k} ({before.get(k)} -> {prints.get(k)})")
    print(f"{len(differ)} of {len(before.keys() | prints.keys())} differ")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
