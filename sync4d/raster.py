"""Differentiable Gaussian splatting on the CPU: the torch face of the Rust rasterizer.

One call renders a camera view of 3D Gaussians::

    out = rasterize(means, quats, scales, opacities, features, viewmat, K, width, height)
    out.features  # [H, W, C]  composited features (+ background where transparent)
    out.alpha     # [H, W, 1]  accumulated opacity
    out.depth     # [H, W, 1]  expected camera depth (0 where alpha == 0)

Inputs (CPU tensors, all float32 — the fast tiled path — or all float64 — the plain reference
path used for gradient checks):

- ``means``      [N, 3] world positions
- ``quats``      [N, 4] rotations (w, x, y, z), need not be normalised
- ``scales``     [N, 3] standard deviations along the local axes (positive, not log-scales)
- ``opacities``  [N]    in [0, 1] (not logits)
- ``features``   [N, C] any channel count C >= 1: RGB, object ids, embeddings
- ``viewmat``    [4, 4] world-to-camera, OpenCV axes (x right, y down, z forward)
- ``K``          [3, 3] pinhole intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels

Gradients flow to means, quats, scales, opacities and features (not to the camera or the
background). Conventions follow gsplat's pinhole path (EWA splatting with a 0.3 px low-pass,
optional ``antialiased`` opacity compensation, 16x16 tiles, front-to-back compositing with the
3DGS alpha rules); see ``docs/raster-contract.md``.

The two stages are also exposed separately (:func:`project_gaussians`,
:func:`rasterize_to_pixels`), as is :func:`spherical_harmonics`. Wrong shapes, dtypes, devices,
non-finite values or a degenerate camera raise ``ValueError`` naming the argument.

Backends (``backend=`` on :func:`rasterize` / :func:`rasterize_to_pixels`, default
:func:`set_default_backend`'s, initially ``"cpu"``): ``"cpu"`` composites with the
multithreaded Rust path; ``"wgpu"`` with the WGSL kernels on the adapter wgpu opens (a GPU, else
a CPU driver such as lavapipe; float32 only); ``"auto"`` takes wgpu when a discrete or
integrated GPU is present and the CPU path otherwise, and says once which it picked. The
projection and spherical harmonics run on the CPU path in every case.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from sync4d import _core
from sync4d.settings import BACKENDS

__all__ = [
    "BACKENDS",
    "Projection",
    "RasterOutput",
    "project_gaussians",
    "rasterize",
    "rasterize_to_pixels",
    "resolve_backend",
    "set_default_backend",
    "spherical_harmonics",
    "sh_features",
]

_default_backend = "cpu"
_auto_choice: str | None = None
_auto_message = ""


def resolve_backend(backend: str | None = None) -> str:
    """The concrete backend (``"cpu"`` or ``"wgpu"``) for `backend` (None: the default).
    ``"wgpu"`` opens the adapter now, so a missing driver is a ``RuntimeError`` here that
    says what to install; ``"auto"`` picks wgpu only for a discrete or integrated GPU, once
    per process, and says why in `auto_choice` (the command line prints it)."""
    global _auto_choice, _auto_message
    b = _default_backend if backend is None else backend
    if b not in BACKENDS:
        raise ValueError(f"backend: expected one of {', '.join(BACKENDS)}, got {b!r}")
    if b == "wgpu":
        _core.wgpu_adapter()
        return "wgpu"
    if b == "auto":
        if _auto_choice is None:
            gpus = [n for n, kind in _core.wgpu_adapters() if kind in ("discrete", "integrated")]
            if gpus:
                try:
                    msg = f"wgpu on {_core.wgpu_adapter()}"
                    _auto_choice = "wgpu"
                except RuntimeError as e:
                    msg = f"cpu ({gpus[0]} did not open: {e})"
                    _auto_choice = "cpu"
            else:
                msg = "cpu (no discrete or integrated GPU adapter)"
                _auto_choice = "cpu"
            _auto_message = f"backend auto -> {msg}"
        return _auto_choice
    return "cpu"


def auto_choice() -> str:
    """Why ``backend="auto"`` resolved as it did ("backend auto -> cpu (no discrete or
    integrated GPU adapter)"), "" before it was resolved."""
    return _auto_message


def set_default_backend(backend: str) -> str:
    """Make `backend` the default of every later render (the ``--backend`` flag of the
    commands); returns the concrete backend it resolves to."""
    global _default_backend
    concrete = resolve_backend(backend)
    _default_backend = concrete
    return concrete


_FLOATS = (torch.float32, torch.float64)


# --------------------------------------------------------------------------------------------
# Argument checks: one clear ValueError naming the argument.
# --------------------------------------------------------------------------------------------


def _check_tensor(name: str, t: object, shape: tuple, dtype: torch.dtype | None = None) -> Tensor:
    """Check that ``t`` is a CPU tensor of ``shape`` (-1 = any) and dtype; returns it."""
    if not isinstance(t, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.device.type != "cpu":
        raise ValueError(f"{name}: must be on the CPU, got device {t.device} (call .cpu())")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name}: expected dtype {dtype}, got {t.dtype}")
    if dtype is None and t.dtype not in _FLOATS:
        raise ValueError(f"{name}: expected float32 or float64, got {t.dtype}")
    ok = t.dim() == len(shape) and all(s in (-1, d) for s, d in zip(shape, t.shape, strict=False))
    if not ok:
        want = "[" + ", ".join("*" if s == -1 else str(s) for s in shape) + "]"
        raise ValueError(f"{name}: expected shape {want}, got {list(t.shape)}")
    return t


def _check_size(name: str, v: object) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or not 1 <= int(v) <= 16384:
        raise ValueError(f"{name}: expected an int in 1..16384, got {v!r}")
    return int(v)


def _check_finite(name: str, t: Tensor) -> None:
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name}: contains NaN or inf")


def thread_count(threads: int | None) -> int:
    """A kernel's `threads` argument checked: a positive int, or None (0: rayon's default)."""
    if threads is None:
        return 0
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads: expected a positive int or None, got {threads!r}")
    return threads


@dataclass(frozen=True)
class _Camera:
    viewmat: list[float]
    intrinsics: tuple[float, float, float, float]
    width: int
    height: int

    def kwargs(self) -> dict:
        """The projection bindings' camera arguments, by name."""
        fx, fy, cx, cy = self.intrinsics
        return {
            "viewmat": self.viewmat,
            "fx": fx,
            "fy": fy,
            "cx": cx,
            "cy": cy,
            "width": self.width,
            "height": self.height,
        }


def _camera(viewmat: Tensor, K: Tensor, width: int, height: int) -> _Camera:
    _check_tensor("viewmat", viewmat, (4, 4))
    _check_tensor("K", K, (3, 3))
    _check_finite("viewmat", viewmat)
    _check_finite("K", K)
    k = K.detach().double()
    if k[0, 1] != 0 or k[1, 0] != 0 or k[2].tolist() != [0.0, 0.0, 1.0]:
        raise ValueError(
            "K: expected a pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), "
            f"got {k.tolist()}"
        )
    w, h = _check_size("width", width), _check_size("height", height)
    intr = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    return _Camera(viewmat.detach().double().reshape(-1).tolist(), intr, w, h)


def _np(t: Tensor) -> np.ndarray:
    """Zero-copy NumPy view of a (contiguous) tensor."""
    return t.detach().contiguous().numpy()


def grad_or_zeros(g: Tensor | None, like: Tensor) -> np.ndarray:
    """An output's gradient as NumPy in `like`'s dtype; zeros when autograd passed None."""
    return _np(torch.zeros_like(like) if g is None else g.to(like.dtype))


# --------------------------------------------------------------------------------------------
# Stage 1: projection.
# --------------------------------------------------------------------------------------------


@dataclass
class Projection:
    """Screen-space splats: ``means2d`` [N, 2] px, ``conics`` [N, 3] (inverse 2D covariance
    xx, xy, yy), ``depths`` [N] camera z, ``opacities`` [N] after antialiasing compensation,
    ``radii`` [N, 2] int32 px (0 = culled)."""

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    opacities: Tensor
    radii: Tensor


class _ProjectFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cam: _Camera, settings, threads):  # type: ignore[override]
        fn = _core.project_forward
        m2, co, de, op, ra, _visible = fn(
            _np(means), _np(quats), _np(scales), _np(opacities),
            **cam.kwargs(), settings=settings, threads=threads,
        )  # fmt: skip
        n = means.shape[0]
        ctx.save_for_backward(means, quats, scales, opacities)
        ctx.cam, ctx.settings, ctx.threads = cam, settings, threads
        radii = torch.from_numpy(ra).reshape(n, 2)
        ctx.mark_non_differentiable(radii)
        return (
            torch.from_numpy(m2).reshape(n, 2),
            torch.from_numpy(co).reshape(n, 3),
            torch.from_numpy(de),
            torch.from_numpy(op),
            radii,
        )

    @staticmethod
    def backward(ctx, v_m2, v_co, v_de, v_op, _v_radii):  # type: ignore[override]
        means, quats, scales, opacities = ctx.saved_tensors
        n = means.shape[0]
        like2 = means.new_empty(n, 2)
        like3 = means.new_empty(n, 3)
        like1 = means.new_empty(n)
        cam = ctx.cam
        fn = _core.project_backward
        gm, gq, gs, go = fn(
            _np(means), _np(quats), _np(scales), _np(opacities),
            **cam.kwargs(), settings=ctx.settings,
            grad_means2d=grad_or_zeros(v_m2, like2), grad_conics=grad_or_zeros(v_co, like3),
            grad_depths=grad_or_zeros(v_de, like1), grad_opacities=grad_or_zeros(v_op, like1),
            threads=ctx.threads,
        )  # fmt: skip
        return (
            torch.from_numpy(gm).reshape(n, 3),
            torch.from_numpy(gq).reshape(n, 4),
            torch.from_numpy(gs).reshape(n, 3),
            torch.from_numpy(go),
            None,
            None,
            None,
        )


def _check_gaussians(means, quats, scales, opacities) -> torch.dtype:
    _check_tensor("means", means, (-1, 3))
    dtype = means.dtype
    n = means.shape[0]
    _check_tensor("quats", quats, (n, 4), dtype)
    _check_tensor("scales", scales, (n, 3), dtype)
    _check_tensor("opacities", opacities, (n,), dtype)
    return dtype


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    near: float = _core.DEFAULT_NEAR,
    far: float = _core.DEFAULT_FAR,
    eps2d: float = _core.DEFAULT_EPS2D,
    antialiased: bool = False,
    threads: int | None = None,
) -> Projection:
    """Project 3D Gaussians ([N, 3] means, [N, 4] wxyz quats, [N, 3] scales, [N] opacities)
    through a pinhole camera into screen-space splats (differentiable, see :class:`Projection`)."""
    _check_gaussians(means, quats, scales, opacities)
    cam = _camera(viewmat, K, width, height)
    settings = _core.ProjectSettings(
        near=float(near), far=float(far), eps2d=float(eps2d), antialiased=bool(antialiased)
    )
    out = _ProjectFn.apply(means, quats, scales, opacities, cam, settings, thread_count(threads))
    return Projection(*out)


# --------------------------------------------------------------------------------------------
# Stage 2: tiling and compositing.
# --------------------------------------------------------------------------------------------


class _ContextPool:
    """Reusable Rust raster contexts of one backend (their buffers stay warm across
    iterations)."""

    def __init__(self, make) -> None:
        self._make = make
        self._free: list = []

    def get(self):
        return self._free.pop() if self._free else self._make()

    def put(self, c) -> None:
        if len(self._free) < 8:
            self._free.append(c)


_POOLS = {"cpu": _ContextPool(_core.RasterContext), "wgpu": _ContextPool(_core.WgpuContext)}


class _Lease:
    """Owns one context for the lifetime of an autograd node and returns it to the pool when
    the node is freed, so a retained graph can run its backward again safely."""

    __slots__ = ("backend", "context")

    def __init__(self, backend: str) -> None:
        self.backend = backend
        self.context = _POOLS[backend].get()

    def __del__(self) -> None:
        try:
            _POOLS[self.backend].put(self.context)
        except Exception:  # interpreter shutdown: nothing to return to
            pass


def _splat_args(means2d, conics, depths, opacities, radii, features, background) -> dict:
    """The compositing bindings' splat arguments, by name (zero-copy NumPy views)."""
    return {
        "means2d": _np(means2d),
        "conics": _np(conics),
        "depths": _np(depths),
        "opacities": _np(opacities),
        "radii": _np(radii),
        "features": _np(features),
        "channels": features.shape[1],
        "background": _np(background),
    }


class _RasterizeFn(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx, means2d, conics, depths, opacities, features, radii, background, opts, info
    ):
        settings, threads, backend = opts
        width, height = settings.width, settings.height
        n, ch = features.shape
        lease = _Lease(backend)
        f, a, d, counters = lease.context.forward(
            **_splat_args(means2d, conics, depths, opacities, radii, features, background),
            settings=settings, threads=threads,
        )  # fmt: skip
        if any(ctx.needs_input_grad[:5]):
            ctx.lease = lease
        info.update(counters)
        ctx.save_for_backward(means2d, conics, depths, opacities, features, radii, background)
        ctx.opts = opts
        return (
            torch.from_numpy(f).reshape(height, width, ch),
            torch.from_numpy(a).reshape(height, width, 1),
            torch.from_numpy(d).reshape(height, width, 1),
        )

    @staticmethod
    def backward(ctx, v_f, v_a, v_d):  # type: ignore[override]
        means2d, conics, depths, opacities, features, radii, background = ctx.saved_tensors
        settings, threads, _backend = ctx.opts
        width, height = settings.width, settings.height
        n, ch = features.shape
        like_f = features.new_empty(height, width, ch)
        like_1 = features.new_empty(height, width, 1)
        g2, gc, gd, go, gf = ctx.lease.context.backward(
            **_splat_args(means2d, conics, depths, opacities, radii, features, background),
            settings=settings,
            grad_features=grad_or_zeros(v_f, like_f),
            grad_alpha=grad_or_zeros(v_a, like_1),
            grad_depth=grad_or_zeros(v_d, like_1),
            threads=threads,
        )
        return (
            torch.from_numpy(g2).reshape(n, 2),
            torch.from_numpy(gc).reshape(n, 3),
            torch.from_numpy(gd),
            torch.from_numpy(go),
            torch.from_numpy(gf).reshape(n, ch),
            None,
            None,
            None,
            None,
        )


def rasterize_to_pixels(
    means2d: Tensor,
    conics: Tensor,
    depths: Tensor,
    opacities: Tensor,
    radii: Tensor,
    features: Tensor,
    width: int,
    height: int,
    *,
    background: Tensor | None = None,
    alpha_max: float = _core.DEFAULT_ALPHA_MAX,
    threads: int | None = None,
    counters: dict | None = None,
    backend: str | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Composite screen-space splats front to back. Returns ``(features [H, W, C],
    alpha [H, W, 1], depth_accum [H, W, 1])`` where ``depth_accum = sum_i z_i alpha_i T_i``.
    Differentiable w.r.t. means2d, conics, depths, opacities and features. Work counters
    (visible, intersections, evaluated, blended) are written into ``counters`` if given.
    `backend`: ``"cpu"``, ``"wgpu"`` or ``"auto"`` (see the module notes)."""
    _check_tensor("features", features, (-1, -1))
    dtype = features.dtype
    n, ch = features.shape
    if ch < 1:
        raise ValueError(f"features: need at least one channel, got shape {list(features.shape)}")
    _check_tensor("means2d", means2d, (n, 2), dtype)
    _check_tensor("conics", conics, (n, 3), dtype)
    _check_tensor("depths", depths, (n,), dtype)
    _check_tensor("opacities", opacities, (n,), dtype)
    _check_tensor("radii", radii, (n, 2), torch.int32)
    w, h = _check_size("width", width), _check_size("height", height)
    if background is None:
        background = features.new_zeros(ch)
    else:
        _check_tensor("background", background, (ch,), dtype)
    background = background.detach()
    am = float(alpha_max)
    if not (_core.ALPHA_MIN <= am < 1.0):
        raise ValueError(f"alpha_max: must lie in [1/255, 1), got {alpha_max}")
    info: dict = {} if counters is None else counters
    be = resolve_backend(backend)
    if be == "wgpu" and dtype != torch.float32:
        raise ValueError(
            "backend 'wgpu' composites float32 only; use backend='cpu' for float64 "
            "(gradient checks)"
        )
    settings = _core.CompositeSettings(width=w, height=h, alpha_max=am)
    opts = (settings, thread_count(threads), be)
    return _RasterizeFn.apply(
        means2d, conics, depths, opacities, features, radii, background, opts, info
    )


# --------------------------------------------------------------------------------------------
# The one-call renderer.
# --------------------------------------------------------------------------------------------


@dataclass
class RasterOutput:
    """A rendered view: ``features`` [H, W, C], ``alpha`` [H, W, 1], ``depth`` [H, W, 1]
    (expected depth), the projection (``means2d`` [N, 2] — call ``retain_grad()`` on it for
    densification statistics — and ``radii`` [N, 2]) and work ``counters``."""

    features: Tensor
    alpha: Tensor
    depth: Tensor
    means2d: Tensor
    radii: Tensor
    counters: dict = field(default_factory=dict)


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    background: Tensor | None = None,
    near: float = _core.DEFAULT_NEAR,
    far: float = _core.DEFAULT_FAR,
    eps2d: float = _core.DEFAULT_EPS2D,
    antialiased: bool = False,
    alpha_max: float = _core.DEFAULT_ALPHA_MAX,
    threads: int | None = None,
    backend: str | None = None,
) -> RasterOutput:
    """Render Gaussians to a ``height`` x ``width`` image (see the module docstring)."""
    dtype = _check_gaussians(means, quats, scales, opacities)
    _check_tensor("features", features, (means.shape[0], -1), dtype)
    proj = project_gaussians(
        means, quats, scales, opacities, viewmat, K, width, height,
        near=near, far=far, eps2d=eps2d, antialiased=antialiased, threads=threads,
    )  # fmt: skip
    counters: dict = {}
    img, alpha, depth_accum = rasterize_to_pixels(
        proj.means2d, proj.conics, proj.depths, proj.opacities, proj.radii, features,
        width, height, background=background, alpha_max=alpha_max, threads=threads,
        counters=counters, backend=backend,
    )  # fmt: skip
    depth = torch.where(alpha > 0, depth_accum / alpha.clamp_min(1e-10), torch.zeros_like(alpha))
    return RasterOutput(img, alpha, depth, proj.means2d, proj.radii, counters)


# --------------------------------------------------------------------------------------------
# Spherical harmonics.
# --------------------------------------------------------------------------------------------


class _ShFn(torch.autograd.Function):
    @staticmethod
    def forward(ctx, degree, dirs, coeffs, threads):  # type: ignore[override]
        n, k, c = coeffs.shape
        fn = _core.sh_forward
        out = fn(degree, _np(dirs), _np(coeffs), bases=k, channels=c, threads=threads)
        ctx.save_for_backward(dirs, coeffs)
        ctx.degree, ctx.threads = degree, threads
        return torch.from_numpy(out).reshape(n, c)

    @staticmethod
    def backward(ctx, v_out):  # type: ignore[override]
        dirs, coeffs = ctx.saved_tensors
        n, k, c = coeffs.shape
        fn = _core.sh_backward
        vd, vc = fn(
            ctx.degree, _np(dirs), _np(coeffs), bases=k, channels=c,
            grad_out=_np(v_out.to(dirs.dtype)), threads=ctx.threads,
        )  # fmt: skip
        return None, torch.from_numpy(vd).reshape(n, 3), torch.from_numpy(vc).reshape(n, k, c), None


def spherical_harmonics(
    degree: int, dirs: Tensor, coeffs: Tensor, *, threads: int | None = None
) -> Tensor:
    """Evaluate real SH of ``degree`` (0-3) at view directions ``dirs`` [N, 3] (normalised
    inside) with ``coeffs`` [N, K, C], K >= (degree + 1)^2; returns [N, C]. Differentiable
    w.r.t. both inputs (the view-direction term included). No +0.5 offset."""
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise ValueError(f"degree: expected an int in 0..3, got {degree!r}")
    _check_tensor("dirs", dirs, (-1, 3))
    _check_tensor("coeffs", coeffs, (dirs.shape[0], -1, -1), dirs.dtype)
    if coeffs.shape[1] < (degree + 1) ** 2:
        raise ValueError(
            f"coeffs: degree {degree} needs >= {(degree + 1) ** 2} coefficients per channel, "
            f"got shape {list(coeffs.shape)}"
        )
    return _ShFn.apply(degree, dirs, coeffs, thread_count(threads))


def sh_features(
    means: Tensor, sh_coeffs: Tensor, viewmat: Tensor, degree: int, *, threads: int | None = None
) -> Tensor:
    """View-dependent colours as in 3DGS: SH of the direction camera centre → mean, plus 0.5,
    clamped at 0. ``means`` [N, 3], ``sh_coeffs`` [N, K, C]; returns [N, C]."""
    _check_tensor("viewmat", viewmat, (4, 4))
    rot = viewmat[:3, :3].to(means.dtype)
    campos = -rot.T @ viewmat[:3, 3].to(means.dtype)
    dirs = means - campos
    return torch.clamp_min(spherical_harmonics(degree, dirs, sh_coeffs, threads=threads) + 0.5, 0.0)


def fov_to_focal(fov_radians: float, pixels: int) -> float:
    """Focal length in pixels for a field of view across ``pixels``."""
    return 0.5 * pixels / math.tan(0.5 * fov_radians)
