"""Phase 1 deformation model (paper Sec. 3.1, Appendix A): per-Gaussian embeddings and the
deformation MLP D_theta(x0, z, gamma(t)) -> (dx, dw, dl), applied as

    x(t) = x0 + dx                                  (Eq. 2)
    q(t) = normalize(aa2q(dw) (x) q0)               (Eq. 3, quaternions w, x, y, z)
    s(t) = exp(log s0 + dl)                         (Eq. 4)

The last layer is zero-initialised, so training starts from the identity deformation.
Beyond the paper, behind `DeformConfig` switches whose defaults are the paper's model: a
positional encoding of x0 (`position_bands`) and bfloat16 hidden layers (`precision`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from sync4d.geometry import axis_angle_to_quat, quat_multiply
from sync4d.settings import choice, ranged

__all__ = [
    "DeformConfig",
    "DeformationMLP",
    "deform_gaussians",
    "position_encoding",
    "time_encoding",
]


@dataclass(frozen=True)
class DeformConfig:
    """Hyperparameters of D_theta (Appendix A defaults)."""

    #: Dimension of each Gaussian's learned embedding z_i.
    embed_dim: int = ranged(32, 1)
    #: Frequencies L of the time encoding gamma(t) = [t, sin(2^k w t), cos(2^k w t)], k < L.
    bands: int = ranged(6, 0, 20)
    #: The time encoding's lowest angular frequency w, radians per unit of time. pi (the
    #: paper, NeRF's encoding) makes every band above the lowest periodic over [0, 1]: the
    #: first and last instants share 2L - 1 of gamma's 2L sines and cosines, and D_theta must
    #: tell them apart from t and one band alone. 1 (Deformable-3DGS's, SC-GS's) repeats no
    #: band's phase at t = 1 below k = 2.
    time_frequency: float = ranged(math.pi, 0.0, 1e3, lo_open=True)
    #: Frequencies of an encoding of the canonical position, [x0, sin(2^k pi x0),
    #: cos(2^k pi x0)] for k below it (3 + 6 L inputs instead of x0's 3). 0 (the paper) feeds
    #: the raw position; Deformable-3DGS encodes it with 10 so limbs next to each other can
    #: move apart.
    position_bands: int = ranged(0, 0, 20)
    #: Width of D_theta's hidden layers.
    hidden: int = ranged(128, 1)
    #: Hidden layers of D_theta (ReLU after each).
    layers: int = ranged(4, 1)
    #: Output scale of the position offset dx (world units).
    scale_position: float = ranged(0.10, 0.0)
    #: World units per unit of D_theta's position input: it reads x0 / position_unit. 1 (the
    #: paper: the raw position) suits scenes the size of D-NeRF's; `fit` advises a value for a
    #: scene of another size, with `scale_position` (docs/results/stability.md).
    position_unit: float = ranged(1.0, 0.0, lo_open=True)
    #: Output scale of the rotation vector dw (radians).
    scale_rotation: float = ranged(0.10, 0.0)
    #: Output scale of the log-scale offset dl.
    scale_log_scale: float = ranged(0.05, 0.0)
    #: Arithmetic of the hidden layers after the first: "float32", or "bfloat16" (CPU
    #: autocast; the first layer, reading the position, and the head stay float32). D_theta
    #: is about half of a Phase 1 iteration's time on a CPU; bfloat16 runs its forward and
    #: backward 1.5-1.8x faster on CPUs with AVX-512 BF16 (docs/results/phase1-articulated.md).
    precision: str = choice("float32", ("float32", "bfloat16"))

    @property
    def input_dim(self) -> int:
        """3 + 6 * position_bands (position) + embedding + 1 + 2 * bands (time encoding): 48
        by default."""
        return 3 * (1 + 2 * self.position_bands) + self.embed_dim + 1 + 2 * self.bands


def time_encoding(t: Tensor, bands: int = 6, frequency: float = math.pi) -> Tensor:
    """gamma(t) = [t, sin(2^0 w t), cos(2^0 w t), ..., sin(2^(L-1) w t), cos(...)], w =
    `frequency` (the paper: pi): [...] -> [..., 1 + 2 L]."""
    t = t.unsqueeze(-1)
    freqs = (2.0 ** torch.arange(bands, dtype=t.dtype, device=t.device)) * frequency
    ang = t * freqs
    enc = torch.stack([torch.sin(ang), torch.cos(ang)], dim=-1).flatten(-2)
    return torch.cat([t, enc], dim=-1)


def position_encoding(x: Tensor, bands: int) -> Tensor:
    """[x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(L-1) pi x), cos(2^(L-1) pi x)], each
    term the 3 coordinates: [N, 3] -> [N, 3 (1 + 2 L)]; `x` itself when `bands` is 0."""
    if bands == 0:
        return x
    freqs = (2.0 ** torch.arange(bands, dtype=x.dtype, device=x.device)) * math.pi
    ang = x.unsqueeze(-2) * freqs.unsqueeze(-1)  # [N, L, 3]
    enc = torch.cat([torch.sin(ang), torch.cos(ang)], dim=-1).flatten(-2)  # [N, 6 L]
    return torch.cat([x, enc], dim=-1)


@torch.no_grad()
def _default_linear_init(layer: nn.Linear, generator: torch.Generator) -> None:
    """nn.Linear's own initialisation (weights Kaiming-uniform with a = sqrt(5), biases
    uniform in +-1/sqrt(fan_in)), drawn from `generator`."""
    nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
    bound = 1.0 / math.sqrt(layer.in_features)
    nn.init.uniform_(layer.bias, -bound, bound, generator=generator)


class DeformationMLP(nn.Module):
    """D_theta: [x0 (or its encoding); z; gamma(t)] (48-d by default) -> Lin 128 -> ReLU ->
    ... -> Lin 9 (zero-initialised), scaled to (dx 0.10, dw 0.10, dl 0.05). Hidden layers
    start with torch's default Linear initialisation drawn from `generator` (torch's unseeded
    global generator when None), so a seeded model is the same in every process."""

    def __init__(
        self, config: DeformConfig | None = None, generator: torch.Generator | None = None
    ) -> None:
        super().__init__()
        self.config = config or DeformConfig()
        c = self.config
        if c.precision not in ("float32", "bfloat16"):
            raise ValueError(f"precision: expected 'float32' or 'bfloat16', got {c.precision!r}")
        if c.position_bands < 0:
            raise ValueError(f"position_bands: expected 0 or more, got {c.position_bands}")
        dims = [c.input_dim] + [c.hidden] * (c.layers - 1)
        blocks: list[nn.Module] = []
        for d_in, d_out in zip(dims[:-1], dims[1:], strict=True):
            layer = nn.Linear(d_in, d_out)
            if generator is not None:
                _default_linear_init(layer, generator)
            blocks += [layer, nn.ReLU()]
        self.trunk = nn.Sequential(*blocks)
        self.head = nn.Linear(dims[-1], 9)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x0: Tensor, z: Tensor, t: float | Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Deltas (dx [N, 3], dw [N, 3] rotation vector, dl [N, 3] log-scale) at time `t`
        (a scalar in [0, 1] or a [N] tensor) for canonical means `x0` [N, 3], embeddings `z`."""
        n = x0.shape[0]
        t = torch.as_tensor(t, dtype=x0.dtype, device=x0.device)
        if t.dim() == 0:
            t = t.expand(n)
        c = self.config
        pos = x0 if c.position_unit == 1.0 else x0 / c.position_unit
        gamma = time_encoding(t, c.bands, c.time_frequency)
        h = torch.cat([position_encoding(pos, c.position_bands), z, gamma], dim=-1)
        if c.precision == "bfloat16" and h.device.type == "cpu":
            first, rest = self.trunk[:2], self.trunk[2:]
            h = first(h)
            with torch.autocast("cpu", dtype=torch.bfloat16):
                h = rest(h)
            o = self.head(h.float())
        else:
            o = self.head(self.trunk(h))
        return (
            o[:, 0:3] * c.scale_position,
            o[:, 3:6] * c.scale_rotation,
            o[:, 6:9] * c.scale_log_scale,
        )


def deform_gaussians(
    x0: Tensor, q0: Tensor, log_s0: Tensor, dx: Tensor, dw: Tensor, dl: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Eqs. 2-4: deformed means [N, 3], unit quaternions [N, 4] and scales [N, 3] (positive)."""
    q = quat_multiply(axis_angle_to_quat(dw), q0)
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return x0 + dx, q, torch.exp(log_s0 + dl)
