"""Checkpoints: round trip, resume gives the same next-step loss, clear errors for bad files."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from support.scenes import orbit_scene, orbit_student
from support.training import train
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.pipeline import resume_trainer
from sync4d.runs import CheckpointError, load_model, save_checkpoint


def _trainer(tmp_path: Path) -> tuple[Phase1Trainer, object, Phase1Config]:
    scene, gt = orbit_scene(tmp_path)
    model = orbit_student(gt, 3, jitter=0.05)
    cfg = Phase1Config(densify=DensifyConfig(start=4, interval=4, stop=100, grad_threshold=1e-5))
    return Phase1Trainer(model, scene, cfg, total_iterations=50, threads=1), scene, cfg


def test_resume_gives_the_same_next_step(tmp_path: Path) -> None:
    trainer, scene, cfg = _trainer(tmp_path)
    train(trainer, 9)  # densification has changed N by now
    n_saved = trainer.model.num_gaussians
    assert n_saved != 40  # densification changed N before the save
    ck = save_checkpoint(trainer, tmp_path / "run" / "ckpt.safetensors")
    assert not (tmp_path / "run" / "ckpt.safetensors.tmp").exists()
    expected = [trainer.step()["loss"] for _ in range(3)]
    resumed = resume_trainer(ck, scene, cfg, threads=1)
    assert resumed.iteration == 9
    got = [resumed.step()["loss"] for _ in range(3)]
    assert got == expected
    model, meta = load_model(ck)
    assert meta["kind"] == "sync4d.phase1" and meta["iteration"] == 9
    assert model.num_gaussians == n_saved
    assert torch.equal(model.means.data, load_model(ck)[0].means.data)


def test_bad_checkpoints_are_named(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="checkpoint file is missing"):
        load_model(tmp_path / "none.safetensors")
    trainer, _, _ = _trainer(tmp_path)
    ck = save_checkpoint(trainer, tmp_path / "ok.safetensors")
    data = ck.read_bytes()
    trunc = tmp_path / "trunc.safetensors"
    trunc.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="trunc.safetensors: not a readable"):
        load_model(trunc)
    with torch.no_grad():
        trainer.model.means[0, 0] = float("nan")
    bad = save_checkpoint(trainer, tmp_path / "nan.safetensors")
    with pytest.raises(CheckpointError, match="'gaussians.means' contains NaN"):
        load_model(bad)


def test_phase2_checkpoint_resumes_the_same_next_step(tmp_path: Path) -> None:
    from sync4d.phase2 import MotionStrategy, Phase2Config, phase2_trainer

    trainer, scene, cfg = _trainer(tmp_path)
    train(trainer, 3)
    p2 = Phase2Config(motion_start=0, velocity_start=0, residual_start=0, warmup_start=0,
                      warmup_end=4, densify=True)  # fmt: skip
    s2 = phase2_trainer(trainer.model, scene, cfg, p2, 30, threads=1)
    t2 = s2.trainer
    n0 = t2.model.num_gaussians
    train(t2, 5)
    assert t2.model.num_gaussians != n0  # densified, so the labels were re-assigned
    assert len(s2.labels) == t2.model.num_gaussians
    ck = save_checkpoint(t2, tmp_path / "p2.safetensors")
    labels = s2.labels.clone()
    expected = [t2.step()["loss"] for _ in range(3)]
    resumed = resume_trainer(ck, scene, cfg, threads=1, phase2=p2)
    (strategy,) = resumed.plugins
    assert isinstance(strategy, MotionStrategy) and resumed.iteration == 5
    assert torch.equal(strategy.labels, labels)
    got = [resumed.step()["loss"] for _ in range(3)]
    assert got == expected
    _, meta = load_model(ck)
    assert meta["kind"] == "sync4d.phase2"
    assert meta["phase2"]["num_objects"] == s2.assignment.num_objects


def test_phase2_keeps_the_phase1_scene_size_and_sh_degree_by_default(tmp_path: Path) -> None:
    from sync4d.phase2 import Phase2Config, phase2_trainer

    trainer, scene, cfg = _trainer(tmp_path)
    train(trainer, 3)
    n0 = trainer.model.num_gaussians
    t2 = phase2_trainer(trainer.model, scene, cfg, Phase2Config(motion_start=0), 30,
                        threads=1).trainer  # fmt: skip
    train(t2, 10)
    assert t2.model.num_gaussians == n0
    assert t2.sh_degree_now() == t2.model.sh_degree


def test_near_plane_is_a_model_setting_saved_with_it(tmp_path: Path) -> None:
    """`near` culls Gaussians closer to the camera in every render, and checkpoints keep it."""
    trainer, scene, _ = _trainer(tmp_path)
    model = trainer.model
    frame = scene.train[0]
    c = torch.as_tensor(frame.camera.center, dtype=torch.float32)
    axis = torch.as_tensor(frame.camera.viewmat[2, :3], dtype=torch.float32)
    with torch.no_grad():  # one opaque Gaussian 5 cm in front of the lens
        model.means[0] = c + 0.05 * axis
        model.opacity_logits[0] = 8.0
        model.log_scales[0] = math.log(0.02)
        near_img = model.render(frame.camera, frame.time, background=torch.ones(3), threads=1)
        model.near = 0.1
        far_img = model.render(frame.camera, frame.time, background=torch.ones(3), threads=1)
    assert near_img.alpha.mean() > far_img.alpha.mean() + 0.3
    ck = save_checkpoint(trainer, tmp_path / "near.safetensors")
    assert load_model(ck)[0].near == 0.1


def test_resume_continues_the_densification_generator(tmp_path: Path) -> None:
    trainer, scene, cfg = _trainer(tmp_path)
    fresh = torch.Generator().manual_seed(cfg.seed).get_state()
    train(trainer, 9)
    # Splits have drawn child offsets before the save, so its generator state is not fresh.
    assert not torch.equal(trainer.densifier.generator.get_state(), fresh)
    ck = save_checkpoint(trainer, tmp_path / "run" / "ckpt.safetensors")
    train(trainer, 8)  # two more densification steps (12, 16)
    resumed = resume_trainer(ck, scene, cfg, threads=1)
    train(resumed, 8)
    assert resumed.model.num_gaussians == trainer.model.num_gaussians
    assert torch.equal(resumed.model.means.data, trainer.model.means.data)
    assert torch.equal(resumed.densifier.generator.get_state(),
                       trainer.densifier.generator.get_state())  # fmt: skip


def test_a_bad_densification_generator_state_is_named(tmp_path: Path) -> None:
    from safetensors import safe_open
    from safetensors.torch import load_file, save_file

    trainer, scene, cfg = _trainer(tmp_path)
    ck = save_checkpoint(trainer, tmp_path / "ok.safetensors")
    with safe_open(str(ck), framework="pt") as f:
        header = f.metadata()
    tensors = load_file(str(ck))
    tensors["densify.rng"] = tensors["densify.rng"][:10].clone()  # a truncated state
    bad = tmp_path / "rng.safetensors"
    save_file(tensors, str(bad), metadata=header)
    with pytest.raises(CheckpointError, match="rng.safetensors: bad 'densify.rng'"):
        resume_trainer(bad, scene, cfg, threads=1)
