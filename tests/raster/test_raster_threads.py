"""`threads=1` runs the Rust ops on the calling thread itself, starting no thread (issue 51: a
one-worker pool took 16 % of a `fit --threads 1`'s CPU time while the caller slept); a thread
that did still reaches the other pools, `threads=None` rayon's default count."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

if not sys.platform.startswith("linux"):
    pytest.skip("counts threads in /proc", allow_module_level=True)

_PROBE = """
import json, os, torch
from support.scenes import raster_scene
from sync4d import _core, raster

def threads():
    return len(os.listdir("/proc/self/task"))

s = raster_scene(300, 48, 40, seed=2)
args = [s[k] for k in ("means", "quats", "scales", "opacities", "features", "viewmat", "K")]
out = {"start": threads()}
one = raster.rasterize(*args, 48, 40, threads=1).features
out["after_one"] = threads()
default = raster.rasterize(*args, 48, 40).features  # from a thread that ran threads=1
two = raster.rasterize(*args, 48, 40, threads=2).features
out["after_all"] = threads()
out["same"] = bool(torch.equal(one, default) and torch.equal(one, two))
out["default_threads"] = _core.default_threads()
print(json.dumps(out))
"""


def test_one_thread_runs_on_the_caller_and_the_others_still_reach_their_pools() -> None:
    tests = str(Path(__file__).resolve().parents[1])  # for `support`
    path = os.pathsep.join(p for p in (tests, os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "PYTHONPATH": path, "RAYON_NUM_THREADS": "3", "OMP_NUM_THREADS": "1",
           "OPENBLAS_NUM_THREADS": "1"}  # fmt: skip
    done = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                          text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["after_one"] == out["start"], out  # no pool thread for threads=1
    assert out["after_all"] == out["start"] + 3 + 2, out  # rayon's default (3), then 2
    assert out["same"], out
    assert out["default_threads"] == 3, out
