"""Phase 2 shared object motion M_phi (paper Sec. 3.3, Eq. 5, Appendix A "Object Motion Model").

One interface, three parameterisations of a transform per object k and time t:

* ``se3`` (default): a per-frame table of rotation vectors w [K, T, 3] and translations
  t [K, T, 3]; x~ = R(w) x0 + t.
* ``affine``: a per-frame table of affine deltas dA [K, T, 3, 3] and offsets b [K, T, 3];
  x~ = (I + dA) x0 + b.
* ``mlp``: a learned 16-d embedding per object concatenated with gamma(t), Lin 64 -> ReLU ->
  Lin 64 -> ReLU -> Lin (6 for SE(3), 12 for affine), zero-initialised output.

Tables hold one entry per stored frame time (the sorted distinct training times); a time
between two stored frames interpolates (quaternion slerp of the rotation, linear elsewhere), so
rendering and export work at any t in [0, 1]. Every transform maps canonical positions x0 to
the object-predicted positions x~_i(t) that only the Phase 2 losses see: rendering always uses
D_theta's x_i(t).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from sync4d.geometry import (
    axis_angle_to_quat,
    fit_affine,
    kabsch,
    matrix_to_rotvec,
    quat_slerp,
    quat_to_matrix,
    robust_fit,
    rotvec_to_matrix,
)
from sync4d.phase1.deform import time_encoding
from sync4d.settings import choice, ranged

__all__ = [
    "MOTION_KINDS",
    "MotionConfig",
    "ObjectMotion",
    "make_motion",
    "still_objects",
]

#: The M_phi parameterisations `make_motion` knows.
MOTION_KINDS = ("se3", "affine", "mlp")


@dataclass(frozen=True)
class MotionConfig:
    """M_phi's parameterisation and optimisation (Appendix A: per-frame SE(3), init sigma 1e-4,
    learning rate cosine-annealed 1e-3 -> 1e-5).

    Settings that must go together (checked when the config is read, `combination_problem`):
    `init = "fit"` needs a kind with a closed-form start; `refine_steps` > 0 needs `init =
    "fit"` and `kind = "se3"`; the refinement's options (`refine_texture_rounds`,
    `refine_retrack_steps`, `refine_restart_jump`) need `refine_steps` > 0; and
    `refine_lr_final` is at most `refine_lr` (the rate only anneals down)."""

    #: M_phi's parameterisation: "se3" (per-frame table of rotations and translations), "affine"
    #: (per-frame affine table) or "mlp".
    kind: str = choice("se3", MOTION_KINDS)
    #: "identity" (the paper: near-identity start, sigma `init_std`) or "fit": start the tables
    #: at the closed-form minimiser of the residual energy given Phase 1's D_theta (weighted
    #: Kabsch per object and frame for SE(3), least squares for affine). A per-frame table
    #: entry is only updated when its frame is drawn, so from the identity it needs many
    #: thousands of iterations to reach large rotations; "fit" suits short CPU schedules.
    init: str = choice("identity", ("identity", "fit"))
    #: Photometric refinement of the fitted SE(3) table (init "fit" only; 0 skips it): at every
    #: stored frame, in time order and starting from the previous frame's result, this many Adam
    #: steps (4x at the first frame) on each moving object's rotation and translation, rendering
    #: the object's Gaussians of the first frame moved rigidly against that frame's views. The
    #: closed-form fit follows D_theta's point correspondences, and D_theta may morph a turning
    #: shape instead of rotating its Gaussians (measured on the embedded scene: 9 of the box's 45
    #: degrees); the images pin the rotation down. Not in the paper.
    refine_steps: int = ranged(0, 0, scales=1)
    #: Adam learning rate of the refinement (radians and metres per step) at each frame's first
    #: step; it is cosine-annealed to `refine_lr_final` over the frame's steps.
    refine_lr: float = ranged(0.01, 0.0, lo_open=True)
    #: Learning rate at each frame's last refinement step (at most `refine_lr`, checked when
    #: the config is read). Equal to
    #: `refine_lr` is a constant rate, as before 2026-12-01: Adam's steps then stay ~0.01 rad
    #: (0.6 degrees) to the end and the result is wherever the last one-view steps left it
    #: (box 2.04 against 1.28 degrees annealed, docs/results/phase2-robustness.md).
    refine_lr_final: float = ranged(0.0005, 0.0, lo_open=True)
    #: Training views rendered per refinement step (their losses summed); 0: all of the frame's
    #: views. 1 draws one view per step in turn.
    refine_views: int = ranged(1, 0)
    #: Rounds of texture fit and re-tracking after the first tracking pass: the template's
    #: base colours (a copy of the moving Gaussians' SH DC) are fitted to every training view
    #: with the poses fixed, then every frame is tracked again from its pose. D_theta's colours
    #: are averaged over a morph, so the rigidly turned template is blurred where the object
    #: turned most and pulls those poses toward the blur (embedded scene, phase1.seed 42: ball
    #: 2.00 -> 0.85 degrees with one round, docs/results/phase2-robustness.md). Not in the paper.
    #: Like `refine_retrack_steps` and `refine_restart_jump`, it needs `refine_steps` > 0.
    refine_texture_rounds: int = ranged(0, 0, scales=0)
    #: Adam learning rate of the texture fit (SH DC units per step).
    refine_colour_lr: float = ranged(0.005, 0.0, lo_open=True)
    #: Passes over every training view in each texture fit (one view per step).
    refine_colour_epochs: int = ranged(2, 0)
    #: Adam steps per frame when re-tracking after a texture fit; 0: `refine_steps`.
    refine_retrack_steps: int = ranged(0, 0, scales=1)
    #: Adam learning rate at the first re-tracking step of each frame (annealed to
    #: `refine_lr_final` like the first pass); 0: `refine_lr`.
    refine_retrack_lr: float = ranged(0.0, 0.0)
    #: Restart a frame whose tracked pose scores a mean loss over its views more than this
    #: fraction above the previous frame's (0: never): each moving object is tracked again from
    #: the previous frame's rotation turned by each of `refine_restart_angles` about the axis of
    #: its last frame-to-frame turn, and the lowest-loss pose is kept. Not in the paper; off by
    #: default until the study has measured it (a flip into a neighbouring minimum of the
    #: ball's texture, docs/results/phase2-robustness.md section 5).
    refine_restart_jump: float = ranged(0.0, 0.0)
    #: Degrees about that axis the restarts start from.
    refine_restart_angles: tuple[float, ...] = ranged(
        (-30.0, -15.0, 15.0, 30.0, 45.0), -180.0, 180.0
    )
    #: For ``mlp``: whether it outputs an affine transform (12) instead of SE(3) (6).
    mlp_affine: bool = False
    #: Standard deviation of the identity start's random perturbation (Appendix A: 1e-4).
    init_std: float = ranged(1e-4, 0.0)
    #: Adam rate of M_phi at the start of Phase 2 (cosine-annealed to `lr_final`).
    lr: float = ranged(1e-3, 0.0, lo_open=True)
    #: M_phi's Adam rate at the end of Phase 2.
    lr_final: float = ranged(1e-5, 0.0)
    #: kind "mlp": dimension of each object's learned embedding.
    mlp_embed_dim: int = ranged(16, 1)
    #: kind "mlp": width of its two hidden layers.
    mlp_hidden: int = ranged(64, 1)
    #: kind "mlp": frequencies of its time encoding.
    mlp_bands: int = ranged(6, 0, 20)

    def combination_problem(self) -> str | None:
        """What is wrong with these settings together (each is within its own range), or
        None; `sync4d.config.validate` calls it once all overrides are applied."""
        if self.init == "fit" and not MOTION_CLASSES[self.kind].fits_closed_form:
            return (f"init=fit: the {self.kind} M_phi has no closed-form start; use "
                    "phase2.motion.init=identity")  # fmt: skip
        if self.refine_steps > 0 and (self.init != "fit" or self.kind != "se3"):
            return ("refine_steps refines the fitted SE(3) table: it needs "
                    f"phase2.motion.init=fit and kind=se3 (got init={self.init!r}, "
                    f"kind={self.kind!r})")  # fmt: skip
        if self.refine_steps == 0:
            for key in ("refine_texture_rounds", "refine_retrack_steps", "refine_restart_jump"):
                if getattr(self, key) > 0:
                    return (f"{key} = {getattr(self, key)} acts only in the refinement, which "
                            "refine_steps = 0 turns off; set phase2.motion.refine_steps > 0 "
                            f"or phase2.motion.{key} = 0")  # fmt: skip
        elif self.refine_lr_final > self.refine_lr:
            return (f"refine_lr_final = {self.refine_lr_final} is above refine_lr = "
                    f"{self.refine_lr}, and the refinement's rate only anneals down; lower "
                    "phase2.motion.refine_lr_final to at most phase2.motion.refine_lr")
        return None


class ObjectMotion(nn.Module, ABC):
    """M_phi for K objects over the stored frame times `times` [T] (sorted, in [0, 1]).

    Subclasses provide `params_at(j)` (the raw per-object parameters at stored frame j, [K, P],
    which the smoothness and identity losses act on; zero is the identity) and `linear_at(t)`:
    the transform at any time as (A [K, 3, 3], b [K, 3]) with x~ = A x0 + b.

    Objects flagged in the buffer `frozen` [K] (bool; `hold`) are held at a constant transform
    (buffers `held_linear` [K, 3, 3] and `held_offset` [K, 3]; the identity by default): every
    transform and loss sees it there, so no gradient reaches their parameters (Phase 2's
    still objects, `still_objects`, `Phase2Config.freeze_static`).
    """

    #: Whether the transform is rigid (SE(3)); the affine ones are not.
    rigid: bool = True
    #: Parameters with one row per object (first dimension K), whose held rows' Adam moments
    #: the trainer clears when it holds them.
    row_params: tuple[str, ...] = ()

    def __init__(self, num_objects: int, times: np.ndarray | list[float]) -> None:
        super().__init__()
        times = np.asarray(times, dtype=np.float64)
        if num_objects < 1:
            raise ValueError(f"M_phi needs at least one object, got {num_objects}")
        if times.ndim != 1 or len(times) < 1 or np.any(np.diff(times) <= 0):
            raise ValueError("M_phi frame times must be a non-empty strictly increasing list")
        self.num_objects = num_objects
        self.register_buffer("times", torch.as_tensor(times, dtype=torch.float64))
        self.register_buffer("frozen", torch.zeros(num_objects, dtype=torch.bool))
        self.register_buffer("held_linear", torch.eye(3).repeat(num_objects, 1, 1))
        self.register_buffer("held_offset", torch.zeros(num_objects, 3))

    @property
    def num_frames(self) -> int:
        """T, the number of stored frame times."""
        return int(self.times.shape[0])

    def frame_index(self, t: float) -> int:
        """Index of the stored frame time nearest to `t`."""
        return int(torch.argmin((self.times - float(t)).abs()))

    def bracket(self, t: float) -> tuple[int, int, float]:
        """Stored frames (j0, j1) around `t` and the interpolation weight of j1 (t is clamped to
        the stored range)."""
        times = self.times
        t = min(max(float(t), float(times[0])), float(times[-1]))
        j1 = int(torch.searchsorted(times, torch.tensor([t], dtype=times.dtype))[0])
        j1 = min(max(j1, 0), self.num_frames - 1)
        if float(times[j1]) == t or j1 == 0:
            return j1, j1, 0.0
        j0 = j1 - 1
        alpha = (t - float(times[j0])) / float(times[j1] - times[j0])
        return j0, j1, alpha

    @abstractmethod
    def params_at(self, j: int) -> Tensor:
        """Raw parameters [K, P] at stored frame `j`."""

    @abstractmethod
    def linear_at(self, t: float) -> tuple[Tensor, Tensor]:
        """(A [K, 3, 3], b [K, 3]) at time `t`: x~ = A x0 + b."""

    def transform_at(self, t: float) -> tuple[Tensor, Tensor]:
        """`linear_at(t)` with the held objects' rows replaced by their constant transform."""
        a, b = self.linear_at(t)
        if bool(self.frozen.any()):
            f = self.frozen
            a = torch.where(f[:, None, None], self.held_linear.to(a.dtype), a)
            b = torch.where(f[:, None], self.held_offset.to(b.dtype), b)
        return a, b

    def rows_at(self, j: int) -> Tensor:
        """`params_at(j)` [K, P] with the held objects' rows zero: constant in time and
        trained by nothing, they are left out of the smoothness and identity losses."""
        p = self.params_at(j)
        if bool(self.frozen.any()):
            p = torch.where(self.frozen[:, None], torch.zeros((), dtype=p.dtype), p)
        return p

    @torch.no_grad()
    def hold(
        self, frozen: Tensor, linear: Tensor | None = None, offset: Tensor | None = None
    ) -> None:
        """Hold the objects flagged in `frozen` [K] (bool) at the constant transform
        x~ = linear[k] x0 + offset[k] (`linear` [K, 3, 3], `offset` [K, 3]; default the
        identity) from now on, and release the others (their parameters keep their values).
        The tables also store it in the held objects' rows at every frame."""
        k = self.num_objects
        self.frozen.copy_(torch.as_tensor(frozen, dtype=torch.bool))
        self.held_linear.copy_(torch.eye(3).repeat(k, 1, 1) if linear is None else linear)
        self.held_offset.copy_(torch.zeros(k, 3) if offset is None else offset)
        self._store_held()

    def _store_held(self) -> None:
        """Write the held transforms into the held objects' parameter rows (the tables)."""

    def forward(self, x0: Tensor, labels: Tensor, t: float) -> Tensor:
        """Object-predicted positions x~ [N, 3] (Eq. 5) of canonical means `x0` [N, 3] whose
        objects are `labels` [N] (long, in [0, K)) at time `t`."""
        a, b = self.transform_at(t)
        a, b = a.to(x0.dtype), b.to(x0.dtype)
        return (a[labels] @ x0.unsqueeze(-1)).squeeze(-1) + b[labels]

    def smoothness(self, j: int) -> Tensor:
        """Eq. 12: (1/K) sum_k ||p_k[j] - p_k[j-1]||^2 between stored frame `j` and the one
        before it (0 at the first frame)."""
        if j <= 0:
            return self.params_at(0).sum() * 0.0
        d = self.rows_at(j) - self.rows_at(j - 1)
        return (d * d).sum() / self.num_objects

    def identity_prior(self, j: int, static: Tensor) -> Tensor:
        """Mean over the objects flagged in `static` [K] (bool) of ||p_k[j]||^2: pulls static
        objects' transforms to the identity (0 when none is static)."""
        p = self.rows_at(j)[static]
        if p.shape[0] == 0:
            return p.sum() * 0.0
        return (p * p).sum() / p.shape[0]

    #: Whether `fit_to` exists (the tables); the MLP has no closed-form initialisation.
    fits_closed_form: bool = True

    def fit_to(self, x0: np.ndarray, positions: list[np.ndarray], labels: np.ndarray) -> None:
        """Set the transforms to the closed-form fit of canonical `x0` [N, 3] onto
        `positions[j]` [N, 3] (D_theta at stored frame j) per object `labels` [N] (held
        objects keep their constant transform)."""
        raise ValueError(
            f"{type(self).__name__} has no closed-form initialisation: use "
            "phase2.motion.init=identity with phase2.motion.kind=mlp"
        )

    def load_state(self, tensors: dict[str, Tensor]) -> None:
        """Load the ``motion.*`` entries of a checkpoint's tensors (the stored frame times stay
        this module's own); ValueError when they do not fit its parameterisation."""
        state = {k.removeprefix("motion."): v for k, v in tensors.items()
                 if k.startswith("motion.")}  # fmt: skip
        state["times"] = self.times
        # Checkpoints from before objects were held have no flags: none is held.
        k = self.num_objects
        state["frozen"] = state.get("frozen", torch.zeros(k)).to(torch.bool)
        state.setdefault("held_linear", torch.eye(3).repeat(k, 1, 1))
        state.setdefault("held_offset", torch.zeros(k, 3))
        try:
            self.load_state_dict(state)
        except RuntimeError as e:
            raise ValueError(f"inconsistent M_phi state ({e})") from None

    @torch.no_grad()
    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """(A [K, T, 3, 3], b [K, T, 3]) float64 at every stored frame, for export (held
        objects at their constant transform)."""
        mats, offs = [], []
        for j in range(self.num_frames):
            a, b = self.transform_at(float(self.times[j]))
            mats.append(a.double().numpy())
            offs.append(b.double().numpy())
        return np.stack(mats, 1), np.stack(offs, 1)


class SE3Table(ObjectMotion):
    """Per-frame SE(3) table: rotation vectors w [K, T, 3] and translations t [K, T, 3]."""

    row_params = ("rotvecs", "translations")

    def __init__(self, num_objects: int, times, init_std: float = 1e-4, generator=None) -> None:
        super().__init__(num_objects, times)
        shape = (num_objects, self.num_frames, 3)
        self.rotvecs = nn.Parameter(torch.randn(shape, generator=generator) * init_std)
        self.translations = nn.Parameter(torch.randn(shape, generator=generator) * init_std)

    def params_at(self, j: int) -> Tensor:
        return torch.cat([self.rotvecs[:, j], self.translations[:, j]], dim=-1)

    @torch.no_grad()
    def fit_to(self, x0: np.ndarray, positions: list[np.ndarray], labels: np.ndarray) -> None:
        for k in range(self.num_objects):
            sel = labels == k
            if sel.sum() < 3 or self.frozen[k]:
                continue
            fits = robust_fit(kabsch, x0[sel], [pos[sel] for pos in positions])
            for j, (r, t) in enumerate(fits):
                self.rotvecs[k, j] = torch.as_tensor(matrix_to_rotvec(r))
                self.translations[k, j] = torch.as_tensor(t)

    @torch.no_grad()
    def _store_held(self) -> None:
        for k in torch.nonzero(self.frozen).flatten().tolist():
            w = matrix_to_rotvec(self.held_linear[k].double().numpy())
            self.rotvecs[k] = torch.as_tensor(w, dtype=self.rotvecs.dtype)
            self.translations[k] = self.held_offset[k].to(self.translations.dtype)

    def linear_at(self, t: float) -> tuple[Tensor, Tensor]:
        j0, j1, alpha = self.bracket(t)
        if j0 == j1:
            return rotvec_to_matrix(self.rotvecs[:, j0]), self.translations[:, j0]
        q = quat_slerp(
            axis_angle_to_quat(self.rotvecs[:, j0]), axis_angle_to_quat(self.rotvecs[:, j1]), alpha
        )
        b = (1 - alpha) * self.translations[:, j0] + alpha * self.translations[:, j1]
        return quat_to_matrix(q), b


class AffineTable(ObjectMotion):
    """Per-frame affine table: deltas dA [K, T, 3, 3] and offsets b [K, T, 3]."""

    rigid = False
    row_params = ("deltas", "offsets")

    def __init__(self, num_objects: int, times, init_std: float = 1e-4, generator=None) -> None:
        super().__init__(num_objects, times)
        k, n = num_objects, self.num_frames
        self.deltas = nn.Parameter(torch.randn((k, n, 3, 3), generator=generator) * init_std)
        self.offsets = nn.Parameter(torch.randn((k, n, 3), generator=generator) * init_std)

    def params_at(self, j: int) -> Tensor:
        return torch.cat([self.deltas[:, j].flatten(1), self.offsets[:, j]], dim=-1)

    @torch.no_grad()
    def fit_to(self, x0: np.ndarray, positions: list[np.ndarray], labels: np.ndarray) -> None:
        for k in range(self.num_objects):
            sel = labels == k
            if sel.sum() < 4 or self.frozen[k]:
                continue
            fits = robust_fit(fit_affine, x0[sel], [pos[sel] for pos in positions])
            for j, (a, b) in enumerate(fits):
                self.deltas[k, j] = torch.as_tensor(a - np.eye(3))
                self.offsets[k, j] = torch.as_tensor(b)

    @torch.no_grad()
    def _store_held(self) -> None:
        f = self.frozen
        self.deltas[f] = (self.held_linear[f] - torch.eye(3)).unsqueeze(1).to(self.deltas.dtype)
        self.offsets[f] = self.held_offset[f].unsqueeze(1).to(self.offsets.dtype)

    def linear_at(self, t: float) -> tuple[Tensor, Tensor]:
        j0, j1, alpha = self.bracket(t)
        d = (1 - alpha) * self.deltas[:, j0] + alpha * self.deltas[:, j1]
        b = (1 - alpha) * self.offsets[:, j0] + alpha * self.offsets[:, j1]
        return torch.eye(3, dtype=d.dtype) + d, b


class MotionMLP(ObjectMotion):
    """The MLP variant: [e_k (16); gamma(t)] -> 64 -> 64 -> 6 (rotation vector, translation)
    or 12 (affine delta, offset), zero-initialised output, so it starts at the identity."""

    fits_closed_form = False
    row_params = ("embeddings",)

    def __init__(
        self, num_objects: int, times, config: MotionConfig | None = None, generator=None
    ) -> None:
        super().__init__(num_objects, times)
        c = config or MotionConfig(kind="mlp")
        self.bands = c.mlp_bands
        self.rigid = not c.mlp_affine
        out = 6 if self.rigid else 12
        self.embeddings = nn.Parameter(
            torch.randn((num_objects, c.mlp_embed_dim), generator=generator) * 0.1
        )
        self.net = nn.Sequential(
            nn.Linear(c.mlp_embed_dim + 1 + 2 * c.mlp_bands, c.mlp_hidden),
            nn.ReLU(),
            nn.Linear(c.mlp_hidden, c.mlp_hidden),
            nn.ReLU(),
            nn.Linear(c.mlp_hidden, out),
        )
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def _out(self, t: float) -> Tensor:
        k = self.num_objects
        gamma = time_encoding(torch.full((k,), float(t), dtype=torch.float32), self.bands)
        return self.net(torch.cat([self.embeddings, gamma], dim=-1))

    def params_at(self, j: int) -> Tensor:
        return self._out(float(self.times[j]))

    def linear_at(self, t: float) -> tuple[Tensor, Tensor]:
        o = self._out(t)
        if self.rigid:
            return rotvec_to_matrix(o[:, :3]), o[:, 3:]
        return torch.eye(3) + o[:, :9].reshape(-1, 3, 3), o[:, 9:]


#: M_phi's class for each `MotionConfig.kind`.
MOTION_CLASSES: dict[str, type[ObjectMotion]] = {
    "se3": SE3Table, "affine": AffineTable, "mlp": MotionMLP,
}  # fmt: skip


def make_motion(
    config: MotionConfig, num_objects: int, times, seed: int = 42
) -> ObjectMotion:
    """The M_phi of `config.kind` for `num_objects` objects over stored frame `times`."""
    g = torch.Generator().manual_seed(seed)
    if config.kind == "se3":
        return SE3Table(num_objects, times, config.init_std, g)
    if config.kind == "affine":
        return AffineTable(num_objects, times, config.init_std, g)
    if config.kind == "mlp":
        return MotionMLP(num_objects, times, config, g)
    raise ValueError(f"unknown M_phi kind {config.kind!r}: expected one of {MOTION_KINDS}")


def still_objects(
    x0: np.ndarray,
    positions: Iterable[np.ndarray],
    labels: np.ndarray,
    num_objects: int,
    max_spread: float,
    max_angle: float,
    rigid: bool = True,
    all_or_none: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which objects do not move, and the constant transform that holds each.

    `positions`: D_theta's positions [N, 3] at the stored frames (iterated twice: a list, or a
    re-iterable that evaluates them each time); `x0` [N, 3] the canonical positions; `labels`
    [N] each Gaussian's object in [0, K). Object k is still when each of its Gaussians stays
    within `max_spread` (world units) of its mean position over the frames, and the
    closed-form rotation (Kabsch, 3 or more Gaussians) of its Gaussians from their mean
    positions onto each frame's turns by at most `max_angle` radians: as Phase 1's static
    Gaussians, a constant offset is not motion. Returns still [K] (bool; an object without
    Gaussians is still), and per object the closed-form fit (Kabsch with `rigid`, else least
    squares) of `x0` onto the mean positions as linear parts [K, 3, 3] and offsets [K, 3]
    (float64; a shift alone below 3 or 4 Gaussians, the identity without any).

    `all_or_none`: only whether every object is still matters; the first frame that moves a
    Gaussian by more than twice `max_spread` along an axis from another frame (so more than
    `max_spread` from its mean) ends the search, with no object still."""
    rows = [np.nonzero(labels == k)[0] for k in range(num_objects)]
    linear = np.tile(np.eye(3), (num_objects, 1, 1))
    offset = np.zeros((num_objects, 3))
    total, count = np.zeros_like(x0, dtype=np.float64), 0
    low = high = None
    for pos in positions:
        total += pos
        count += 1
        if all_or_none:
            low = pos.copy() if low is None else np.minimum(low, pos, out=low)
            high = pos.copy() if high is None else np.maximum(high, pos, out=high)
            if (high - low).max(initial=0.0) > 2.0 * max_spread:
                return np.zeros(num_objects, dtype=bool), linear, offset
    mean = total / max(count, 1)
    spread = np.zeros(len(x0))
    angle = np.zeros(num_objects)
    for pos in positions:
        np.maximum(spread, np.linalg.norm(pos - mean, axis=1), out=spread)
        for k, sel in enumerate(rows):
            if len(sel) >= 3:
                r = kabsch(mean[sel], pos[sel])[0]
                angle[k] = max(angle[k], float(np.linalg.norm(matrix_to_rotvec(r))))
    still = np.ones(num_objects, dtype=bool)
    for k, sel in enumerate(rows):
        if len(sel) == 0:
            continue
        still[k] = spread[sel].max() <= max_spread and angle[k] <= max_angle
        if len(sel) >= (3 if rigid else 4):
            linear[k], offset[k] = (kabsch if rigid else fit_affine)(x0[sel], mean[sel])
        else:
            offset[k] = (mean[sel] - x0[sel]).mean(0)
    return still, linear, offset


def cosine_lr(start: float, final: float, frac: float) -> float:
    """Cosine annealing from `start` to `final` as `frac` goes 0 -> 1."""
    frac = min(1.0, max(0.0, frac))
    return final + 0.5 * (start - final) * (1.0 + math.cos(math.pi * frac))
