"""The fused node-weighted sum of the node motion model (`sync4d.phase1.nodes`) and the linear
blend's epilogue, on the Rust kernels of sync4d-motion (`rust/motion`, through `sync4d._core`).

For N Gaussians at canonical means `x0` [N, 3], each blending its K nodes `index` [N, K] out of
M nodes at `positions` [M, 3] with inverse squared radii `inv_r2` [M] and values `table`
[M, C]::

    d2_ik = |x0_i - p_j|^2,  j = index[i, k]
    w_ik  = softmax_k(-0.5 d2_ik inv_r2_j)          (each row's maximum subtracted)
    b_i   = sum_k w_ik table[j]                     [N, C]

`node_weighted_sum` is this function with its exact backward to `x0`, `positions`, `inv_r2` and
`table`, the same values as indexing + `softmax` + `gather_blend` in torch without their
[N, K, 4] gathers, index_add_ scatters and autograd graph: one pass over the Gaussians forward,
one over the Gaussians and one over the nodes backward, parallel over Gaussians (resp. nodes)
on `threads` threads. Node gradients are summed in a fixed order, so results are bit-identical
for any thread count. A Gaussian far from all its nodes gets finite weights (its nearest node's
tends to 1). No double backward.

`linear_epilogue` applies each Gaussian's blended row b_i [19] (affine map A [9], translation
t [3], rotation quaternion p [4], log-scale offset dl [3]) to its canonical mean, unit
quaternion and log-scales: x = A x0 + t, q = normalize(p (x) q0), s = exp(log_s0 + dl), the
same values as the torch expression in `nodes.blend`'s reference path, in one pass over the
Gaussians each way instead of about forty elementwise torch calls with their autograd graph.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from sync4d import _core
from sync4d.raster import grad_or_zeros, thread_count

__all__ = ["linear_epilogue", "node_weighted_sum"]

_FLOATS = (torch.float32, torch.float64)
_INDICES = (torch.int32, torch.int64)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _check(name: str, t: object, dim: int, dtypes: tuple[torch.dtype, ...]) -> Tensor:
    if not isinstance(t, Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if t.device.type != "cpu":
        raise ValueError(f"{name}: must be on the CPU, got device {t.device}")
    if t.dtype not in dtypes:
        want = " or ".join(str(d).removeprefix("torch.") for d in dtypes)
        raise ValueError(f"{name}: expected {want}, got {t.dtype}")
    if t.dim() != dim:
        raise ValueError(f"{name}: expected {dim} dimensions, got shape {list(t.shape)}")
    return t


class _NodeWeightedSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x0, positions, inv_r2, table, index, threads):  # type: ignore[override]
        arrays = tuple(_np(t) for t in (x0, positions, inv_r2, table, index))
        k, c = index.shape[1], table.shape[1]
        b, _ = _core.node_weighted_sum_forward(
            *arrays, neighbours=k, channels=c, want_weights=False, threads=threads
        )
        ctx.save_for_backward(x0, positions, inv_r2, table, index)
        ctx.threads = threads
        return torch.from_numpy(b).reshape(x0.shape[0], c)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):  # type: ignore[override]
        x0, positions, inv_r2, table, index = ctx.saved_tensors
        (m, c), k = table.shape, index.shape[1]
        arrays = tuple(_np(t) for t in (x0, positions, inv_r2, table, index))
        gx, gp, gr, gt = _core.node_weighted_sum_backward(
            *arrays, neighbours=k, channels=c, grad_out=_np(grad.to(x0.dtype)), threads=ctx.threads
        )
        grads = (
            torch.from_numpy(gx).reshape(-1, 3),
            torch.from_numpy(gp).reshape(m, 3),
            torch.from_numpy(gr),
            torch.from_numpy(gt).reshape(m, c),
        )
        need = ctx.needs_input_grad
        return (*(g if need[a] else None for a, g in enumerate(grads)), None, None)


def node_weighted_sum(
    x0: Tensor, positions: Tensor, inv_r2: Tensor, table: Tensor, index: Tensor,
    *, threads: int | None = None,
) -> Tensor:  # fmt: skip
    """b [N, C] = sum_k softmax_k(-0.5 |x0_i - p_j|^2 inv_r2_j) table[j], j = index[i, k], of
    CPU tensors `x0` [N, 3], `positions` [M, 3], `inv_r2` [M], `table` [M, C] (all float32, or
    all float64) and `index` [N, K] (int32 or int64, entries in 0..M, K >= 1), differentiable in
    the four float tensors (module docstring). `threads`: the kernel's thread count (None:
    rayon's default; 1 runs on the calling thread). Bad arguments raise ValueError naming
    them."""
    _check("x0", x0, 2, _FLOATS)
    for name, t, dim in (("positions", positions, 2), ("inv_r2", inv_r2, 1), ("table", table, 2)):
        _check(name, t, dim, (x0.dtype,))
    _check("index", index, 2, _INDICES)
    n, m = x0.shape[0], positions.shape[0]
    wants = (
        ("x0", x0, (n, 3)), ("positions", positions, (m, 3)), ("inv_r2", inv_r2, (m,)),
        ("table", table, (m, max(table.shape[1], 1))),
        ("index", index, (n, max(index.shape[1], 1))),
    )  # fmt: skip
    for name, t, want in wants:
        if tuple(t.shape) != want:
            raise ValueError(f"{name}: expected shape {list(want)}, got {list(t.shape)}")
    return _NodeWeightedSum.apply(x0, positions, inv_r2, table, index, thread_count(threads))


class _LinearEpilogue(torch.autograd.Function):
    @staticmethod
    def forward(ctx, blended, x0, q0, log_s0, threads):  # type: ignore[override]
        arrays = tuple(_np(t) for t in (blended, x0, q0, log_s0))
        means, quats, scales = _core.linear_epilogue_forward(*arrays, threads=threads)
        ctx.save_for_backward(blended, x0, q0, log_s0)
        ctx.threads = threads
        n = x0.shape[0]
        return (torch.from_numpy(means).reshape(n, 3), torch.from_numpy(quats).reshape(n, 4),
                torch.from_numpy(scales).reshape(n, 3))  # fmt: skip

    @staticmethod
    @once_differentiable
    def backward(ctx, gm, gq, gs):  # type: ignore[override]
        blended, x0, q0, log_s0 = ctx.saved_tensors
        arrays = tuple(_np(t) for t in (blended, x0, q0, log_s0))
        grads = tuple(grad_or_zeros(g, t) for g, t in ((gm, x0), (gq, q0), (gs, log_s0)))
        out = _core.linear_epilogue_backward(
            *arrays, grad_means=grads[0], grad_quats=grads[1], grad_scales=grads[2],
            threads=ctx.threads,
        )  # fmt: skip
        shapes = (blended.shape, x0.shape, q0.shape, log_s0.shape)
        need = ctx.needs_input_grad
        return (*(torch.from_numpy(g).reshape(s) if need[a] else None
                  for a, (g, s) in enumerate(zip(out, shapes, strict=True))), None)  # fmt: skip


def linear_epilogue(
    blended: Tensor, x0: Tensor, q0: Tensor, log_s0: Tensor, *, threads: int | None = None,
) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """The linear blend's epilogue (module docstring) of CPU tensors `blended` [N, 19], `x0`
    [N, 3], `q0` [N, 4], `log_s0` [N, 3] (all float32, or all float64): deformed means [N, 3],
    unit quaternions [N, 4] and scales [N, 3], differentiable in all four. `threads` as for
    `node_weighted_sum`. Bad arguments raise ValueError naming them."""
    _check("blended", blended, 2, _FLOATS)
    for name, t in (("x0", x0), ("q0", q0), ("log_s0", log_s0)):
        _check(name, t, 2, (blended.dtype,))
    n = blended.shape[0]
    for name, t, want in (("blended", blended, (n, 19)), ("x0", x0, (n, 3)), ("q0", q0, (n, 4)),
                          ("log_s0", log_s0, (n, 3))):  # fmt: skip
        if tuple(t.shape) != want:
            raise ValueError(f"{name}: expected shape {list(want)}, got {list(t.shape)}")
    return _LinearEpilogue.apply(blended, x0, q0, log_s0, thread_count(threads))
