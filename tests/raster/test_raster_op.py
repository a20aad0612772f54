"""The torch op over the Rust rasterizer: float64 gradchecks, float32 vs float64 agreement,
argument errors, counters, thread safety and determinism."""

from __future__ import annotations

import inspect
import threading

import pytest
import torch

from support.scenes import raster_scene
from sync4d import _core, raster

GAUSSIAN_ARGS = ("means", "quats", "scales", "opacities", "features")


def render(scene: dict, **kw) -> raster.RasterOutput:
    return raster.rasterize(
        *(scene[k] for k in GAUSSIAN_ARGS),
        scene["viewmat"],
        scene["K"],
        scene["width"],
        scene["height"],
        **kw,
    )


@pytest.mark.gradcheck
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("wrt", GAUSSIAN_ARGS)
def test_gradcheck_full_pipeline(wrt: str, antialiased: bool) -> None:
    """Finite differences in float64 through project + composite, for every input."""
    scene = raster_scene(8, 20, 16, channels=2, seed=3, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.7], dtype=torch.float64)
    weights = torch.rand(16, 20, 4, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def f(x: torch.Tensor) -> torch.Tensor:
        s = dict(scene, **{wrt: x})
        out = render(s, background=bg, antialiased=antialiased)
        stacked = torch.cat([out.features, out.alpha, out.depth], -1)
        return (stacked * weights).sum()

    x = scene[wrt].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.gradcheck
def test_gradcheck_rasterize_to_pixels_inputs() -> None:
    """The compositing stage alone, w.r.t. means2d, conics, depths and opacities."""
    s = raster_scene(10, 18, 14, seed=5, dtype=torch.float64)
    p = raster.project_gaussians(
        s["means"], s["quats"], s["scales"], s["opacities"], s["viewmat"], s["K"], 18, 14
    )
    w = torch.rand(14, 18, 5, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    base = [p.means2d.detach(), p.conics.detach(), p.depths.detach(), p.opacities.detach()]
    for i in range(4):

        def f(x: torch.Tensor, i: int = i) -> torch.Tensor:
            args = list(base)
            args[i] = x
            img, alpha, depth = raster.rasterize_to_pixels(*args, p.radii, s["features"], 18, 14)
            return (torch.cat([img, alpha, depth], -1) * w).sum()

        x = base[i].clone().requires_grad_(True)
        assert torch.autograd.gradcheck(f, (x,), eps=1e-7, atol=1e-6, rtol=1e-4)


@pytest.mark.gradcheck
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_gradcheck_spherical_harmonics(degree: int) -> None:
    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn(5, 3, generator=g, dtype=torch.float64, requires_grad=True)
    coeffs = torch.randn(5, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda d, c: raster.spherical_harmonics(degree, d, c), (dirs, coeffs), eps=1e-6, atol=1e-7
    )


def test_float32_fast_path_matches_float64_reference() -> None:
    s64 = raster_scene(300, 64, 48, channels=4, seed=9, dtype=torch.float64)
    s32 = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in s64.items()}
    for s in (s32, s64):
        for k in GAUSSIAN_ARGS:
            s[k] = s[k].detach().clone().requires_grad_(True)
    out32, out64 = render(s32), render(s64)
    for name in ("features", "alpha"):
        a, b = getattr(out32, name), getattr(out64, name)
        assert (a.double() - b).abs().max() < 1e-4, name
    mask = out64.alpha > 0.05
    assert (out32.depth.double() - out64.depth)[mask].abs().max() < 1e-3
    w = torch.rand(48, 64, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    (out32.features * w.float()).sum().backward()
    (out64.features * w).sum().backward()
    for k in GAUSSIAN_ARGS:
        g32, g64 = s32[k].grad.double(), s64[k].grad
        rel = (g32 - g64).norm() / g64.norm()
        assert rel < 1e-3, f"{k}: relative L2 error {rel:.2e}"
    assert out32.counters["visible"] == out64.counters["visible"] > 0
    assert out32.counters["blended"] == out64.counters["blended"] > 0


def test_outputs_shapes_counters_and_means2d_grad(small_scene: dict) -> None:
    s = small_scene
    for k in GAUSSIAN_ARGS:
        s[k].requires_grad_(True)
    out = render(s, background=torch.tensor([1.0, 0.0, 0.5]))
    assert out.features.shape == (40, 48, 3)
    assert out.alpha.shape == out.depth.shape == (40, 48, 1)
    assert out.radii.dtype == torch.int32 and out.radii.shape == (40, 2)
    assert set(out.counters) == {"visible", "intersections", "evaluated", "blended"}
    assert out.counters["blended"] > 0
    out.means2d.retain_grad()
    out.features.mean().backward()
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0
    # Where nothing is drawn the background shows through.
    empty = out.alpha[..., 0] == 0
    if empty.any():
        assert torch.allclose(out.features[empty], torch.tensor([1.0, 0.0, 0.5]))


def test_no_grad_forward_and_repeated_calls_are_identical(small_scene: dict) -> None:
    with torch.no_grad():
        a = render(small_scene)
        b = render(small_scene)
    assert torch.equal(a.features, b.features) and torch.equal(a.depth, b.depth)


def test_thread_counts_give_identical_results() -> None:
    s = raster_scene(2000, 96, 80, seed=4)
    for k in GAUSSIAN_ARGS:
        s[k].requires_grad_(True)
    results = []
    for threads in (1, 2):
        out = render(s, threads=threads)
        grads = torch.autograd.grad(
            out.features.sum() + out.depth.sum(), [s[k] for k in GAUSSIAN_ARGS]
        )
        results.append((out.features.detach(), grads))
    assert torch.equal(results[0][0], results[1][0])
    for g1, g2 in zip(results[0][1], results[1][1], strict=True):
        assert torch.equal(g1, g2)


def test_concurrent_renders_from_python_threads() -> None:
    """The GIL is released while Rust works; concurrent calls stay correct."""
    s = raster_scene(500, 64, 64, seed=8)
    with torch.no_grad():
        expected = render(s).features
    outputs: list = [None] * 4
    errors: list = []

    def work(i: int) -> None:
        try:
            with torch.no_grad():
                outputs[i] = render(s, threads=1).features
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for o in outputs:
        assert torch.equal(o, expected)


# ---------------------------------------------------------------------------------------------
# Bad input: one ValueError naming the argument.
# ---------------------------------------------------------------------------------------------


def _bad(scene: dict, **changes) -> dict:
    s = dict(scene)
    s.update(changes)
    return s


@pytest.mark.parametrize(
    "arg,value,match",
    [
        ("means", torch.zeros(40, 2), "means: expected shape"),
        ("quats", torch.zeros(39, 4), "quats: expected shape"),
        ("scales", torch.zeros(40, 3, dtype=torch.float64), "scales: expected dtype"),
        ("opacities", torch.zeros(40, dtype=torch.int64), "opacities: expected dtype"),
        ("features", torch.zeros(40, 0), "features"),
        ("means", [[0.0, 0.0, 1.0]], "means: expected a torch.Tensor"),
        ("viewmat", torch.eye(3), "viewmat: expected shape"),
        ("K", torch.eye(3) * 0, "K"),
        (
            "K",
            torch.tensor([[100.0, 1.0, 5.0], [0.0, 100.0, 5.0], [0.0, 0.0, 1.0]]),
            "K: expected a pinhole",
        ),
        (
            "viewmat",
            torch.diag(torch.tensor([2.0, 1.0, 1.0, 1.0])),
            "viewmat: upper 3x3 must be a rotation",
        ),
        ("width", 0, "width"),
        ("height", 1.5, "height"),
    ],
)
def test_bad_arguments_raise_value_error_naming_them(small_scene, arg, value, match) -> None:
    with pytest.raises(ValueError, match=match):
        render(_bad(small_scene, **{arg: value}))


@pytest.mark.parametrize("arg", ["means", "quats", "scales", "opacities", "features"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_inputs_are_rejected(small_scene, arg, bad) -> None:
    t = small_scene[arg].clone()
    t.view(-1)[3] = bad
    with pytest.raises(ValueError, match=f"^{arg}: .*non-finite|^{arg}: .*NaN"):
        render(_bad(small_scene, **{arg: t}))


def test_nan_camera_and_bad_ranges_are_rejected(small_scene) -> None:
    vm = torch.eye(4)
    vm[0, 3] = float("nan")
    with pytest.raises(ValueError, match="viewmat: contains NaN"):
        render(_bad(small_scene, viewmat=vm))
    with pytest.raises(ValueError, match="scales: must be >= 0"):
        render(_bad(small_scene, scales=-small_scene["scales"]))
    with pytest.raises(ValueError, match=r"opacities: must lie in \[0, 1\]"):
        render(_bad(small_scene, opacities=small_scene["opacities"] + 1.0))
    with pytest.raises(ValueError, match="near"):
        render(small_scene, near=0.0)
    with pytest.raises(ValueError, match="alpha_max"):
        render(small_scene, alpha_max=1.0)
    with pytest.raises(ValueError, match="background: expected shape"):
        render(small_scene, background=torch.zeros(2))
    with pytest.raises(ValueError, match="threads"):
        render(small_scene, threads=0)


def test_keyword_defaults_come_from_the_rust_core() -> None:
    """The wrapper's defaults are the core's `Default` settings, exported by `_core`; the
    literal values pin them, so a change on the Rust side is noticed."""
    core = {
        "near": _core.DEFAULT_NEAR,
        "far": _core.DEFAULT_FAR,
        "eps2d": _core.DEFAULT_EPS2D,
        "alpha_max": _core.DEFAULT_ALPHA_MAX,
    }
    assert core == {"near": 0.01, "far": 1e10, "eps2d": 0.3, "alpha_max": 0.99}
    assert all(type(v) is float for v in core.values())
    wrappers = {
        raster.project_gaussians: ("near", "far", "eps2d"),
        raster.rasterize_to_pixels: ("alpha_max",),
        raster.rasterize: ("near", "far", "eps2d", "alpha_max"),
    }
    for fn, names in wrappers.items():
        params = inspect.signature(fn).parameters
        for name in names:
            assert params[name].default == core[name], f"{fn.__name__}({name}=...)"


def test_wrong_device_is_named(small_scene) -> None:
    meta = torch.zeros(40, 3, device="meta")
    with pytest.raises(ValueError, match="means: must be on the CPU"):
        render(_bad(small_scene, means=meta))


def test_sh_argument_errors() -> None:
    with pytest.raises(ValueError, match="degree"):
        raster.spherical_harmonics(4, torch.zeros(2, 3), torch.zeros(2, 25, 3))
    with pytest.raises(ValueError, match="coeffs: degree 2 needs >= 9"):
        raster.spherical_harmonics(2, torch.zeros(2, 3), torch.zeros(2, 4, 3))
    with pytest.raises(ValueError, match="coeffs: expected shape"):
        raster.spherical_harmonics(1, torch.zeros(2, 3), torch.zeros(3, 4, 3))


def test_sh_features_view_dependence() -> None:
    """Degree-0 colour is 0.5 + C0 * c; higher degrees change with the camera position."""
    means = torch.zeros(1, 3)
    coeffs = torch.zeros(1, 4, 3)
    coeffs[0, 0] = 1.0
    coeffs[0, 3] = 1.0  # the x-linear basis term
    vm_a = torch.eye(4)
    vm_a[0, 3] = 1.0  # camera centre at x = -1: direction +x
    vm_b = torch.eye(4)
    vm_b[0, 3] = -1.0
    c0 = 0.28209479177387814
    ca = raster.sh_features(means, coeffs, vm_a, 0)
    assert torch.allclose(ca, torch.full((1, 3), 0.5 + c0))
    a = raster.sh_features(means, coeffs, vm_a, 1)
    b = raster.sh_features(means, coeffs, vm_b, 1)
    assert not torch.allclose(a, b)


def test_retained_graph_backward_twice_with_renders_in_between() -> None:
    """Each autograd node owns its buffers: a second backward of a retained graph is still
    right even after other renders reused the pool in between."""
    a = raster_scene(300, 48, 40, seed=1)
    b = raster_scene(300, 48, 40, seed=2)
    a["means"].requires_grad_(True)
    out = render(a)
    loss = out.features.sum()
    (g1,) = torch.autograd.grad(loss, a["means"], retain_graph=True)
    for _ in range(3):
        render(b)  # other forwards that keep their nodes alive
    kept = [render(b) for _ in range(2)]
    (g2,) = torch.autograd.grad(loss, a["means"])
    assert torch.equal(g1, g2)
    assert kept[0].features.shape == (40, 48, 3)


def _wgpu_or_skip() -> None:
    """Skip without a wgpu adapter, unless SYNC4D_REQUIRE_GPU=1 (CI, lavapipe) makes it a
    failure."""
    import os

    from sync4d import _core

    try:
        _core.wgpu_adapter()
    except RuntimeError as e:
        if os.environ.get("SYNC4D_REQUIRE_GPU") == "1":
            raise
        pytest.skip(f"no wgpu adapter: {e}")


def test_wgpu_backend_matches_cpu_forward_and_gradients() -> None:
    _wgpu_or_skip()
    scene = raster_scene(300, 48, 40, channels=3, seed=11)
    outs, grads = {}, {}
    for backend in ("cpu", "wgpu"):
        s = {k: (v.clone().requires_grad_(True) if k in GAUSSIAN_ARGS else v)
             for k, v in scene.items()}  # fmt: skip
        out = render(s, backend=backend, background=torch.tensor([0.1, 0.2, 0.3]))
        w = torch.linspace(0.5, 1.5, out.features.numel()).reshape(out.features.shape)
        ((out.features * w).sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        outs[backend] = (out.features.detach(), out.alpha.detach(), out.counters)
        grads[backend] = {k: s[k].grad for k in GAUSSIAN_ARGS}
    for a, b in zip(outs["cpu"][:2], outs["wgpu"][:2], strict=True):
        assert (a - b).abs().max() <= 1e-4
    assert outs["cpu"][2]["blended"] == outs["wgpu"][2]["blended"] > 0
    for k in GAUSSIAN_ARGS:
        a, b = grads["cpu"][k], grads["wgpu"][k]
        rel = (a - b).abs().max() / a.abs().max().clamp_min(1e-12)
        assert rel <= 1e-3, f"{k}: relative error {rel}"


def test_backend_arguments() -> None:
    scene = raster_scene(20, 16, 16, seed=2, dtype=torch.float64)
    with pytest.raises(ValueError, match="backend: expected one of cpu, wgpu, auto"):
        render(scene, backend="cuda")
    assert raster.resolve_backend("cpu") == "cpu"
    assert raster.resolve_backend("auto") in ("cpu", "wgpu")
    _wgpu_or_skip()
    with pytest.raises(ValueError, match="float32 only"):
        render(scene, backend="wgpu")
