"""Checkpoints: one safetensors file holding every tensor (canonical Gaussians, D_theta
weights, Adam moments, densification statistics; in Phase 2 also M_phi, its Adam moments, the
object labels, the residual EMA and the motion export) and a JSON header (format version, kind
"sync4d.phase1" or "sync4d.phase2", model config, iteration, learning rates, RNG state).
Written atomically (temporary file, then rename), so an interrupted write never replaces the
last good checkpoint. The standalone Rust renderer reads the same file.
"""

from __future__ import annotations

import json
import os
import random
from dataclasses import asdict
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from sync4d.deform import DeformConfig
from sync4d.densify import PER_GAUSSIAN
from sync4d.gaussians import DeformableGaussians
from sync4d.phase2 import Phase2Config, Phase2Trainer
from sync4d.train import Phase1Config, Phase1Trainer

__all__ = [
    "CheckpointError",
    "FORMAT_VERSION",
    "camera_records",
    "save_checkpoint",
    "load_model",
    "resume_trainer",
]

FORMAT_VERSION = 1


class CheckpointError(ValueError):
    """An unreadable, truncated or inconsistent checkpoint; the message names the file."""

    def __init__(self, path: str | Path, problem: str) -> None:
        super().__init__(f"{path}: {problem}")


def _rng_to_json(state: tuple) -> list:
    version, internal, gauss = state
    return [version, list(internal), gauss]


def camera_records(scene) -> list[dict]:
    """Every train and test camera of `scene` as JSON-ready records (viewmat row-major 4x4
    world-to-camera, OpenCV axes; intrinsics in pixels; frame time), for renderers that read a
    checkpoint without the dataset."""
    out = []
    for split, frames in (("train", scene.train), ("test", scene.test)):
        for f in frames:
            c = f.camera
            out.append(
                {
                    "split": split,
                    "name": f.name,
                    "time": float(f.time),
                    "viewmat": [float(v) for v in c.viewmat.reshape(-1)],
                    "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                    "width": c.width, "height": c.height,
                }  # fmt: skip
            )
    return out


def save_checkpoint(trainer: Phase1Trainer, path: str | Path, extra: dict | None = None) -> Path:
    """Write the trainer's model, optimizer and loop state to `path` atomically; `extra`
    (JSON-serialisable: run settings, cameras) is stored in the header under "run"."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = trainer.model
    tensors: dict[str, torch.Tensor] = {
        f"gaussians.{n}": getattr(m, n).detach() for n in PER_GAUSSIAN
    }
    for k, v in m.deform.state_dict().items():
        tensors[f"deform.{k}"] = v.detach()
    steps: dict[str, float] = {}
    for gi, group in enumerate(trainer.optimizer.param_groups):
        for pi, p in enumerate(group["params"]):
            st = trainer.optimizer.state.get(p)
            if st:
                for k in ("exp_avg", "exp_avg_sq"):
                    tensors[f"optim.{gi}.{pi}.{k}"] = st[k]
                steps[f"{gi}.{pi}"] = float(st["step"])
    tensors["densify.grad_accum"] = trainer.densifier.grad_accum
    tensors["densify.count"] = trainer.densifier.count
    tensors["densify.max_radius"] = trainer.densifier.max_radius
    tensors["densify.rng"] = trainer.densifier.generator.get_state()
    phase2 = None
    if isinstance(trainer, Phase2Trainer):
        phase2 = _phase2_state(trainer, tensors)
    meta = {
        "format_version": FORMAT_VERSION,
        "kind": "sync4d.phase2" if phase2 else "sync4d.phase1",
        "iteration": trainer.iteration,
        "total_iterations": trainer.total,
        "sh_degree": m.sh_degree,
        "near": m.near,
        "deform_config": asdict(m.config),
        "lrs": [g["lr"] for g in trainer.optimizer.param_groups],
        "adam_steps": steps,
        "python_rng": _rng_to_json(trainer._rng.getstate()),
        "background": list(trainer.config.background),
    }
    if phase2:
        meta["phase2"] = phase2
    if extra:
        meta["run"] = extra
    tmp = path.with_name(path.name + ".tmp")
    save_file(
        {k: v.contiguous() for k, v in tensors.items()},
        str(tmp),
        metadata={"sync4d": json.dumps(meta)},
    )
    os.replace(tmp, path)
    return path


def _phase2_state(trainer: Phase2Trainer, tensors: dict[str, torch.Tensor]) -> dict:
    """Add Phase 2's tensors to `tensors`; return its JSON header entry."""
    for k, v in trainer.motion.state_dict().items():
        tensors[f"motion.{k}"] = v.detach().float()
    steps: dict[str, float] = {}
    for pi, p in enumerate(trainer.motion_optimizer.param_groups[0]["params"]):
        st = trainer.motion_optimizer.state.get(p)
        if st:
            tensors[f"motion_optim.{pi}.exp_avg"] = st["exp_avg"]
            tensors[f"motion_optim.{pi}.exp_avg_sq"] = st["exp_avg_sq"]
            steps[str(pi)] = float(st["step"])
    tensors["phase2.labels"] = trainer.labels.to(torch.int64)
    tensors["phase2.residual_ema"] = trainer.residual_ema
    tensors["phase2.static"] = trainer.static.to(torch.uint8)
    for k, v in trainer.motion_export().items():
        tensors[f"export.{k}"] = torch.as_tensor(v).float() if k != "labels" else torch.as_tensor(v)
    a = trainer.assignment
    return {
        "num_objects": a.num_objects,
        "names": {str(k): v for k, v in a.names.items()},
        "assignment": a.source,
        "motion_kind": trainer.phase2.motion.kind,
        "motion_rigid": trainer.motion.rigid,
        "times": [float(t) for t in trainer.times],
        "ema_started": trainer._ema_started,
        "motion_adam_steps": steps,
    }


def _read(path: Path) -> tuple[dict[str, torch.Tensor], dict]:
    if not path.exists():
        raise CheckpointError(path, "checkpoint file is missing")
    try:
        tensors = load_file(str(path))
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
    except (SafetensorError, OSError) as e:
        raise CheckpointError(path, f"not a readable safetensors checkpoint ({e})") from None
    if "sync4d" not in header:
        raise CheckpointError(path, "no sync4d metadata in the header (not a sync4d checkpoint)")
    meta = json.loads(header["sync4d"])
    if meta.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(path, f"unsupported format version {meta.get('format_version')}")
    for name, t in tensors.items():
        if t.is_floating_point() and not torch.isfinite(t).all():
            raise CheckpointError(path, f"tensor '{name}' contains NaN or inf")
    return tensors, meta


def load_model(path: str | Path) -> tuple[DeformableGaussians, dict]:
    """The model stored in a checkpoint, and its metadata."""
    path = Path(path)
    tensors, meta = _read(path)
    try:
        means = tensors["gaussians.means"]
        model = DeformableGaussians(
            means, None, sh_degree=meta["sh_degree"], config=DeformConfig(**meta["deform_config"])
        )
        model.near = float(meta.get("near", 0.01))
        with torch.no_grad():
            for n in PER_GAUSSIAN:
                src = tensors[f"gaussians.{n}"]
                if src.shape != getattr(model, n).shape:
                    want = list(getattr(model, n).shape)
                    raise CheckpointError(
                        path, f"'gaussians.{n}' has shape {list(src.shape)}, expected {want}"
                    )
                getattr(model, n).copy_(src)
        deform = {k[len("deform.") :]: v for k, v in tensors.items() if k.startswith("deform.")}
        model.deform.load_state_dict(deform)
    except KeyError as e:
        raise CheckpointError(path, f"missing tensor or field {e}") from None
    except RuntimeError as e:
        raise CheckpointError(path, f"inconsistent deformation weights ({e})") from None
    return model, meta


def resume_trainer(
    path: str | Path,
    scene,
    config: Phase1Config | None = None,
    threads: int | None = None,
    total_iterations: int | None = None,
    phase2: Phase2Config | None = None,
) -> Phase1Trainer:
    """Rebuild the trainer (`Phase1Trainer`, or `Phase2Trainer` for a Phase 2 checkpoint, with
    `phase2`'s settings) exactly as it was when `path` was saved (`total_iterations` extends or
    shortens the run; the learning-rate schedules follow the new length)."""
    path = Path(path)
    model, meta = load_model(path)
    tensors, _ = _read(path)
    total = total_iterations or meta["total_iterations"]
    if meta.get("kind") == "sync4d.phase2":
        trainer: Phase1Trainer = _resume_phase2(
            path, tensors, meta, model, scene, config, phase2, threads, total
        )
    else:
        trainer = Phase1Trainer(model, scene, config, total_iterations=total, threads=threads)
    trainer.iteration = meta["iteration"]
    for gi, group in enumerate(trainer.optimizer.param_groups):
        group["lr"] = meta["lrs"][gi]
        for pi, p in enumerate(group["params"]):
            key = f"{gi}.{pi}"
            if key in meta["adam_steps"]:
                trainer.optimizer.state[p] = {
                    "step": torch.tensor(meta["adam_steps"][key]),
                    "exp_avg": tensors[f"optim.{key}.exp_avg"].clone(),
                    "exp_avg_sq": tensors[f"optim.{key}.exp_avg_sq"].clone(),
                }
    trainer.densifier.grad_accum = tensors["densify.grad_accum"].clone()
    trainer.densifier.count = tensors["densify.count"].clone()
    if "densify.max_radius" in tensors:  # absent in checkpoints before sync4d 0.2
        trainer.densifier.max_radius = tensors["densify.max_radius"].clone()
    if "densify.rng" in tensors:  # absent in older checkpoints: the seed's generator
        try:
            trainer.densifier.generator.set_state(tensors["densify.rng"].clone())
        except (RuntimeError, TypeError) as e:
            raise CheckpointError(path, f"bad 'densify.rng' generator state ({e})") from None
    try:
        version, internal, gauss = meta["python_rng"]
        trainer._rng = random.Random()
        trainer._rng.setstate((version, tuple(internal), gauss))
    except (ValueError, TypeError) as e:
        raise CheckpointError(path, f"bad frame-sampler state ({e})") from None
    return trainer


def _resume_phase2(
    path: Path, tensors: dict, meta: dict, model, scene, config, phase2, threads, total
) -> Phase2Trainer:
    from sync4d.assign import Assignment

    try:
        info = meta["phase2"]
        labels = tensors["phase2.labels"].numpy().astype("int64")
        if len(labels) != model.num_gaussians:
            raise CheckpointError(path, "'phase2.labels' does not match the Gaussian count")
        names = {int(k): v for k, v in info["names"].items()}
        assignment = Assignment(labels, int(info["num_objects"]), names, info["assignment"])
        trainer = Phase2Trainer(
            model, scene, config, phase2, total, threads, assignment=assignment
        )
        motion = {k[len("motion.") :]: v for k, v in tensors.items() if k.startswith("motion.")}
        motion["times"] = trainer.motion.times
        trainer.motion.load_state_dict(motion)
        for pi, p in enumerate(trainer.motion_optimizer.param_groups[0]["params"]):
            key = str(pi)
            if key in info["motion_adam_steps"]:
                trainer.motion_optimizer.state[p] = {
                    "step": torch.tensor(info["motion_adam_steps"][key]),
                    "exp_avg": tensors[f"motion_optim.{key}.exp_avg"].clone(),
                    "exp_avg_sq": tensors[f"motion_optim.{key}.exp_avg_sq"].clone(),
                }
        trainer.residual_ema = tensors["phase2.residual_ema"].clone()
        trainer._ema_started = bool(info["ema_started"])
        trainer.static = tensors["phase2.static"].to(torch.bool).clone()
    except KeyError as e:
        raise CheckpointError(path, f"missing Phase 2 tensor or field {e}") from None
    except RuntimeError as e:
        raise CheckpointError(path, f"inconsistent Phase 2 state ({e})") from None
    return trainer
