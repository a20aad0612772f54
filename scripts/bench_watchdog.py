"""The watchdog's cost per training step (issue 53): its checks on a Phase 1 model of 19,000
Gaussians with D_theta (15 parameter tensors, 1.77 M values; their gradients; the render's
inputs at one time), each the fastest of `--reps` runs, against the checks before issue 53
(a float64 sum per gradient and per parameter, no input check), timed here the same way.

    python scripts/bench_watchdog.py --threads 2 --out docs/bench/watchdog-cost.json
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path

import torch

from sync4d import watchdog
from sync4d.phase1.gaussians import DeformableGaussians


def _legacy(tensors: dict[str, torch.Tensor | None]) -> bool:
    """The check before issue 53: one float64 sum per tensor, one isfinite over them."""
    present = [v for v in tensors.values() if v is not None and v.numel()]
    return bool(torch.isfinite(torch.stack([v.detach().double().sum() for v in present])).all())


def _fastest_ms(fn, reps: int) -> float:
    for _ in range(10):
        fn()
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return round(1e3 * best, 3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=19_000)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument("--note", default="", help="what else ran on the machine")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    n = args.gaussians
    model = DeformableGaussians(torch.randn(n, 3), torch.rand(n, 3), sh_degree=3)
    params = dict(model.named_parameters())
    for p in params.values():
        p.grad = torch.randn_like(p)
    with torch.no_grad():
        means, quats, scales = model.at_time(0.5)
        inputs = {"means": means, "quats": quats, "scales": scales,
                  "opacities": torch.sigmoid(model.opacity_logits),
                  "sh": torch.cat([model.sh_dc, model.sh_rest], 1), "colors": torch.rand(n, 3)}
    grads = {k: p.grad for k, p in params.items()}
    now = {
        "gradients_ms": _fastest_ms(lambda: watchdog.check_grads("Phase 1", 1, params), args.reps),
        "parameters_ms": _fastest_ms(lambda: watchdog.check_params("Phase 1", 1, params),
                                     args.reps),
        "inputs_ms": _fastest_ms(lambda: watchdog.check_inputs("Phase 1", 1, inputs), args.reps),
    }  # fmt: skip
    now["step_ms"] = round(sum(now.values()), 3)
    before = {
        "gradients_ms": _fastest_ms(lambda: _legacy(grads), args.reps),
        "parameters_ms": _fastest_ms(lambda: _legacy(params), args.reps),
    }
    before["step_ms"] = round(sum(before.values()), 3)
    record = {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": shlex.join(["python", "scripts/bench_watchdog.py",
                               *(sys.argv[1:] if argv is None else argv)]),
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                    "torch": torch.__version__},
        "note": args.note,
        "gaussians": n, "threads": args.threads, "reps": args.reps,
        "parameter_tensors": len(params),
        "parameter_values": sum(p.numel() for p in params.values()),
        "input_values": sum(v.numel() for v in inputs.values()),
        "before_issue_53": before, "now": now,
    }  # fmt: skip
    text = json.dumps(record, indent=2) + "\n"
    if args.out:
        args.out.write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
