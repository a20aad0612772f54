"""``sync4d bench step RUN``: where a Phase 1 training step's time goes, per motion model, at
the run's own Gaussian count.

Each variant (``NAME:KEY=VALUE,...`` overrides of the run's recorded config, e.g.
``nodes:phase1.motion=nodes``) gets a copy of the run's latest checkpoint (a variant asking
for nodes on a per-Gaussian run samples them first, `Motion.to_final_stage`) and a Phase 1
trainer at the finished schedule (full SH degree, D_theta on) with densification off, so every
variant steps the same Gaussians (a per-Gaussian variant of a node run drops its nodes: the
motion is then not the run's, the cost of a step is D_theta's on every row). Rounds
interleave the variants (a change of machine load hits them alike). Per round and variant
it times `steps` whole training steps, then the same number of the motion alone (D_theta
and, for nodes, the blend: forward and backward of the deformed means, rotations and scales
at a training frame's time), of D_theta alone (on the nodes, or on every Gaussian) and of
the rasterizer alone (SH colours, projection,
compositing; forward and backward), of the photometric loss alone (L1 and D-SSIM of a
render against its target, forward and backward) and of the optimizer's update alone (Adam
over every parameter group, with the gradients a step leaves). The shares are each part's
median over the step's median; the rest of a step is the densification statistics, the
watchdog's checks and Python. Prints a table and writes a JSON with the date, machine and threads.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from sync4d.errors import Sync4dError
from sync4d.options import add_threads, positive_int
from sync4d.report import align_table

__all__ = ["add_arguments", "bench_step", "main"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The description and arguments of ``sync4d bench step`` (`sync4d.cli`)."""
    p.description = (
        "Step a run's Gaussians with each variant of its config in turn and time the whole "
        "step, the motion (D_theta, the node blend) and the rasterizer, forward and backward; "
        "prints a table and writes a JSON."
    )
    p.add_argument("run", metavar="RUN", help="run folder (its Gaussians are stepped)")
    p.add_argument("--variant", action="append", default=None, metavar="NAME[:KEY=VALUE,...]",
                   help="a motion variant: overrides of the run's config (repeatable; default: "
                   "gaussians:phase1.motion=gaussians and nodes:phase1.motion=nodes)")  # fmt: skip
    p.add_argument("--steps", type=positive_int, default=10, metavar="N",
                   help="steps timed per round and variant (default 10)")
    p.add_argument("--rounds", type=positive_int, default=3, metavar="R",
                   help="rounds, each variant in turn (default 3)")
    p.add_argument("--data", default=None, metavar="DATA",
                   help="the run's dataset, if it has moved")
    p.add_argument("--out", default="bench-step.json", metavar="FILE.json",
                   help="results JSON (default bench-step.json)")
    add_threads(p, "torch and the rasterizer")


def _median_ms(xs: list[float]) -> float:
    return 1000.0 * statistics.median(xs)


def bench_step(run_dir: Path, variants: dict[str, list[str]], steps: int, rounds: int,
               threads: int | None, data: str | None = None) -> dict[str, Any]:  # fmt: skip
    """Step, motion and rasterizer times (ms) of each variant on `run_dir`'s Gaussians."""
    import torch

    from sync4d.config import apply_overrides
    from sync4d.phase1.densify import DensifyConfig
    from sync4d.phase1.gaussians import DeformableGaussians
    from sync4d.phase1.losses import photometric_loss
    from sync4d.phase1.motion import motion_for
    from sync4d.phase1.trainer import FinishedSchedule, Phase1Trainer
    from sync4d.pipeline.record import read_record, recorded_config
    from sync4d.runs import RunError, load_run

    if threads:
        torch.set_num_threads(threads)
    run = load_run(run_dir)
    cfg = recorded_config(read_record(run.path), run.path)
    scene = run.scene(data)
    if scene is None:
        raise RunError(f"{run_dir}: its dataset is gone; pass --data DATA")
    never = DensifyConfig(start=2**62, stop=2**62, opacity_reset_interval=2**62)
    tensors, meta = run.model.state()
    trainers: dict[str, Phase1Trainer] = {}
    for name, overrides in variants.items():
        vcfg = apply_overrides(cfg, overrides).phase1
        model = DeformableGaussians.from_state(tensors, meta)
        if vcfg.motion != model.motion_model.name:
            # Another motion than the run's (a node run stepped per Gaussian: D_theta on every
            # row with the Gaussians' own embeddings): the motion is not the run's, the cost
            # per step is the variant's.
            model.set_motion(motion_for(vcfg))
        trainer = Phase1Trainer(model, scene, vcfg, total_iterations=vcfg.iterations,
                                threads=threads, densify=never,
                                schedule=FinishedSchedule())  # fmt: skip
        model.motion_model.to_final_stage(trainer)  # nodes sampled now on a per-Gaussian run
        trainer.step()  # warm-up: caches the first image, allocates
        trainers[name] = trainer
    frames = scene.train
    parts = ("step", "motion", "d_theta", "raster", "loss", "optimizer")
    timings: dict[str, dict[str, list[float]]] = {n: {k: [] for k in parts} for n in variants}
    for r in range(rounds):
        for name, trainer in trainers.items():
            model = trainer.model
            for _ in range(steps):
                t0 = time.perf_counter()
                trainer.step()
                timings[name]["step"].append(time.perf_counter() - t0)
            for k in range(steps):
                frame = frames[(r * steps + k) % len(frames)]
                t0 = time.perf_counter()
                out = model.at_time(frame.time)
                sum(o.sum() for o in out).backward()
                timings[name]["motion"].append(time.perf_counter() - t0)
                model.zero_grad(set_to_none=True)
            for k in range(steps):  # D_theta alone: on the nodes, or on every Gaussian
                frame = frames[(r * steps + k) % len(frames)]
                t0 = time.perf_counter()
                # on the nodes, or on the rows `at_time` evaluates (static: skipped)
                out = model.motion_model.network(model, frame.time)
                sum(o.sum() for o in out).backward()
                timings[name]["d_theta"].append(time.perf_counter() - t0)
                model.zero_grad(set_to_none=True)
            for k in range(steps):
                frame = frames[(r * steps + k) % len(frames)]
                with torch.no_grad():
                    deformed = [o.detach().requires_grad_() for o in model.at_time(frame.time)]
                t0 = time.perf_counter()
                img = model.render(frame.camera, frame.time, background=trainer.background,
                                   deformed=tuple(deformed), threads=threads).features  # fmt: skip
                img.sum().backward()
                timings[name]["raster"].append(time.perf_counter() - t0)
                model.zero_grad(set_to_none=True)
            c = trainer.config
            target = trainer.target(0, frames[0], trainer.background)  # any image of the size
            for k in range(steps):
                frame = frames[(r * steps + k) % len(frames)]
                with torch.no_grad():
                    img = model.render(frame.camera, frame.time, background=trainer.background,
                                       threads=threads).features  # fmt: skip
                img.requires_grad_()
                t0 = time.perf_counter()
                photometric_loss(img, target, c.lambda_l1, c.lambda_dssim,
                                 threads=threads).backward()  # fmt: skip
                timings[name]["loss"].append(time.perf_counter() - t0)
            for k in range(steps):  # the update alone, on the gradients of a render
                frame = frames[(r * steps + k) % len(frames)]
                out = model.render(frame.camera, frame.time, background=trainer.background,
                                   threads=threads)  # fmt: skip
                out.features.sum().backward()
                t0 = time.perf_counter()
                trainer.optimizer.step()
                timings[name]["optimizer"].append(time.perf_counter() - t0)
                trainer.optimizer.zero_grad(set_to_none=True)
        print(f"bench step: round {r + 1}/{rounds} done", file=sys.stderr)
    rows = []
    base = None
    for name, trainer in trainers.items():
        t = timings[name]
        step, motion, dth, rast, loss, opt = (_median_ms(t[k]) for k in parts)
        base = base or step
        rows.append({
            "variant": name, "overrides": variants[name],
            "motion_model": trainer.model.motion,
            "gaussians": trainer.model.num_gaussians,
            "nodes": trainer.model.motion_model.counts().get("nodes"),
            "step_ms": step, "motion_ms": motion, "d_theta_ms": dth, "raster_ms": rast,
            "loss_ms": loss, "optimizer_ms": opt,
            "motion_share": motion / step, "d_theta_share": dth / step,
            "raster_share": rast / step, "loss_share": loss / step,
            "optimizer_share": opt / step,
            "speedup": base / step, "raw_s": t,
        })  # fmt: skip
    return {
        "date": _dt.date.today().isoformat(),
        "command": "sync4d " + " ".join(sys.argv[1:]),
        "machine": {"platform": platform.platform(), "processor": platform.processor(),
                    "cpus": os.cpu_count()},  # fmt: skip
        "threads": threads, "run": str(run_dir), "steps": steps, "rounds": rounds,
        "rows": rows,
    }  # fmt: skip


def main(args: argparse.Namespace) -> int:
    from sync4d.bench.fit import parse_variant
    from sync4d.config import ConfigError

    try:
        texts = args.variant or ["gaussians:phase1.motion=gaussians", "nodes:phase1.motion=nodes"]
        pairs = [parse_variant(v) for v in texts]
    except ConfigError as e:
        print(f"bench step: {e}", file=sys.stderr)
        return 2
    variants = dict(pairs)
    if len(variants) != len(pairs):
        print("bench step: two --variant share a name", file=sys.stderr)
        return 2
    try:
        result = bench_step(Path(args.run), variants, args.steps, args.rounds, args.threads,
                            args.data)  # fmt: skip
    except Sync4dError as e:  # exit 2; 3: the watchdog's stop
        print(f"bench step: {e}", file=sys.stderr)
        return e.exit_code
    except FileNotFoundError as e:
        print(f"bench step: {e}", file=sys.stderr)
        return 2
    table = [["variant", "motion", "gaussians", "nodes", "step ms", "motion ms", "share",
              "D_theta ms", "share", "raster ms", "share", "loss ms", "share", "Adam ms",
              "share", "speed-up"]]  # fmt: skip
    for r in result["rows"]:
        table.append([r["variant"], r["motion_model"], f"{r['gaussians']:,}",
                      "-" if r["nodes"] is None else str(r["nodes"]), f"{r['step_ms']:.1f}",
                      f"{r['motion_ms']:.1f}", f"{100 * r['motion_share']:.0f} %",
                      f"{r['d_theta_ms']:.1f}", f"{100 * r['d_theta_share']:.1f} %",
                      f"{r['raster_ms']:.1f}", f"{100 * r['raster_share']:.0f} %",
                      f"{r['loss_ms']:.1f}", f"{100 * r['loss_share']:.0f} %",
                      f"{r['optimizer_ms']:.1f}", f"{100 * r['optimizer_share']:.0f} %",
                      f"{r['speedup']:.2f}x"])  # fmt: skip
    print(align_table(table[0], table[1:]))
    out = Path(args.out)
    out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")
    print(f"bench step: wrote {out}", file=sys.stderr)
    return 0

