"""Measure the figures docs/install.md and the README quote about installing (issue 53) and
write them as a record: the installed size of torch and its nvidia-* packages in this
environment, and the time to generate the embedded synthetic scene on first use.

    OMP_NUM_THREADS=1 RAYON_NUM_THREADS=1 nice -n 10 python scripts/record_install_figures.py \
        --out docs/bench/install-figures.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from sync4d.bench.measure import machine_info


def tree_bytes(path: Path) -> int:
    total = 0
    for root, _dirs, files in os.walk(path):
        for name in files:
            p = Path(root) / name
            if not p.is_symlink():
                total += p.stat().st_size
    return total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    import torch

    site = Path(torch.__file__).resolve().parent.parent
    packages = {"torch": tree_bytes(site / "torch")}
    nvidia = site / "nvidia"
    if nvidia.is_dir():
        packages["nvidia"] = tree_bytes(nvidia)
    total = sum(packages.values())

    from sync4d.data.synthetic import SyntheticConfig, write_synthetic_scene

    seconds = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            write_synthetic_scene(Path(tmp) / "scene", SyntheticConfig())
            seconds.append(time.perf_counter() - t0)

    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": " ".join(["python", *sys.argv]),
        "machine": {
            **machine_info(),
            "threads": os.environ.get("OMP_NUM_THREADS"),
            "note": "the 2-core machine, shared with other sessions' jobs; nice -n 10",
        },
        "torch_version": torch.__version__,
        "installed_bytes": packages,
        "installed_total_bytes": total,
        "installed_total_gib": total / 2**30,
        "synthetic_scene_seconds": seconds,
        "note": "installed size on disk (files under site-packages/torch and "
        "site-packages/nvidia), not the download; the scene written into a temporary folder "
        "with the default SyntheticConfig, as ensure_default_scene does on first use",
    }
    Path(args.out).write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps({k: record[k] for k in ("installed_total_gib", "synthetic_scene_seconds")}))


if __name__ == "__main__":
    main()
