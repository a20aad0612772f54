"""Phase 1 training loop (paper Sec. 3.1, Appendix A): photometric loss on one random training
frame per iteration, Adam with per-group learning rates and the usual exponential decay of the
position learning rate, the SH-degree schedule, and adaptive density control.

This module holds the loop only; data loading, checkpoints and the command line live elsewhere.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from sync4d.data.scene import Frame, Scene
from sync4d.densify import Densifier, DensifyConfig
from sync4d.gaussians import DeformableGaussians
from sync4d.losses import photometric_loss, psnr

__all__ = ["Phase1Config", "Phase1Trainer", "scene_extent"]


@dataclass(frozen=True)
class Phase1Config:
    """Learning rates (3DGS values for Gaussian attributes; 5e-4 for D_theta and embeddings,
    Appendix A), schedules and loss weights."""

    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacity: float = 5e-2
    lr_sh: float = 2.5e-3
    lr_deform: float = 5e-4
    lr_embed: float = 5e-4
    sh_degree_interval: int = 1_000
    lambda_l1: float = 0.8
    lambda_dssim: float = 0.2
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    seed: int = 42
    densify: DensifyConfig = field(default_factory=DensifyConfig)


def scene_extent(scene: Scene) -> float:
    """Radius of the training cameras around their centroid, times 1.1 (3DGS's extent)."""
    centres = np.stack([f.camera.center for f in scene.train])
    return float(1.1 * np.linalg.norm(centres - centres.mean(0), axis=1).max() + 1e-6)


class Phase1Trainer:
    """Owns the optimizer, densifier and image cache for one `DeformableGaussians` model."""

    def __init__(
        self,
        model: DeformableGaussians,
        scene: Scene,
        config: Phase1Config | None = None,
        total_iterations: int = 30_000,
        threads: int | None = None,
    ) -> None:
        self.model = model
        self.scene = scene
        self.config = config or Phase1Config()
        self.total = max(1, total_iterations)
        self.threads = threads
        self.extent = scene_extent(scene)
        self.iteration = 0
        self.densifier = Densifier(self.config.densify)
        self._rng = random.Random(self.config.seed)
        self._images: dict[int, torch.Tensor] = {}
        c = self.config
        m = model
        groups = [
            ("means", m.means, c.lr_means * self.extent),
            ("quats", m.quats, c.lr_quats),
            ("log_scales", m.log_scales, c.lr_scales),
            ("opacity_logits", m.opacity_logits, c.lr_opacity),
            ("sh_dc", m.sh_dc, c.lr_sh),
            ("sh_rest", m.sh_rest, c.lr_sh / 20.0),
            ("embeddings", m.embeddings, c.lr_embed),
        ]
        self.optimizer = torch.optim.Adam(
            [{"params": [p], "name": n, "lr": lr} for n, p, lr in groups]
            + [{"params": list(m.deform.parameters()), "name": "deform", "lr": c.lr_deform}],
            eps=1e-15,
        )

    def _image(self, index: int, frame: Frame) -> torch.Tensor:
        if index not in self._images:
            self._images[index] = torch.from_numpy(frame.load_image(self.config.background))
        return self._images[index]

    def _position_lr(self) -> float:
        """Log-linear decay from lr_means to lr_means_final over the run (scaled by extent)."""
        c = self.config
        frac = min(1.0, self.iteration / self.total)
        lr = math.exp((1 - frac) * math.log(c.lr_means) + frac * math.log(c.lr_means_final))
        return lr * self.extent

    def step(self) -> dict[str, float]:
        """One iteration on a random training frame; returns loss, PSNR and N."""
        c = self.config
        self.iteration += 1
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = self._position_lr()
        idx = self._rng.randrange(len(self.scene.train))
        frame = self.scene.train[idx]
        target = self._image(idx, frame)
        degree = min(self.model.sh_degree, (self.iteration - 1) // c.sh_degree_interval)
        bg = torch.tensor(c.background, dtype=torch.float32)
        out = self.model.render(
            frame.camera, frame.time, sh_degree=degree, background=bg, threads=self.threads
        )
        out.means2d.retain_grad()
        loss = photometric_loss(out.features, target, c.lambda_l1, c.lambda_dssim)
        loss.backward()
        with torch.no_grad():
            self.densifier.accumulate(
                out.means2d.grad, out.radii, frame.camera.width, frame.camera.height
            )
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        self.densifier.step(self.model, self.optimizer, self.iteration, self.extent)
        return {
            "loss": float(loss.detach()),
            "psnr": psnr(out.features.detach(), target),
            "gaussians": float(self.model.num_gaussians),
        }

    def train(self, iterations: int, callback: Callable[[int, dict], None] | None = None) -> dict:
        """Run `iterations` steps, calling `callback(iteration, stats)` after each."""
        stats: dict = {}
        for _ in range(iterations):
            stats = self.step()
            if callback is not None:
                callback(self.iteration, stats)
        return stats
