"""How well each node blend (linear, dual quaternions) can reproduce a trained per-Gaussian
motion: the measurement behind `NodeConfig.blend`'s default (docs/results/nodes.md).

Takes a per-Gaussian run (D_theta on every Gaussian), samples control nodes on its Gaussians
as training does (`DeformableGaussians.use_nodes`), and gives every node a free rigid motion
per time (a rotation vector and a translation at each of `--times` frame times, no MLP), then
fits those motions with Adam so that the blended Gaussians land where D_theta puts them, for
each blend in turn from the same start. Reports the RMS position error (in units of the
scene's extent and of the mean motion) and the mean rotation error of the Gaussians, and
writes a JSON.

    python scripts/blend_fidelity.py RUN --out docs/bench/blend-fidelity-hook.json
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import platform
import sys
from pathlib import Path

import torch

from sync4d.geometry import axis_angle_to_quat
from sync4d.phase1.nodes import BLENDS, NodeConfig, blend
from sync4d.runs import load_run


def fidelity(run_dir: Path, count: int, neighbours: int, times: int, steps: int,
             seed: int = 0) -> dict:  # fmt: skip
    run = load_run(run_dir)
    model = run.model
    if model.motion != "gaussians":
        raise SystemExit(f"{run_dir}: a node run; give a per-Gaussian run")
    ts = torch.linspace(0.0, 1.0, times)
    with torch.no_grad():
        target = [model.at_time(float(t)) for t in ts]  # (x, q, s) per time
        x0 = model.means.detach()
        q0 = model.quats.detach() / model.quats.detach().norm(dim=-1, keepdim=True)
        ls0 = model.log_scales.detach()
    extent = float((x0 - x0.mean(0)).norm(dim=-1).max())
    motion = torch.stack([x - x0 for x, _, _ in target]).norm(dim=-1)  # [T, N]
    mean_motion = float(motion.mean())
    out: dict = {"run": str(run_dir), "gaussians": int(x0.shape[0]), "times": times,
                 "extent": extent, "mean_motion": mean_motion, "blends": {}}  # fmt: skip
    for kind in BLENDS:
        cfg = NodeConfig(count=count, neighbours=neighbours, blend=kind)
        own = model.motion_model
        nodes = model.use_nodes(cfg, torch.Generator().manual_seed(seed))
        model.set_motion(own)  # the run's model stays per-Gaussian
        pos, lr, index = nodes.positions.detach(), nodes.log_radii.detach(), nodes.index
        m = pos.shape[0]
        rv = torch.zeros(times, m, 3, requires_grad=True)
        dx = torch.zeros(times, m, 3, requires_grad=True)
        opt = torch.optim.Adam([{"params": [dx], "lr": 0.01 * extent},
                                {"params": [rv], "lr": 0.01}])  # fmt: skip
        zero = torch.zeros(m, 3)
        for step in range(steps):
            loss = 0.0
            for j in range(times):
                q = axis_angle_to_quat(rv[j])
                x, _, _ = blend(x0, q0, ls0, pos, (q, dx[j], zero), index, None, kind, lr)
                loss = loss + ((x - target[j][0]) ** 2).sum(-1).mean()
            opt.zero_grad()
            (loss / times).backward()
            opt.step()
            if step % 50 == 0:
                print(f"{kind}: step {step} rms {math.sqrt(float(loss.detach()) / times):.5f}",
                      file=sys.stderr)
        with torch.no_grad():
            err, rot = [], []
            for j in range(times):
                q = axis_angle_to_quat(rv[j])
                x, qt, _ = blend(x0, q0, ls0, pos, (q, dx[j], zero), index, None, kind, lr)
                err.append(((x - target[j][0]) ** 2).sum(-1))
                dot = (qt * target[j][1]).sum(-1).abs().clamp(max=1.0)
                rot.append(2.0 * torch.acos(dot))
            rms = float(torch.stack(err).mean().sqrt())
            out["blends"][kind] = {
                "rms_position": rms, "rms_over_extent": rms / extent,
                "rms_over_mean_motion": rms / max(mean_motion, 1e-12),
                "mean_rotation_error_deg": float(torch.stack(rot).mean()) * 180 / math.pi,
                "nodes": m,
            }  # fmt: skip
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run")
    p.add_argument("--count", type=int, default=NodeConfig().count)
    p.add_argument("--neighbours", type=int, default=NodeConfig().neighbours)
    p.add_argument("--times", type=int, default=12)
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", required=True)
    a = p.parse_args()
    torch.set_num_threads(a.threads)
    res = fidelity(Path(a.run), a.count, a.neighbours, a.times, a.steps)
    res.update({"date": _dt.date.today().isoformat(), "command": " ".join(sys.argv),
                "machine": platform.platform(), "threads": a.threads})  # fmt: skip
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    for kind, r in res["blends"].items():
        print(f"{kind:16s} RMS {r['rms_position']:.5f} ({100 * r['rms_over_extent']:.2f} % "
              f"of the extent, {100 * r['rms_over_mean_motion']:.1f} % of the mean motion), "
              f"rotation error {r['mean_rotation_error_deg']:.2f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
