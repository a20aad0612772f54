"""Phase 1 scene model: canonical Gaussians (Appendix A initialisation) plus the deformation
MLP, rendered at any time through :mod:`sync4d.raster`.

Parameters are stored unconstrained: log-scales, opacity logits, SH coefficients (DC band
`sh_dc` [N, 1, 3] and higher bands `sh_rest` [N, 15, 3]), unnormalised quaternions (w, x, y, z),
and a 32-d embedding per Gaussian.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from sync4d import raster, watchdog
from sync4d.data.scene import Camera
from sync4d.phase1.deform import DeformationMLP, DeformConfig
from sync4d.phase1.motion import GaussianMotion, Motion, NodesMotion, motion_from_state
from sync4d.phase1.nodes import NodeConfig, NodeMotion

__all__ = ["DeformableGaussians", "PER_GAUSSIAN", "rgb_to_sh_dc", "SH_C0"]

#: Constant of the degree-0 real SH basis function.
SH_C0 = 0.28209479177387814

#: Per-Gaussian parameters of `DeformableGaussians` (dimension 0 is N).
PER_GAUSSIAN = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "embeddings")


def rgb_to_sh_dc(rgb: Tensor) -> Tensor:
    """DC SH coefficient whose colour (with the 3DGS +0.5 offset) is `rgb` [N, 3]."""
    return (rgb - 0.5) / SH_C0


class DeformableGaussians(nn.Module):
    """Canonical Gaussians + D_theta. `points` [N, 3] and `colors` [N, 3] in [0, 1] seed them
    (Appendix A: identity rotation, scale 0.02, opacity 0.1, embeddings ~ N(0, 0.01^2))."""

    def __init__(
        self,
        points: Tensor,
        colors: Tensor | None = None,
        sh_degree: int = 3,
        config: DeformConfig | None = None,
        init_scale: float = 0.02,
        init_opacity: float = 0.1,
        embed_std: float = 0.01,
        generator: torch.Generator | None = None,
        near: float = 0.01,
    ) -> None:
        super().__init__()
        if points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"points: expected shape [N, 3], got {list(points.shape)}")
        if not torch.isfinite(points).all():
            raise ValueError("points: contains NaN or inf")
        n = points.shape[0]
        if colors is None:
            colors = torch.full((n, 3), 0.5)
        if colors.shape != (n, 3):
            raise ValueError(f"colors: expected shape [{n}, 3], got {list(colors.shape)}")
        self.config = config or DeformConfig()
        self.sh_degree = sh_degree
        if not (math.isfinite(near) and near > 0):
            raise ValueError(f"near: must be a finite distance > 0 (world units), got {near}")
        #: Near clipping plane of every render, world units: Gaussians whose centre is closer
        #: to the camera are not drawn (see `Phase1Config.near`).
        self.near = float(near)
        k = (sh_degree + 1) ** 2
        f32 = torch.float32
        self.means = nn.Parameter(points.to(f32).clone())
        quats = torch.zeros(n, 4, dtype=f32)
        quats[:, 0] = 1.0
        self.quats = nn.Parameter(quats)
        self.log_scales = nn.Parameter(torch.full((n, 3), math.log(init_scale), dtype=f32))
        logit = math.log(init_opacity / (1.0 - init_opacity))
        self.opacity_logits = nn.Parameter(torch.full((n,), logit, dtype=f32))
        self.sh_dc = nn.Parameter(rgb_to_sh_dc(colors.to(f32)).unsqueeze(1))
        self.sh_rest = nn.Parameter(torch.zeros(n, k - 1, 3, dtype=f32))
        z = torch.randn(n, self.config.embed_dim, generator=generator, dtype=f32) * embed_std
        self.embeddings = nn.Parameter(z)
        self.deform = DeformationMLP(self.config, generator)
        #: Static Gaussians [N] bool: their canonical state is their state at every time and
        #: D_theta is not evaluated for them (`sync4d.phase1.static`); none by default.
        self.static = torch.zeros(n, dtype=torch.bool)
        #: Rows D_theta evaluated and rows it skipped (static) in `at_time` calls so far: the
        #: counters behind `fit`'s "skipped" line and the tests of the skip.
        self.deform_rows = 0
        self.deform_rows_skipped = 0
        #: D_theta's offsets (dx, dw, dl) of the moving rows at the last deformed `at_time`
        #: call (None before one, and when every Gaussian is static): the motion-sparsity
        #: loss reads them (`sync4d.phase1.static.motion_sparsity`).
        self.last_offsets: tuple[Tensor, Tensor, Tensor] | None = None
        #: What moves the Gaussians (`sync4d.phase1.motion`): D_theta per Gaussian until a
        #: trainer configures another (`Phase1Trainer`) or a checkpoint loads one.
        self.motion_model: Motion = GaussianMotion()
        #: The names under which the motion's modules are registered (`attach_motion_modules`).
        self._motion_module_names: tuple[str, ...] = ()

    @property
    def motion(self) -> str:
        """What moves the Gaussians now: "gaussians" (D_theta per Gaussian), "nodes" (control
        nodes), or another registered motion's name (`Motion.current`)."""
        return self.motion_model.current

    def set_motion(self, motion: Motion) -> None:
        """Let `motion` move the Gaussians from now on (its modules registered)."""
        self.motion_model = motion
        self.attach_motion_modules()

    def attach_motion_modules(self) -> None:
        """Register the motion's modules (`Motion.modules`) as this model's submodules, and
        drop those of a former motion, so their parameters are the model's."""
        for name in self._motion_module_names:
            delattr(self, name)
        modules = self.motion_model.modules()
        for name, module in modules.items():
            setattr(self, name, module)
        self._motion_module_names = tuple(modules)

    def use_nodes(self, config: NodeConfig, generator: torch.Generator | None = None
                  ) -> NodeMotion:  # fmt: skip
        """Hand the motion to control nodes sampled among the Gaussians (`NodesMotion.sample`)
        with node settings `config`. Returns the nodes."""
        motion = NodesMotion()
        self.set_motion(motion)
        return motion.sample(self, config, generator)

    @classmethod
    def random_in_box(
        cls, n: int, lo: Tensor, hi: Tensor, generator: torch.Generator | None = None, **kw
    ) -> DeformableGaussians:
        """`n` Gaussians uniform in the box [lo, hi] with random colours (no point cloud)."""
        u = torch.rand(n, 3, generator=generator)
        colors = torch.rand(n, 3, generator=generator)
        return cls(lo + u * (hi - lo), colors, generator=generator, **kw)

    def state(self) -> tuple[dict[str, Tensor], dict]:
        """The model as tensors (``gaussians.<name>`` [N, ...] for `PER_GAUSSIAN`,
        ``deform.<key>`` D_theta's weights) and JSON-ready settings (SH degree, near plane,
        D_theta's config), for checkpoints; `from_state` rebuilds it."""
        tensors = {f"gaussians.{n}": getattr(self, n).detach() for n in PER_GAUSSIAN}
        if bool(self.static.any()):  # absent: none static (and files of older versions)
            tensors["gaussians.static"] = self.static.to(torch.float32)
        tensors.update({f"deform.{k}": v.detach() for k, v in self.deform.state_dict().items()})
        meta = {"sh_degree": self.sh_degree, "near": self.near,
                "deform_config": dataclasses.asdict(self.config)}  # fmt: skip
        more, more_meta = self.motion_model.state()  # nothing for D_theta per Gaussian
        tensors.update(more)
        meta.update(more_meta)
        return tensors, meta

    @classmethod
    def from_state(
        cls, tensors: dict[str, Tensor], meta: dict, near: float | None = None
    ) -> DeformableGaussians:
        """The model `state` returned (`near` replaces the stored near plane). Raises KeyError
        for a missing tensor or setting, ValueError for a shape or weight that does not fit."""
        model = cls(
            tensors["gaussians.means"], None, sh_degree=int(meta["sh_degree"]),
            config=DeformConfig(**meta["deform_config"]),
            near=float(meta.get("near", 0.01) if near is None else near),
        )  # fmt: skip
        with torch.no_grad():
            for n in PER_GAUSSIAN:
                src = tensors[f"gaussians.{n}"]
                if src.shape != getattr(model, n).shape:
                    want = list(getattr(model, n).shape)
                    got = list(src.shape)
                    raise ValueError(f"'gaussians.{n}' has shape {got}, expected {want}")
                getattr(model, n).copy_(src)
        static = tensors.get("gaussians.static")
        if static is not None:
            if static.shape != (model.num_gaussians,):
                raise ValueError(f"'gaussians.static' has shape {list(static.shape)}, expected "
                                 f"[{model.num_gaussians}]")  # fmt: skip
            model.static = static > 0.5
        model.set_motion(motion_from_state(model, tensors, meta))
        deform = {k.removeprefix("deform."): v for k, v in tensors.items()
                  if k.startswith("deform.")}  # fmt: skip
        try:
            model.deform.load_state_dict(deform)
        except RuntimeError as e:
            raise ValueError(f"inconsistent deformation weights ({e})") from None
        return model

    @property
    def num_gaussians(self) -> int:
        """Number of Gaussians N."""
        return self.means.shape[0]

    def at_time(self, t: float, deform: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """Deformed means [N, 3], unit quaternions [N, 4] and scales [N, 3] at time `t`
        (the canonical Gaussians when `deform` is False)."""
        q0 = self.quats / self.quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        if not deform:
            return self.means, q0, torch.exp(self.log_scales)
        return self.motion_model.deformed(self, t, q0)

    def render(
        self,
        camera: Camera,
        t: float,
        sh_degree: int | None = None,
        background: Tensor | None = None,
        deform: bool = True,
        deformed: tuple[Tensor, Tensor, Tensor] | None = None,
        sh_dc: Tensor | None = None,
        check: Callable[[dict[str, Tensor]], None] | None = None,
        **raster_kw,
    ) -> raster.RasterOutput:
        """Render the scene deformed to time `t` from `camera` (RGB features from SH of degree
        `sh_degree`, default the model's; the canonical scene when `deform` is False).
        `deformed` passes `at_time(t)`'s result when the caller already computed it; `sh_dc`
        [N, 1, 3] replaces the model's base colours. `check` (the watchdog's) sees what the
        rasteriser is about to receive, by name (``means``, ``quats``, ``scales``,
        ``opacities``, ``sh``, the node motion's ``node_*``; then ``colors``), before it does;
        without one the watchdog checks them as phase "Rendering" (a NaN is its message, not
        the rasteriser's ValueError)."""
        if check is None:
            check = _rendering_check
        means, quats, scales = deformed if deformed is not None else self.at_time(t, deform)
        viewmat = torch.as_tensor(camera.viewmat, dtype=torch.float32)
        coeffs = torch.cat([self.sh_dc if sh_dc is None else sh_dc, self.sh_rest], dim=1)
        degree = self.sh_degree if sh_degree is None else sh_degree
        opacities = torch.sigmoid(self.opacity_logits)
        if check is not None:
            check({"means": means, "quats": quats, "scales": scales, "opacities": opacities,
                   "sh": coeffs, **self.node_motion()})  # fmt: skip
        # The colours on the rasterizer's threads too: without them SH ran on all cores
        # (rayon's default pool) in a `fit --threads 1` (issue 51).
        threads = raster_kw.get("threads")
        colors = raster.sh_features(means, coeffs, viewmat, degree, threads=threads)
        if check is not None:
            check({"colors": colors})
        K = torch.as_tensor(camera.K, dtype=torch.float32)
        raster_kw.setdefault("near", self.near)
        return raster.rasterize(
            means, quats, scales, opacities, colors, viewmat, K,
            camera.width, camera.height, background=background, **raster_kw,
        )  # fmt: skip

    def node_motion(self) -> dict[str, Tensor]:
        """What the motion's last deformation fed the render (`Motion.render_inputs`: the
        node motion's rotations, translations and log-scale offsets) by the watchdog's names;
        {} for D_theta per Gaussian."""
        return self.motion_model.render_inputs()


def _rendering_check(inputs: dict[str, Tensor]) -> None:
    """The watchdog's check of a render outside training (`render` without `check`)."""
    watchdog.check_inputs("Rendering", None, inputs)
