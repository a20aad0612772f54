"""Phase 1 training loop (paper Sec. 3.1, Appendix A): photometric loss on one random training
frame per iteration, Adam with per-group learning rates and the usual exponential decay of the
position learning rate, the SH-degree schedule, and adaptive density control.

This module holds the loop only; data loading, checkpoints and the command line live elsewhere.

What the loop does is composed, not overridden, where it is a policy: densification is the
`Densifier` strategy (its settings `densify`, default `Phase1Config.densify`), and the
iteration schedules (coarse resolution, SH degree, D_theta's warm-up) are a `Phase1Schedule`
(`FinishedSchedule` for a trainer that continues a finished model), both passed at
construction. A phase that adds to the step (Phase 2's motion strategy) is a plug-in
(`sync4d.phase1.plugin.TrainerPlugin`, `plug`), not a subclass: its hooks run at fixed points
of `step` (rates, loss terms before the backward pass, watched parameters, its own update
after Phase 1's, re-assignment after densification) and its state goes into the checkpoint
beside Phase 1's. One loop runs every phase: the pipeline's (`sync4d.pipeline.fit`), calling
`step`. Other modules read the trainer through public names (`image`, `background`), never
its private attributes.
"""

from __future__ import annotations

import math
import random

import numpy as np
import torch
import torch.nn.functional as F

from sync4d import watchdog
from sync4d.data.scene import Camera, Frame, Scene
from sync4d.metrics import psnr
from sync4d.phase1.config import Phase1Config
from sync4d.phase1.densify import Densifier, DensifyConfig
from sync4d.phase1.gaussians import PER_GAUSSIAN, DeformableGaussians
from sync4d.phase1.init import scene_extent, scene_scale
from sync4d.phase1.losses import photometric_loss
from sync4d.phase1.plugin import CheckpointKind, TrainerPlugin
from sync4d.phase1.static import StaticUpdate, motion_sparsity, update_static_set

__all__ = ["FinishedSchedule", "Phase1Config", "Phase1Schedule", "Phase1Trainer"]


class Phase1Schedule:
    """Phase 1's iteration schedules, asked at every step: coarse iterations (`coarse_scale`
    for the first `coarse_iterations`), the SH degree (one band more every
    `sh_degree_interval`) and D_theta's static warm-up and rate ramp (`static_warmup`,
    `lr_deform_warmup`)."""

    def __init__(self, config: Phase1Config) -> None:
        self.config = config

    def coarse(self, iteration: int) -> bool:
        """Whether `iteration` trains at `coarse_scale` (the first `coarse_iterations`)."""
        c = self.config
        return c.coarse_scale < 1.0 and iteration <= c.coarse_iterations

    def sh_degree(self, iteration: int, full: int) -> int:
        """SH degree used at `iteration` (at most `full`): one more every `sh_degree_interval`."""
        return min(full, (iteration - 1) // self.config.sh_degree_interval)

    def deform_active(self, iteration: int) -> bool:
        """Whether D_theta deforms the Gaussians at `iteration` (not during the static
        warm-up)."""
        return iteration > self.config.static_warmup

    def deform_lr_factor(self, iteration: int) -> float:
        """The warm-up ramp's factor on D_theta's and the embeddings' rates, in (0, 1]."""
        c = self.config
        if c.lr_deform_warmup <= 0:
            return 1.0
        return min(1.0, max(1, iteration - c.static_warmup) / c.lr_deform_warmup)


class FinishedSchedule:
    """The schedules once Phase 1 is over, for a trainer that continues its model (Phase 2):
    full resolution, the full SH degree, D_theta on at its full rate, whatever the config's
    Phase 1 schedules say. `Phase1Schedule`'s methods."""

    def coarse(self, iteration: int) -> bool:
        return False

    def sh_degree(self, iteration: int, full: int) -> int:
        return full

    def deform_active(self, iteration: int) -> bool:
        return True

    def deform_lr_factor(self, iteration: int) -> float:
        return 1.0


class Phase1Trainer:
    """Owns the optimizer, densifier and image cache for one `DeformableGaussians` model, and
    the training step; later phases plug into the step (`plug`, `sync4d.phase1.plugin`)."""

    #: The `kind` its checkpoints record without a plug-in that names another.
    KIND = CheckpointKind.PHASE1

    def __init__(
        self,
        model: DeformableGaussians,
        scene: Scene,
        config: Phase1Config | None = None,
        total_iterations: int | None = None,
        threads: int | None = None,
        *,
        densify: DensifyConfig | None = None,
        schedule: Phase1Schedule | FinishedSchedule | None = None,
    ) -> None:
        """`densify`: the densification strategy's settings (default `config.densify`);
        `schedule`: the iteration schedules (default `Phase1Schedule(config)`)."""
        self.model = model
        self.scene = scene
        self.config = config or Phase1Config()
        total = self.config.iterations if total_iterations is None else total_iterations
        self.total = max(1, total)
        self.threads = threads
        self.extent = scene_extent(scene)
        #: The watchdog's world scale: positions beyond 1e6 times it have diverged.
        self.watch_scale = scene_scale(scene)
        self.iteration = 0
        self.schedule: Phase1Schedule | FinishedSchedule = schedule or Phase1Schedule(self.config)
        self.densifier = Densifier(densify or self.config.densify, seed=self.config.seed)
        self._rng = random.Random(self.config.seed)
        self._images: dict[int, torch.Tensor] = {}
        #: Colour times alpha and alpha [H, W, 4] (or [H, W, 3] without alpha) of the
        #: training frames, for a background drawn at each step (`train_background`).
        self._layer_images: dict[int, torch.Tensor] = {}
        self._background = torch.tensor(self.config.background, dtype=torch.float32)
        self._coarse_images: dict[int, torch.Tensor] = {}
        #: Full-resolution pixels of the training frames so far; of those, the ones of coarse
        #: iterations, and the pixels those rendered instead (in this process): `fit`'s
        #: skip line.
        self.pixels = 0
        self.coarse_full_pixels = 0
        self.coarse_pixels = 0
        #: The last check of the static set (None before the first).
        self.last_static_update: StaticUpdate | None = None
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
            fused=True,  # one multithreaded kernel for all groups: ~4x faster than the default
        )
        #: What moves the Gaussians (`sync4d.phase1.motion`): the model's, or a new one of the
        #: configured kind; its Adam groups follow D_theta's.
        m.set_motion(m.motion_model.for_config(self.config))
        for name, p, lr in m.motion_model.param_groups(self):
            self.optimizer.add_param_group({"params": [p], "name": name, "lr": lr})
        #: The sorted distinct times of the training frames (a motion's regulariser draws
        #: second times from them).
        self.train_times = sorted({float(f.time) for f in scene.train})
        #: The plug-ins called at fixed points of each step, in order (`plug`).
        self.plugins: list[TrainerPlugin] = []

    def plug(self, plugin: TrainerPlugin) -> None:
        """Add `plugin` to every later step (`sync4d.phase1.plugin` says where it is called)."""
        self.plugins.append(plugin)

    @property
    def kind(self) -> CheckpointKind:
        """The checkpoint kind: the last plug-in's that names one, else `KIND`."""
        return next((p.kind for p in reversed(self.plugins) if p.kind), self.KIND)

    @property
    def phase_name(self) -> str:
        """The name the watchdog gives this trainer's failures ("Phase 1", or a plug-in's)."""
        return next((p.phase_name for p in reversed(self.plugins) if p.phase_name), "Phase 1")

    @property
    def background(self) -> torch.Tensor:
        """The RGB [3] (float32) composited behind the Gaussians (`Phase1Config.background`)."""
        return self._background

    def image(self, index: int, frame: Frame) -> torch.Tensor:
        """Training frame `index`'s target image [H, W, 3] (`frame`'s, composited on the
        background), loaded once and cached."""
        if index not in self._images:
            self._images[index] = torch.from_numpy(frame.load_image(self.config.background))
        return self._images[index]

    def step_background(self) -> torch.Tensor:
        """The RGB [3] (float32) behind this iteration's render and target: `background`, or
        for `train_background = "random"` a colour uniform in [0, 1]^3 drawn from a generator
        seeded by the run's seed and the iteration (a resumed run draws the same)."""
        if self.config.train_background != "random":
            return self._background
        generator = torch.Generator().manual_seed(self.config.seed * 1_000_003 + self.iteration)
        return torch.rand(3, generator=generator, dtype=torch.float32)

    def _layers(self, index: int, frame: Frame) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Training frame `index`'s colour times alpha [H, W, 3] and alpha [H, W, 1] (None
        without alpha; `Frame.load_layers`), loaded once and cached."""
        if index not in self._layer_images:
            colour, alpha = frame.load_layers()
            layers = colour if alpha is None else np.concatenate([colour, alpha], axis=-1)
            self._layer_images[index] = torch.from_numpy(layers)
        layers = self._layer_images[index]
        return (layers, None) if layers.shape[-1] == 3 else (layers[..., :3], layers[..., 3:])

    def target(self, index: int, frame: Frame, background: torch.Tensor) -> torch.Tensor:
        """Training frame `index`'s full-resolution target [H, W, 3] on `background` (this
        iteration's, `step_background`)."""
        if self.config.train_background != "random":
            return self.image(index, frame)
        colour, alpha = self._layers(index, frame)
        return colour if alpha is None else colour + background * (1.0 - alpha)

    def coarse(self) -> bool:
        """Whether the current iteration trains at `coarse_scale` (`schedule`)."""
        return self.schedule.coarse(self.iteration)

    def _coarse_view(
        self, index: int, frame: Frame, background: torch.Tensor | None = None
    ) -> tuple[Camera, torch.Tensor]:
        """`frame`'s camera and target image at `coarse_scale` on `background` (default
        `background`): the image area-averaged to the camera's size, cached until the coarse
        iterations end; colour times alpha and alpha are averaged apart, so the target on
        any background is exact."""
        background = self._background if background is None else background
        camera = frame.camera.scaled(self.config.coarse_scale)
        random_background = self.config.train_background == "random"
        if index not in self._coarse_images:
            if random_background:
                colour, alpha = self._layers(index, frame)
                full = colour if alpha is None else torch.cat([colour, alpha], dim=-1)
            else:
                full = self.image(index, frame)
            small = F.interpolate(full.permute(2, 0, 1).unsqueeze(0),
                                  size=(camera.height, camera.width), mode="area")  # fmt: skip
            self._coarse_images[index] = small[0].permute(1, 2, 0).contiguous()
        small = self._coarse_images[index]
        if random_background and small.shape[-1] == 4:
            return camera, small[..., :3] + background * (1.0 - small[..., 3:])
        return camera, small

    def decayed(self, start: float, final: float) -> float:
        """Log-linear interpolation from `start` to `final` over the run."""
        frac = min(1.0, self.iteration / self.total)
        if start <= 0 or final <= 0:
            return start
        return math.exp((1 - frac) * math.log(start) + frac * math.log(final))

    def _position_lr(self) -> float:
        """Log-linear decay from lr_means to lr_means_final over the run (scaled by extent)."""
        c = self.config
        return self.decayed(c.lr_means, c.lr_means_final) * self.extent

    def deform_active(self) -> bool:
        """Whether D_theta deforms the Gaussians at the current iteration (`schedule`)."""
        return self.schedule.deform_active(self.iteration)

    def deform_lr_factor(self) -> float:
        """The warm-up ramp's factor on D_theta's and the embeddings' rates (`schedule`)."""
        return self.schedule.deform_lr_factor(self.iteration)

    def update_learning_rates(self) -> None:
        """Set the rates of this iteration: the means' and D_theta's decays, the ramp; then
        the plug-ins set their own optimizers' rates."""
        c = self.config
        ramp = self.deform_lr_factor()
        for g in self.optimizer.param_groups:
            if g["name"] == "means":
                g["lr"] = self._position_lr()
            elif g["name"] == "deform":
                g["lr"] = ramp * self.decayed(c.lr_deform, c.lr_deform_final)
            elif g["name"] == "embeddings":
                g["lr"] = ramp * self.decayed(c.lr_embed, c.lr_embed_final)
        self.model.motion_model.update_learning_rates(self, ramp)
        for plugin in self.plugins:
            plugin.update_learning_rates()

    def step(self) -> dict[str, float]:
        """One iteration on a random training frame; returns loss, PSNR and N."""
        c = self.config
        if self.densifier.reset_due(self.iteration):
            self.densifier.reset_opacity(self.model, self.optimizer)
        self.iteration += 1
        motion = self.model.motion_model
        motion.begin_step(self)
        self.update_learning_rates()
        idx = self._rng.randrange(len(self.scene.train))
        frame = self.scene.train[idx]
        background = self.step_background()
        if self.coarse():
            camera, target = self._coarse_view(idx, frame, background)
            self.coarse_pixels += camera.width * camera.height
            self.coarse_full_pixels += frame.camera.width * frame.camera.height
        else:
            camera, target = frame.camera, self.target(idx, frame, background)
            self._coarse_images.clear()
        self.pixels += frame.camera.width * frame.camera.height
        degree = self.sh_degree_now()
        deformed = self.model.at_time(frame.time, deform=self.deform_active())
        out = self.model.render(
            camera, frame.time, sh_degree=degree, background=background,
            deformed=deformed, threads=self.threads, check=self.check_inputs,
        )  # fmt: skip
        out.means2d.retain_grad()
        loss = photometric_loss(
            out.features, target, c.lambda_l1, c.lambda_dssim, threads=self.threads
        )
        extra, extra_stats = self.auxiliary_loss(frame, deformed[0])
        if extra is not None:
            loss = loss + extra
        s = c.static
        if s.enabled and s.sparsity > 0 and self.deform_active() and self.model.last_offsets:
            sparse = motion_sparsity(self.model.last_offsets, self.extent,
                                     self.model.num_gaussians, s.sparsity_below)  # fmt: skip
            loss = loss + s.sparsity * sparse
        regulariser = motion.regulariser(self, frame.time) if self.deform_active() else None
        if regulariser is not None:
            loss = loss + regulariser
        loss = watchdog.check_loss(self.phase_name, self.iteration, loss)
        loss.backward()
        params, units = self.watched()
        watchdog.check_grads(self.phase_name, self.iteration, params, units)
        with torch.no_grad():
            self.densifier.accumulate(out.means2d.grad, out.radii, camera.width, camera.height)
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        watchdog.check_params(self.phase_name, self.iteration, params, units, self.watch_scale)
        motion.after_optimizer_step(self)
        changed = self.densifier.step(self.model, self.optimizer, self.iteration, self.extent)
        if any(changed.values()):
            self.on_gaussians_changed()
        if self.static_check_due(any(changed.values())):
            self.update_static()
        stats = {
            "loss": float(loss.detach()),
            "psnr": psnr(out.features.detach(), target),
            "gaussians": float(self.model.num_gaussians),
            **extra_stats,
            **motion.step_stats(self),
        }
        for plugin in self.plugins:
            plugin.after_step()
        return stats

    def check_inputs(self, inputs: dict[str, torch.Tensor]) -> None:
        """The watchdog's check of what this iteration's render receives (`render`'s
        `check`): NonFinite, naming the input, unless it is all finite."""
        watchdog.check_inputs(self.phase_name, self.iteration, inputs, scale=self.watch_scale)

    def watched(self) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
        """The parameters the watchdog checks each step (name -> tensor) and the unit of their
        rows (per-Gaussian tensors: "Gaussians")."""
        units = dict.fromkeys(PER_GAUSSIAN, "Gaussians")
        units.update(self.model.motion_model.watched_units())
        params = dict(self.model.named_parameters())
        for plugin in self.plugins:
            more, more_units = plugin.watched()
            params.update(more)
            units.update(more_units)
        return params, units

    def static_check_due(self, densified: bool) -> bool:
        """Whether the static set is re-checked after this iteration: from `static.start` on,
        every `static.every` iterations and after the last densification. Not after every
        densification: split and cloned children inherit their parent's flag, and a check
        after each one (hook, 3000 iterations: every 37) cost more than it found (0.92x)."""
        s = self.config.static
        if not s.enabled or self.iteration < s.start or not self.deform_active():
            return False
        if not self.model.motion_model.static_set_applies():
            return False
        d = self.densifier.config
        last_densification = densified and self.iteration + d.interval >= d.stop
        return last_densification or (self.iteration - s.start) % s.every == 0

    def static_check_times(self) -> torch.Tensor:
        """The training times D_theta is evaluated at to find static Gaussians: `static.times`
        evenly spread over the sorted distinct times of the training frames."""
        times = self.train_times
        k = min(len(times), self.config.static.times)
        picks = torch.linspace(0, len(times) - 1, k).round().long()
        return torch.tensor(times, dtype=torch.float32)[picks]

    def update_static(self) -> StaticUpdate:
        """Re-check which Gaussians are static (`sync4d.phase1.static.update_static_set`)."""
        self.last_static_update = update_static_set(
            self.model, self.static_check_times(), self.extent, self.config.static
        )
        return self.last_static_update

    def sh_degree_now(self) -> int:
        """SH degree used at the current iteration (`schedule`)."""
        return self.schedule.sh_degree(self.iteration, self.model.sh_degree)

    def auxiliary_loss(
        self, frame: Frame, means: torch.Tensor
    ) -> tuple[torch.Tensor | None, dict[str, float]]:
        """The plug-ins' loss terms added to the photometric loss for `frame`, given the
        deformed means [N, 3] the render used, and their scalars to report; Phase 1 alone has
        none."""
        total: torch.Tensor | None = None
        stats: dict[str, float] = {}
        for plugin in self.plugins:
            loss, more = plugin.loss(frame, means)
            if loss is not None:
                total = loss if total is None else total + loss
            stats.update(more)
        return total, stats

    def on_gaussians_changed(self) -> None:
        """After densification changed the number of Gaussians: the plug-ins follow (Phase 2
        re-assigns)."""
        for plugin in self.plugins:
            plugin.on_gaussians_changed()

    # -- checkpoint state -------------------------------------------------------------------
    def state(self) -> tuple[dict[str, torch.Tensor], dict]:
        """Everything needed to continue training, as tensors (the model's, Adam's moments
        ``optim.<group>.<param>.*``, the densification statistics and generator) and JSON-ready
        settings (`KIND`, iteration, learning rates, Adam step counts, the frame sampler's
        state); `from_state` rebuilds the trainer from them."""
        tensors, meta = self.model.state()
        steps: dict[str, float] = {}
        for gi, group in enumerate(self.optimizer.param_groups):
            for pi, p in enumerate(group["params"]):
                st = self.optimizer.state.get(p)
                if st:
                    for k in ("exp_avg", "exp_avg_sq"):
                        tensors[f"optim.{gi}.{pi}.{k}"] = st[k]
                    steps[f"{gi}.{pi}"] = float(st["step"])
        tensors["densify.grad_accum"] = self.densifier.grad_accum
        tensors["densify.count"] = self.densifier.count
        tensors["densify.max_radius"] = self.densifier.max_radius
        tensors["densify.rng"] = self.densifier.generator.get_state()
        version, internal, gauss = self._rng.getstate()
        meta.update({
            "kind": self.kind,
            "iteration": self.iteration,
            "total_iterations": self.total,
            "lrs": [g["lr"] for g in self.optimizer.param_groups],
            "adam_steps": steps,
            "python_rng": [version, list(internal), gauss],
            "background": list(self.config.background),
        })  # fmt: skip
        for plugin in self.plugins:
            more, more_meta = plugin.state()
            tensors.update(more)
            meta.update(more_meta)
        return tensors, meta

    @classmethod
    def from_state(
        cls,
        tensors: dict[str, torch.Tensor],
        meta: dict,
        scene: Scene,
        *,
        config: Phase1Config | None = None,
        total_iterations: int | None = None,
        threads: int | None = None,
        near: float | None = None,
    ) -> Phase1Trainer:
        """The trainer `state` described, exactly as it was (`total_iterations` extends or
        shortens the run, default the stored length; the learning-rate schedules follow it).
        Raises KeyError for a missing tensor or setting, ValueError for one that does not fit."""
        model = DeformableGaussians.from_state(tensors, meta, near)
        total = total_iterations or meta["total_iterations"]
        trainer = cls(model, scene, config, total_iterations=total, threads=threads)
        trainer.restore(tensors, meta)
        return trainer

    def restore(self, tensors: dict[str, torch.Tensor], meta: dict) -> None:
        """Load the loop state of `state` (iteration, optimizer, densifier, frame sampler) into
        this trainer, whose model already holds the stored Gaussians."""
        self.iteration = int(meta["iteration"])
        for gi, group in enumerate(self.optimizer.param_groups):
            group["lr"] = meta["lrs"][gi]
            for pi, p in enumerate(group["params"]):
                key = f"{gi}.{pi}"
                if key in meta["adam_steps"]:
                    self.optimizer.state[p] = {
                        "step": torch.tensor(meta["adam_steps"][key]),
                        "exp_avg": tensors[f"optim.{key}.exp_avg"].clone(),
                        "exp_avg_sq": tensors[f"optim.{key}.exp_avg_sq"].clone(),
                    }
        self.densifier.grad_accum = tensors["densify.grad_accum"].clone()
        self.densifier.count = tensors["densify.count"].clone()
        if "densify.max_radius" in tensors:  # absent in checkpoints before sync4d 0.2
            self.densifier.max_radius = tensors["densify.max_radius"].clone()
        if "densify.rng" in tensors:  # absent in older checkpoints: the seed's generator
            try:
                self.densifier.generator.set_state(tensors["densify.rng"].clone())
            except (RuntimeError, TypeError) as e:
                raise ValueError(f"bad 'densify.rng' generator state ({e})") from None
        try:
            version, internal, gauss = meta["python_rng"]
            self._rng = random.Random()
            self._rng.setstate((version, tuple(internal), gauss))
        except (ValueError, TypeError) as e:
            raise ValueError(f"bad frame-sampler state ({e})") from None
