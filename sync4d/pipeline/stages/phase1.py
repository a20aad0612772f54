"""Phase 1 as a stage: the initial Gaussians (the dataset's points, triangulated ones or
random), the advice for a scene far from the size the absolute lengths are for, and the
trainer of the canonical Gaussians and D_theta; what it skipped (`phase1_skips`).
"""

from __future__ import annotations

import torch

from sync4d.config import ConfigError, RunConfig
from sync4d.data import Scene
from sync4d.events import Override, ScaleAdvice, emit
from sync4d.phase1.init import initial_model, scene_extent, with_initial_points
from sync4d.phase1.trainer import Phase1Trainer
from sync4d.pipeline.stages.base import FitState, TrainingStage
from sync4d.runs import CheckpointKind

__all__ = ["LENGTH_TOLERANCE", "PHASE1", "REFERENCE_EXTENT", "SSIM_WINDOW", "Phase1Stage",
           "coarse_problem", "length_advice", "phase1_skips"]  # fmt: skip

#: The scene extent (3DGS: 1.1 times the cameras' radius) the absolute lengths' defaults are
#: for: D-NeRF's scenes (cameras 4.03 units from the objects) and the embedded one.
REFERENCE_EXTENT = 4.4
#: Scenes whose extent is off the reference by more than this factor get `length_advice`.
LENGTH_TOLERANCE = 10.0


def length_advice(extent: float, p1) -> ScaleAdvice | None:
    """The advice for a scene whose size is far from the one the absolute lengths (`near`,
    `init_scale`, `deform.scale_position`, `deform.position_unit`) are for: the settings that
    scale them to it, or None
    when the scene is within `LENGTH_TOLERANCE` of `REFERENCE_EXTENT` or they were set already.
    Measured (docs/results/stability.md): the embedded scene scaled by 1e-3 loses 6.3 dB with
    the defaults, and matches the unscaled one with the lengths scaled alike."""
    ratio = extent / REFERENCE_EXTENT
    d = p1.deform
    lengths = (p1.near, p1.init_scale, d.scale_position, d.position_unit)
    defaults = lengths == (0.01, 0.02, 0.1, 1.0)
    if not defaults or 1.0 / LENGTH_TOLERANCE <= ratio <= LENGTH_TOLERANCE:
        return None
    return ScaleAdvice(ratio, extent, REFERENCE_EXTENT, (
        Override("phase1.near", 0.01 * ratio), Override("phase1.init_scale", 0.02 * ratio),
        Override("phase1.deform.scale_position", 0.1 * ratio),
        Override("phase1.deform.position_unit", ratio),
    ))  # fmt: skip


def phase1_skips(trainer: Phase1Trainer) -> dict[str, int | float]:
    """What Phase 1 skipped in this process, for each switch that is on (the `Skipped` event's
    counts): D_theta on the Gaussians (control nodes carry the motion: ``nodes``,
    ``nodes_from``, ``nodes_added``, ``nodes_removed``) or on static Gaussians
    (`static_skip_counts`), pixels of the coarse iterations (``coarse_iterations``,
    ``coarse_scale``, ``pixels_saved``: a fraction), transparent Gaussians pruned after
    densification (``pruned``, ``prune_opacity``); ``gaussians`` the count now."""
    c = trainer.config
    out: dict[str, int | float] = {"gaussians": trainer.model.num_gaussians}
    out.update(trainer.model.motion_model.skip_counts(trainer))
    if c.coarse_iterations > 0 and c.coarse_scale < 1.0 and trainer.pixels:
        out.update(coarse_iterations=c.coarse_iterations, coarse_scale=c.coarse_scale,
                   pixels_saved=(trainer.coarse_full_pixels - trainer.coarse_pixels)
                   / trainer.pixels)  # fmt: skip
    if c.densify.prune_after_stop:
        out.update(pruned=trainer.densifier.pruned_transparent,
                   prune_opacity=c.densify.prune_opacity)  # fmt: skip
    return out


#: The photometric loss's SSIM window (`sync4d.phase1.losses`): an image's smallest side.
SSIM_WINDOW = 3


def coarse_problem(scene: Scene, p1, iteration: int = 0) -> str | None:
    """Why the coarse iterations cannot train on `scene`'s images (one sentence), or None:
    `coarse_scale` shrinks the smallest training image below the SSIM window."""
    if p1.coarse_scale >= 1.0 or p1.coarse_iterations <= iteration or not scene.train:
        return None
    small = min((f.camera for f in scene.train), key=lambda c: min(c.width, c.height))
    coarse = small.scaled(p1.coarse_scale)
    if min(coarse.width, coarse.height) >= SSIM_WINDOW:
        return None
    need = SSIM_WINDOW / min(small.width, small.height)
    return (f"phase1.coarse_scale = {p1.coarse_scale:g} shrinks the {small.width}x{small.height} "
            f"training images to {coarse.width}x{coarse.height} pixels, below the loss's "
            f"{SSIM_WINDOW}x{SSIM_WINDOW} SSIM window; raise phase1.coarse_scale to at least "
            f"{need:.3g} or set phase1.coarse_iterations = 0")


class Phase1Stage(TrainingStage):
    """Phase 1: a new model from the initial points, trained for `phase1.iterations`."""

    phase = 1
    name = "phase1"
    task = "fit"
    kind = CheckpointKind.PHASE1
    fresh = True

    def iterations(self, cfg: RunConfig) -> int:
        return cfg.phase1.iterations

    def start(self, fit: FitState) -> None:
        p1 = fit.cfg.phase1
        if (problem := coarse_problem(fit.scene, p1)) is not None:
            raise ConfigError(problem)
        scene = with_initial_points(fit.scene, p1, threads=torch.get_num_threads())
        model = initial_model(
            scene, p1.init_points, p1.sh_degree, p1.deform, p1.init_box_fraction, p1.seed,
            near=p1.near, init_scale=p1.init_scale,
        )  # fmt: skip
        advice = length_advice(scene_extent(scene), p1)
        if advice:
            emit(advice)
        fit.scene = scene
        fit.trainer = Phase1Trainer(model, scene, p1, p1.iterations, threads=fit.n_threads)

    def resume(self, tensors, meta, scene, *, config=None, phase2=None,
               total_iterations=None, threads=None, near=None) -> Phase1Trainer:  # fmt: skip
        trainer = Phase1Trainer.from_state(tensors, meta, scene, config=config,
                                           threads=threads, total_iterations=total_iterations,
                                           near=near)  # fmt: skip
        if (problem := coarse_problem(scene, trainer.config, trainer.iteration)) is not None:
            raise ConfigError(problem)
        return trainer

    def counts(self, fit: FitState) -> dict:
        return phase1_skips(fit.trainer)


#: The Phase 1 stage.
PHASE1 = Phase1Stage()
