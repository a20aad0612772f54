"""Phase 2 on the embedded synthetic scene from a Phase 1 checkpoint, with each object's motion
error after the closed-form fit, after the photometric refinement (per frame with --per-frame)
and every 250 Phase 2 iterations: the measurements of docs/results/phase2-robustness.md.

    python -m sync4d fit --out runs/s42 --phases 1 --set phase1.seed=42 --threads 1
    python scripts/phase2_from_checkpoint.py runs/s42/checkpoint.safetensors --iters 1000 \\
        --set phase2.motion.refine_steps=80 --threads 1
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from sync4d.config import load_config, repo_configs
from sync4d.data import synthetic as syn
from sync4d.data.detect import load_scene
from sync4d.phase2 import MotionStrategy, phase2_trainer
from sync4d.phase2.refine import refine_motion
from sync4d.pipeline import set_threads
from sync4d.runs import load_model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--iters", type=int, default=0, help="Phase 2 iterations after refining")
    ap.add_argument("--set", action="append", default=[], help="config override (repeatable)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--per-frame", action="store_true", help="per-frame rotation errors")
    args = ap.parse_args()
    root = syn.default_scene_dir()
    cfg = load_config(repo_configs() / "synthetic.toml", args.set)
    threads = set_threads(args.threads)
    scene = load_scene(root, cfg.resolution_scale)
    gt = syn.load_ground_truth(root)
    model, _ = load_model(args.checkpoint)

    def report(what: str, trainer: MotionStrategy) -> None:
        errors = gt.export_errors(trainer.motion_export())
        cells = ", ".join(f"{n} {r:.2f} deg / {c:.2f} %" for n, (r, c) in errors.items())
        print(f"{what} ({time.perf_counter() - t0:.0f} s): {cells}", flush=True)

    t0 = time.perf_counter()
    mc = cfg.phase2.motion
    fitted = dataclasses.replace(cfg.phase2, motion=dataclasses.replace(mc, refine_steps=0))
    trainer = phase2_trainer(model, scene, cfg.phase1, fitted, max(1, args.iters), threads)
    report("closed-form fit", trainer)
    if mc.refine_steps > 0:
        refine_motion(trainer, mc)
        report("refined", trainer)
    if args.per_frame:
        export = trainer.motion_export()
        for name, label, static in zip(gt.names, gt.ids, gt.static, strict=True):
            if not static:
                rot, _ = gt.motion_errors(
                    export["rotations"][label], export["translations"][label], export["times"],
                    label,
                )  # fmt: skip
                print(f"  {name}, every other frame:", " ".join(f"{v:.2f}" for v in rot[::2]))
    for i in range(args.iters):
        trainer.step()
        if (i + 1) % 250 == 0 or i + 1 == args.iters:
            report(f"Phase 2 iteration {i + 1}", trainer)


if __name__ == "__main__":
    main()
