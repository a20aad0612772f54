"""Phase 1's settings (paper Sec. 3.1, Appendix A; the paper's values as defaults), the section
``[phase1]`` of a run config, with its sections: D_theta (`deform`), densification
(`densify`), static Gaussians (`static`) and control nodes (`nodes`). Every iteration count a
shorter budget scales is declared `ranged(..., scales=floor)` (`sync4d.config.with_budget`
scales what is marked, not a list); ranges are checked by the config, once.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sync4d.phase1.deform import DeformConfig
from sync4d.phase1.densify import DensifyConfig
from sync4d.phase1.init import INIT_SOURCES
from sync4d.phase1.motion import MOTIONS
from sync4d.phase1.nodes import NodeConfig
from sync4d.phase1.static import StaticConfig
from sync4d.settings import choice, ranged

__all__ = ["Phase1Config"]


@dataclass(frozen=True)
class Phase1Config:
    """Phase 1: the model (SH degree, D_theta, initial Gaussians, near plane), the length of
    training, learning rates (3DGS values for Gaussian attributes; 5e-4 for D_theta and
    embeddings, Appendix A), schedules and loss weights.

    Settings that must go together (checked when the config is read, `combination_problem`):
    `lambda_l1` and `lambda_dssim` are not both 0 (no photometric loss: nothing is learnt);
    `static_warmup` is below `iterations` (else D_theta never trains); with densification on
    (`densify.stop` > 0) `densify.start` is below `densify.stop` and below `iterations` (else
    no iteration densifies); with `motion = "nodes"`, `nodes.init_after` is below
    `iterations` (else the nodes never take over); with `static.enabled`, `static.start` is
    at most `iterations` (else no Gaussian is ever checked). `fit --iters` scales these
    counts together, so a config that passes keeps passing at any budget."""

    #: Training iterations (Appendix A: 30k).
    iterations: int = ranged(30_000, 1)
    #: Spherical-harmonics degree of the Gaussians' colours (0-3).
    sh_degree: int = ranged(3, 0, 3)
    deform: DeformConfig = field(default_factory=DeformConfig)
    #: What D_theta moves (`sync4d.phase1.motion`, one registered plug-in each): "gaussians"
    #: (the paper: every Gaussian) or "nodes" (a few hundred control nodes whose rigid motions
    #: each Gaussian blends, after a coarse stage of per-Gaussian D_theta; `nodes`,
    #: `sync4d.phase1.nodes`).
    motion: str = choice("gaussians", check=lambda v: None if v in MOTIONS else
                         f"expected one of {', '.join(MOTIONS)}",
                         text="a registered motion (sync4d.phase1.motion): gaussians, nodes")
    #: The control nodes of `motion = "nodes"`.
    nodes: NodeConfig = field(default_factory=NodeConfig)
    #: Near clipping plane of every render (training, evaluation, `render`), world units;
    #: Gaussians whose centre is closer to the camera are not drawn. Capture domes need more
    #: than the default: each camera's own housing, reconstructed from the cameras facing it,
    #: sits a few centimetres in front of its lens and would cover its whole view.
    near: float = ranged(0.01, 0.0, lo_open=True, what="distance")
    #: Initial scale of every Gaussian, world units (Appendix A: 0.02). Like `near` and
    #: `deform.scale_position` it is an absolute length, the paper's for scenes the size of
    #: D-NeRF's (cameras about 4 units from the objects); `fit` says what to set for a scene
    #: of another size (`sync4d.pipeline.fit.length_advice`; docs/results/stability.md).
    init_scale: float = ranged(0.02, 0.0, lo_open=True, what="distance")
    #: Where the initial Gaussians come from: "points" (the dataset's point cloud, e.g.
    #: COLMAP's), "triangulate" (SIFT matches of the training cameras at one instant,
    #: triangulated with the dataset's poses; multi-view captures), "random" (`init_points`
    #: uniform in a cube), or "auto": points if the dataset has them, else triangulate when
    #: several cameras see one instant, else random.
    init_from: str = choice("auto", INIT_SOURCES)
    #: Random initial Gaussians when the dataset has no point cloud (3DGS uses 100k on a GPU).
    init_points: int = ranged(20_000, 1)
    #: Points added to the initial ones on the wall of a capture dome (`init_from` points or
    #: triangulate): directions uniform on the sphere through the cameras, at
    #: `init_dome_radius` times its radius, coloured from the first instant's training images
    #: (`sync4d.phase1.init.dome_points`). 0 (default) adds none. A dome's wall is seen
    #: by few cameras at grazing angles and triangulates sparsely; without it, Gaussians
    #: floating in front of the wall explain the training views and fog the novel ones.
    init_dome_points: int = ranged(0, 0)
    #: Radius of those points as a multiple of the cameras' sphere (the cameras hang on the
    #: wall, so just behind them).
    init_dome_radius: float = ranged(1.03, 0.5, 4.0)
    #: Half-size of the random-init cube as a fraction of the mean camera distance.
    init_box_fraction: float = ranged(0.33, 0.0, lo_open=True)
    #: Adam rate of the canonical means, times the scene extent (3DGS).
    lr_means: float = ranged(1.6e-4, 0.0, lo_open=True)
    #: The means' rate at the end of training (log-linear decay, times the extent).
    lr_means_final: float = ranged(1.6e-6, 0.0, lo_open=True)
    #: Adam rate of the canonical rotations.
    lr_quats: float = ranged(1e-3, 0.0, lo_open=True)
    #: Adam rate of the log-scales.
    lr_scales: float = ranged(5e-3, 0.0, lo_open=True)
    #: Adam rate of the opacity logits.
    lr_opacity: float = ranged(5e-2, 0.0, lo_open=True)
    #: Adam rate of the SH DC colours (the higher bands get 1/20 of it).
    lr_sh: float = ranged(2.5e-3, 0.0, lo_open=True)
    #: Adam rate of D_theta (Appendix A).
    lr_deform: float = ranged(5e-4, 0.0, lo_open=True)
    #: Adam rate of the per-Gaussian embeddings (Appendix A).
    lr_embed: float = ranged(5e-4, 0.0, lo_open=True)
    #: D_theta's rate at the end of training: it decays log-linearly (the position-lr rule).
    lr_deform_final: float = ranged(5e-6, 0.0, lo_open=True)
    #: The embeddings' rate at the end of training (log-linear decay).
    lr_embed_final: float = ranged(5e-6, 0.0, lo_open=True)
    #: Iterations between steps of the SH degree (one band more each time).
    sh_degree_interval: int = ranged(1_000, 1, scales=1)
    #: Iterations at the start that train the canonical Gaussians alone, D_theta off (the
    #: static warm-up of Deformable-3DGS): the static scene settles first, so its gradients do
    #: not drown D_theta's time signal. 0 disables it; below `iterations` (else D_theta
    #: never trains: refused when the config is read).
    static_warmup: int = ranged(0, 0, scales=0)
    #: Iterations (after the static warm-up) over which D_theta's and the embeddings' learning
    #: rates ramp linearly from 0 to their schedule. 0 (the paper) starts them at full rate.
    #: Adam's first steps move every weight of the zero-initialised head by about its rate in
    #: one direction, which shifts all Gaussians together: with a position scale of 1.0 and
    #: a rate of 1.6e-3 this threw hook's whole scene out of view within 100 iterations and
    #: it never recovered (docs/results/phase1-articulated.md).
    lr_deform_warmup: int = ranged(0, 0, scales=0)
    #: Weight of the L1 term of the photometric loss.
    lambda_l1: float = ranged(0.8, 0.0)
    #: Weight of the D-SSIM term of the photometric loss (not 0 with `lambda_l1`: refused).
    lambda_dssim: float = ranged(0.2, 0.0)
    #: RGB in [0, 1] composited behind the Gaussians and into RGBA training images.
    background: tuple[float, float, float] = ranged((1.0, 1.0, 1.0), 0.0, 1.0, length=3)
    #: The background of each training step: "fixed" (`background`, the paper) or "random"
    #: (a colour drawn uniformly in [0, 1]^3 at every step, behind the Gaussians and in the
    #: RGBA target alike: SC-GS's `random_bg_color`). On a fixed background the model may
    #: paint Gaussians of the background's colour that no view can see against it; a random
    #: one shows them, so only alpha explains the image. Images without alpha train on
    #: themselves either way. `background` stays the run's colour for `eval` and `render`.
    train_background: str = choice("fixed", ("fixed", "random"))
    #: Seed of the initial Gaussians, D_theta's weights, the frame order and densification.
    seed: int = ranged(42, 0, 2**32 - 1)
    #: Iterations at the start that train at a reduced resolution (`coarse_scale`): the
    #: camera and target image shrink, so compositing and the loss cost a fraction while the
    #: scene is still blurry anyway. 0 (the paper) trains at full resolution throughout.
    coarse_iterations: int = ranged(0, 0, scales=0)
    #: Image scale of those iterations (targets area-averaged).
    coarse_scale: float = ranged(0.5, 0.0, 1.0, lo_open=True)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    #: Static Gaussians skip D_theta (`sync4d.phase1.static`; off by default).
    static: StaticConfig = field(default_factory=StaticConfig)

    def combination_problem(self) -> str | None:
        """What is wrong with these settings together (each is within its own range), or None;
        `sync4d.config.validate` calls it once all overrides are applied. Each rule refuses a
        combination that trains without effect (the window it sets is empty)."""
        it, d = self.iterations, self.densify
        if self.lambda_l1 == 0 and self.lambda_dssim == 0:
            return ("lambda_l1 = 0 and lambda_dssim = 0 leave no photometric loss, so nothing is "
                    "learnt from the images; raise phase1.lambda_l1 or phase1.lambda_dssim")
        if self.static_warmup >= it:
            return (f"static_warmup = {self.static_warmup} is not below iterations = {it}, so "
                    "D_theta never trains; lower phase1.static_warmup")
        if d.stop > 0 and d.start >= d.stop:
            return (f"densify.start = {d.start} is not below densify.stop = {d.stop}, so no "
                    "iteration densifies; lower phase1.densify.start, raise "
                    "phase1.densify.stop, or set phase1.densify.stop = 0 to turn it off")
        if d.stop > 0 and d.start >= it:
            return (f"densify.start = {d.start} is not below iterations = {it}, so no iteration "
                    "densifies; lower phase1.densify.start (fit --iters scales it with the run) "
                    "or set phase1.densify.stop = 0 to turn it off")
        if self.motion == "nodes" and self.nodes.init_after >= it:
            return (f"nodes.init_after = {self.nodes.init_after} is not below iterations = "
                    f"{it}, so the control nodes never take over (motion = \"nodes\"); lower "
                    "phase1.nodes.init_after")
        if self.static.enabled and self.static.start > it:
            return (f"static.start = {self.static.start} is after iterations = {it}, so no "
                    "Gaussian is ever checked; lower phase1.static.start or set "
                    "phase1.static.enabled = false")
        return None
