"""The fused node-weighted sum (sync4d.phase1.node_op) against the torch path of
`sync4d.phase1.nodes.blend` (indexing + softmax + gather_blend): forward and every gradient,
float32 against a float64 reference, far-away Gaussians, K = 1, float64 gradcheck,
determinism across calls and thread counts, and the argument checks; the linear epilogue
(`linear_epilogue`) against the torch expression of `blend`'s reference path, likewise."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from sync4d.geometry import quat_multiply
from sync4d.phase1.node_op import linear_epilogue, node_weighted_sum
from sync4d.phase1.nodes import gather_blend

F64 = torch.float64


def _torch_path(x0: Tensor, positions: Tensor, inv_r2: Tensor, table: Tensor, index: Tensor
                ) -> Tensor:  # fmt: skip
    """The weighted sum as `blend` computes it with given weights, in torch."""
    g = torch.cat([positions, inv_r2.unsqueeze(-1)], dim=-1)[index.long()]
    d2 = ((x0.unsqueeze(1) - g[..., :3]) ** 2).sum(-1)
    weights = torch.softmax(-0.5 * d2 * g[..., 3], dim=-1)
    return gather_blend(table, index.long(), weights)


def _case(n: int, m: int, k: int, c: int, far: int = 0, seed: int = 0,
          dtype: torch.dtype = torch.float32) -> tuple[list[Tensor], Tensor]:  # fmt: skip
    """(x0, positions, inv_r2, table) requiring gradients, and index [n, k] (int64); the first
    `far` Gaussians 1e3 away from every node (radii 0.2-0.8)."""
    g = torch.Generator().manual_seed(seed)
    positions = torch.rand(m, 3, generator=g, dtype=F64) * 2 - 1
    radii = 0.2 + 0.6 * torch.rand(m, generator=g, dtype=F64)
    table = torch.randn(m, c, generator=g, dtype=F64)
    x0 = torch.rand(n, 3, generator=g, dtype=F64) * 2.4 - 1.2
    x0[:far, 0] += 1e3
    index = torch.randint(0, m, (n, k), generator=g)
    inputs = [t.to(dtype).requires_grad_() for t in (x0, positions, radii**-2, table)]
    return inputs, index


def _grads(out: Tensor, inputs: list[Tensor], grad: Tensor) -> list[Tensor]:
    return list(torch.autograd.grad(out, inputs, grad.to(out.dtype)))


def _assert_close(name: str, got: Tensor, want: Tensor, rtol: float) -> None:
    """|got - want| <= rtol max|want| (+ a tiny floor), elementwise; both finite."""
    got, want = got.detach(), want.detach()
    assert bool(torch.isfinite(got).all()), name
    scale = float(want.abs().max()) if want.numel() else 0.0
    err = float((got.double() - want.double()).abs().max()) if want.numel() else 0.0
    assert err <= rtol * scale + 1e-7, f"{name}: max error {err:.3g}, scale {scale:.3g}"


NAMES = ("x0", "positions", "inv_r2", "table")


@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
@pytest.mark.parametrize(("n", "m", "k", "c", "far"),
                         [(600, 40, 8, 19, 20), (300, 30, 4, 11, 5), (150, 9, 3, 5, 2),
                          (120, 10, 1, 19, 3)])  # fmt: skip
def test_float32_op_matches_the_float64_torch_path(
    n: int, m: int, k: int, c: int, far: int, index_dtype: torch.dtype
) -> None:
    inputs, index = _case(n, m, k, c, far, seed=k * c)
    grad = torch.randn(n, c, generator=torch.Generator().manual_seed(1), dtype=F64)
    out = node_weighted_sum(*inputs, index.to(index_dtype), threads=2)
    grads = _grads(out, inputs, grad)
    ref_inputs = [t.detach().double().requires_grad_() for t in inputs]
    ref = _torch_path(*ref_inputs, index)
    ref_grads = _grads(ref, ref_inputs, grad)
    assert out.dtype == torch.float32 and out.shape == (n, c)
    _assert_close("b", out, ref, 1e-5)
    for name, g, r in zip(NAMES, grads, ref_grads, strict=True):
        assert g.dtype == torch.float32 and g.shape == r.shape, name
        _assert_close(name, g, r, 1e-4)
    if k == 1:
        # One node: weight 1, b is its row and no gradient reaches the geometry.
        assert torch.equal(out.detach(), inputs[3].detach()[index[:, 0]])
        for name, g in zip(NAMES[:3], grads[:3], strict=True):
            assert bool((g == 0).all()), name


def test_float64_gradcheck() -> None:
    inputs, index = _case(12, 5, 3, 4, far=1, seed=3, dtype=F64)
    inputs[0].data[0, 0] -= 999.0  # far, but not so far that its weights are all 0 or 1

    def fn(x0: Tensor, positions: Tensor, inv_r2: Tensor, table: Tensor) -> Tensor:
        return node_weighted_sum(x0, positions, inv_r2, table, index, threads=1)

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-8, rtol=1e-6)


def test_far_gaussians_take_their_nearest_node_without_nan() -> None:
    positions = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    inv_r2 = torch.full((3,), 1e4)  # radius 0.01
    table = torch.tensor([[1.0, -1.0], [2.0, -2.0], [3.0, -3.0]])
    x0 = torch.tensor([[1e4, 0.0, 0.0], [-1e4, 5.0, 0.0]])
    index = torch.tensor([[0, 1, 2], [2, 1, 0]])
    inputs = [t.requires_grad_() for t in (x0, positions, inv_r2, table)]
    out = node_weighted_sum(*inputs, index)
    assert torch.equal(out.detach(), torch.tensor([[3.0, -3.0], [1.0, -1.0]]))
    for name, g in zip(NAMES, _grads(out, inputs, torch.ones(2, 2)), strict=True):
        assert bool(torch.isfinite(g).all()), name
    # The torch path agrees (it subtracts the maximum too).
    assert torch.allclose(_torch_path(*[t.detach() for t in inputs], index), out)


def test_deterministic_across_calls_and_thread_counts() -> None:
    inputs, index = _case(3_000, 200, 8, 19, far=10, seed=5)
    grad = torch.randn(3_000, 19, generator=torch.Generator().manual_seed(2))
    runs = []
    for threads in (1, 2, 2, 3, None):
        out = node_weighted_sum(*inputs, index, threads=threads)
        runs.append([out.detach(), *_grads(out, inputs, grad)])
    for run in runs[1:]:
        for a, b in zip(runs[0], run, strict=True):
            assert torch.equal(a, b)


def test_gradients_only_where_asked_and_views_as_inputs() -> None:
    inputs, index = _case(50, 6, 4, 19, seed=7)
    x0, positions, inv_r2, table = (t.detach() for t in inputs)
    table.requires_grad_()
    # Non-contiguous views: a transposed x0 and a column slice of a wider table.
    x0_t = x0.t().contiguous().t()
    wide = torch.cat([table.detach(), torch.zeros(6, 3)], dim=1)[:, :19]
    assert not x0_t.is_contiguous() and not wide.is_contiguous()
    out = node_weighted_sum(x0_t, positions, inv_r2, table, index)
    (g_table,) = torch.autograd.grad(out.sum(), [table])
    assert torch.equal(node_weighted_sum(x0, positions, inv_r2, wide, index), out.detach())
    assert torch.allclose(g_table, _grads(_torch_path(x0, positions, inv_r2, table, index),
                                          [table], torch.ones(50, 19))[0], atol=1e-5)  # fmt: skip


def test_bad_arguments_raise_value_errors_naming_them() -> None:
    inputs, index = _case(10, 4, 3, 5, seed=1)
    x0, positions, inv_r2, table = (t.detach() for t in inputs)
    cases = {
        "x0": (x0[:, :2], positions, inv_r2, table, index),
        "positions": (x0, positions.double(), inv_r2, table, index),
        "inv_r2": (x0, positions, inv_r2[:3], table, index),
        "table": (x0, positions, inv_r2, table[:3], index),
        "index": (x0, positions, inv_r2, table, index.float()),
    }
    for name, args in cases.items():
        with pytest.raises(ValueError, match=f"^{name}:"):
            node_weighted_sum(*args)
    with pytest.raises(ValueError, match="^index:"):
        node_weighted_sum(x0, positions, inv_r2, table, index[:, :0])
    with pytest.raises(ValueError, match="^index:"):
        node_weighted_sum(x0, positions, inv_r2, table, index[:9])
    bad = index.clone()
    bad[4, 1] = 4
    with pytest.raises(ValueError, match=r"^index: entry 13 \(Gaussian 4\)"):
        node_weighted_sum(x0, positions, inv_r2, table, bad)
    bad[4, 1] = -1
    with pytest.raises(ValueError, match="^index:"):
        node_weighted_sum(x0, positions, inv_r2, table, bad)
    with pytest.raises(ValueError, match="^threads:"):
        node_weighted_sum(x0, positions, inv_r2, table, index, threads=0)


def _torch_epilogue(b: Tensor, x0: Tensor, q0: Tensor, log_s0: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
    """The linear epilogue as `blend`'s reference path computes it, in torch."""
    x = (b[:, :9].reshape(-1, 3, 3) * x0.unsqueeze(1)).sum(-1) + b[:, 9:12]
    r = quat_multiply(b[:, 12:16], q0)
    q = r / r.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return x, q, torch.exp(log_s0 + b[:, 16:19])


def _epilogue_case(n: int, seed: int, dtype: torch.dtype = torch.float32) -> list[Tensor]:
    """(blended, x0, q0, log_s0) requiring gradients; q0 unit, blended rows near a rigid map."""
    g = torch.Generator().manual_seed(seed)
    b = torch.randn(n, 19, generator=g, dtype=F64) * 0.3
    b[:, [0, 4, 8]] += 1.0
    b[:, 12] += 1.0
    q0 = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=F64), dim=-1)
    x0 = torch.randn(n, 3, generator=g, dtype=F64)
    log_s0 = torch.randn(n, 3, generator=g, dtype=F64) - 3.0
    return [t.to(dtype).requires_grad_() for t in (b, x0, q0, log_s0)]


EPILOGUE_NAMES = ("blended", "x0", "q0", "log_s0")


@pytest.mark.parametrize("n", [1, 700, 1_500])
def test_linear_epilogue_matches_the_float64_torch_expression(n: int) -> None:
    inputs = _epilogue_case(n, seed=n)
    g = torch.Generator().manual_seed(4)
    grads_out = [torch.randn(n, w, generator=g, dtype=F64) for w in (3, 4, 3)]
    outs = linear_epilogue(*inputs, threads=2)
    ref_inputs = [t.detach().double().requires_grad_() for t in inputs]
    refs = _torch_epilogue(*ref_inputs)
    for name, o, r in zip(("means", "quats", "scales"), outs, refs, strict=True):
        assert o.dtype == torch.float32 and o.shape == r.shape, name
        _assert_close(name, o, r, 1e-5)
    got = torch.autograd.grad(outs, inputs, [t.float() for t in grads_out])
    want = torch.autograd.grad(refs, ref_inputs, grads_out)
    for name, a, r in zip(EPILOGUE_NAMES, got, want, strict=True):
        assert a.dtype == torch.float32 and a.shape == r.shape, name
        _assert_close(name, a, r, 1e-4)


def test_linear_epilogue_float64_gradcheck_and_unused_outputs() -> None:
    inputs = _epilogue_case(9, seed=2, dtype=F64)

    def fn(*args: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        return linear_epilogue(*args, threads=1)

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-8, rtol=1e-6)
    # Only the means used: the quaternion and scale outputs get no gradient (None), and the
    # blended row's rotation and scale columns none either.
    x, _, _ = linear_epilogue(*inputs)
    gb, gq0 = torch.autograd.grad(x.sum(), [inputs[0], inputs[2]])
    assert bool((gb[:, 12:] == 0).all()) and bool((gq0 == 0).all())


def test_linear_epilogue_is_the_same_for_any_thread_count() -> None:
    inputs = _epilogue_case(5_000, seed=9)
    runs = []
    for threads in (1, 2, 3, None):
        outs = linear_epilogue(*inputs, threads=threads)
        runs.append([o.detach() for o in outs]
                    + list(torch.autograd.grad(sum(o.sum() for o in outs), inputs)))
    for run in runs[1:]:
        for a, b in zip(runs[0], run, strict=True):
            assert torch.equal(a, b)


def test_linear_epilogue_bad_arguments_raise_value_errors_naming_them() -> None:
    b, x0, q0, log_s0 = (t.detach() for t in _epilogue_case(6, seed=1))
    cases = {
        "blended": (b[:, :18], x0, q0, log_s0),
        "x0": (b, x0[:5], q0, log_s0),
        "q0": (b, x0, q0.double(), log_s0),
        "log_s0": (b, x0, q0, log_s0[:, :2]),
    }
    for name, args in cases.items():
        with pytest.raises(ValueError, match=f"^{name}:"):
            linear_epilogue(*args)
    with pytest.raises(ValueError, match="^threads:"):
        linear_epilogue(b, x0, q0, log_s0, threads=0)
