"""Property tests of the torch op on edge cases: zero, tiny and huge scales; Gaussians behind, on
or just in front of the camera plane; opacity 0 and 1; coincident means; extreme anisotropy;
zero and huge quaternions; 1x1, 1xN, Nx1 and 4096x4096 images. No exception, every output and
gradient finite, alpha in [0, 1], the background wherever alpha == 0. NaN/inf inputs not
covered by test_raster_op.py raise a ValueError naming the argument."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.scenes import raster_scene
from sync4d import raster

F32_MAX = float(np.finfo(np.float32).max)
NEAR = float(np.float32(0.01))  # z == near is then exact for float32 means too
JUST_IN_FRONT = float(np.nextafter(np.float32(NEAR), np.float32(1.0)))
GAUSSIAN_ARGS = ("means", "quats", "scales", "opacities", "features")

PROPERTY_SETTINGS = settings(
    max_examples=40,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

# ---------------------------------------------------------------------------------------------
# Strategies (one Gaussian at a time; its mean in camera space).
# ---------------------------------------------------------------------------------------------

TYPICAL_SCALE = st.floats(-4.5, -0.7).map(math.exp)
AXIS_SCALE = st.one_of(
    TYPICAL_SCALE,
    TYPICAL_SCALE,
    st.just(0.0),
    st.sampled_from([1e-30, 1e-6, 1e3, 1e30, F32_MAX]),
    st.floats(-38.0, 38.0).map(lambda e: 10.0**e),  # the whole float32 range
)
SCALES = st.one_of(
    st.tuples(AXIS_SCALE, AXIS_SCALE, AXIS_SCALE),
    AXIS_SCALE.map(lambda s: (s, s, s)),
    st.permutations([1e-6, 1e3, 1e3]).map(tuple),  # disc
    st.permutations([1e-6, 1e-6, 1e3]).map(tuple),  # needle
)
UNIT = st.floats(-1.0, 1.0)
QUATS = st.one_of(
    st.tuples(UNIT, UNIT, UNIT, UNIT),
    st.just((1.0, 0.0, 0.0, 0.0)),
    st.just((0.0, 0.0, 0.0, 0.0)),
    st.floats(0.0, 6.3).map(lambda t: (math.cos(t / 2), 0.0, 0.0, math.sin(t / 2))),
    st.tuples(UNIT, UNIT, UNIT, UNIT).map(lambda q: tuple(v * 1e30 for v in q)),
    st.just((F32_MAX, 1.0, -F32_MAX, 1e-30)),
    st.tuples(UNIT, UNIT, UNIT, UNIT).map(lambda q: tuple(v * 1e-30 for v in q)),
)
OPACITIES = st.one_of(
    st.floats(0.0, 1.0), st.just(0.0), st.just(1.0), st.sampled_from([1e-30, 1.0 / 255.0])
)
IN_VIEW = st.tuples(UNIT, UNIT, st.floats(0.3, 6.0)).map(
    lambda p: (0.6 * p[0] * p[2], 0.6 * p[1] * p[2], p[2])
)
MEANS_CAM = st.one_of(
    IN_VIEW,
    IN_VIEW,
    st.tuples(UNIT, UNIT, st.sampled_from([0.0, -1e-30, -1e-6, -1e-3, -2.0, -1e30])),
    st.tuples(UNIT, UNIT).map(lambda p: (p[0] * NEAR, p[1] * NEAR, NEAR)),
    st.tuples(UNIT, UNIT).map(lambda p: (p[0] * NEAR, p[1] * NEAR, JUST_IN_FRONT)),
    st.tuples(UNIT, UNIT, st.sampled_from([1e3, 1e6, 1e10, 1e20, 1e30, 1e38])).map(
        lambda p: (0.6 * p[0] * p[2], 0.6 * p[1] * p[2], p[2])
    ),
    st.tuples(st.sampled_from([1e30, -1e30, F32_MAX, 1e6]), st.floats(0.3, 3.0)).map(
        lambda p: (p[0], 0.1, p[1])
    ),
)
GAUSSIAN = st.tuples(MEANS_CAM, QUATS, SCALES, OPACITIES)
SIZES = st.one_of(
    st.sampled_from([(1, 1), (1, 64), (64, 1), (300, 1), (1, 300), (1, 17), (16, 16)]),
    st.tuples(st.integers(1, 48), st.integers(1, 48)),
)


def _rotation(seed: int) -> np.ndarray:
    """A rotation by up to 0.3 rad about a random axis."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    th = rng.uniform(-0.3, 0.3)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(th) * k + (1 - math.cos(th)) * k @ k


@st.composite
def edge_scenes(draw, max_n: int = 16) -> dict:
    gs = draw(st.lists(GAUSSIAN, max_size=max_n))
    for src, dst, whole in draw(
        st.lists(st.tuples(st.integers(0, 999), st.integers(0, 999), st.booleans()), max_size=3)
    ):
        if gs:  # coincident means, or whole duplicated Gaussians
            s, d = src % len(gs), dst % len(gs)
            gs[d] = gs[s] if whole else (gs[s][0], *gs[d][1:])
    width, height = draw(SIZES)
    channels = draw(st.integers(1, 5))
    seed = draw(st.integers(0, 2**32 - 1))
    viewmat = np.eye(4)
    if draw(st.booleans()):
        viewmat[:3, :3] = _rotation(seed)
        viewmat[:3, 3] = [0.1, -0.05, 4.0]
    rot, t = viewmat[:3, :3], viewmat[:3, 3]
    f = draw(st.sampled_from([0.9, 0.9, 0.9, 1e-3, 1e3])) * max(width, height)
    rng = np.random.default_rng(seed)
    n = len(gs)
    means_cam = np.array([g[0] for g in gs], dtype=np.float64).reshape(n, 3)

    def f32(a, *shape: int) -> torch.Tensor:
        return torch.tensor(np.asarray(a, dtype=np.float64).reshape(shape), dtype=torch.float32)

    return {
        "means": f32((means_cam - t) @ rot, n, 3),  # world = R^T (p_cam - t), row-wise
        "quats": f32([g[1] for g in gs], n, 4),
        "scales": f32([g[2] for g in gs], n, 3),
        "opacities": f32([g[3] for g in gs], n),
        "features": f32(rng.uniform(-1.0, 2.0, size=(n, channels)), n, channels),
        "background": torch.tensor(rng.uniform(0.0, 1.0, size=channels), dtype=torch.float32),
        "viewmat": torch.tensor(viewmat),
        "K": torch.tensor([[f, 0.0, 0.52 * width], [0.0, 1.05 * f, 0.47 * height], [0, 0, 1.0]]),
        "width": width,
        "height": height,
        "near": NEAR,
        "far": draw(st.sampled_from([1e10, 1e10, 1e12])),
        "eps2d": draw(st.sampled_from([0.3, 0.3, 0.0, 1e-4])),
        "antialiased": draw(st.booleans()),
        "alpha_max": draw(st.sampled_from([0.99, 0.999, 0.5, 1.0 / 255.0])),
    }


# ---------------------------------------------------------------------------------------------
# Checks.
# ---------------------------------------------------------------------------------------------

OPTIONS = ("background", "near", "far", "eps2d", "antialiased", "alpha_max")


def render(scene: dict, **kw) -> raster.RasterOutput:
    opts = {k: scene[k] for k in OPTIONS if k in scene}
    opts.update(kw)
    return raster.rasterize(
        *(scene[k] for k in GAUSSIAN_ARGS),
        scene["viewmat"],
        scene["K"],
        scene["width"],
        scene["height"],
        **opts,
    )


def check_output(out: raster.RasterOutput, scene: dict) -> None:
    h, w, c = scene["height"], scene["width"], scene["features"].shape[1]
    assert out.features.shape == (h, w, c) and out.alpha.shape == out.depth.shape == (h, w, 1)
    for name in ("features", "alpha", "depth", "means2d"):
        t = getattr(out, name)
        assert torch.isfinite(t).all(), f"{name} not finite"
    assert (out.radii >= 0).all()
    alpha = out.alpha[..., 0]
    assert ((alpha >= 0) & (alpha <= 1)).all(), "alpha outside [0, 1]"
    assert (out.depth >= 0).all()
    empty = alpha == 0
    bg = scene.get("background")
    bg = torch.zeros(c) if bg is None else bg
    assert torch.equal(out.features[empty], bg.expand(int(empty.sum()), c)), "not the background"
    assert (out.depth[empty] == 0).all()
    if out.counters["visible"] == 0 or (scene["opacities"] == 0).all():
        assert empty.all(), "alpha without a visible splat"


def check_projection(scene: dict) -> None:
    """Finite projection; conics are inverses of a covariance dilated by eps2d, so their
    diagonal is >= 0 and no entry exceeds 1 / eps2d (a long needle once gave ~4e37)."""
    opts = {k: scene[k] for k in ("near", "far", "eps2d", "antialiased") if k in scene}
    p = raster.project_gaussians(
        *(scene[k] for k in GAUSSIAN_ARGS[:4]),
        scene["viewmat"],
        scene["K"],
        scene["width"],
        scene["height"],
        **opts,
    )
    for name in ("means2d", "conics", "depths", "opacities"):
        assert torch.isfinite(getattr(p, name)).all(), f"projected {name} not finite"
    conics = p.conics.double()
    assert (conics[:, 0] >= 0).all() and (conics[:, 2] >= 0).all()
    eps2d = scene.get("eps2d", 0.3)
    if eps2d > 0:
        assert (conics.abs() <= (1 + 1e-4) / eps2d).all(), f"conic above 1 / eps2d = {1 / eps2d}"


def check_backward(scene: dict) -> None:
    """loss = features.sum() + alpha.sum() + depth.sum(); every input gradient finite."""
    check_projection(scene)
    leaves = {k: scene[k].detach().clone().requires_grad_(True) for k in GAUSSIAN_ARGS}
    out = render(dict(scene, **leaves))
    check_output(out, scene)
    loss = out.features.sum() + out.alpha.sum() + out.depth.sum()
    loss.backward()
    for k, v in leaves.items():
        assert v.grad is not None and torch.isfinite(v.grad).all(), f"grad {k} not finite"
    # Gaussians at or behind the near plane get no gradient (the camera here is a rigid map,
    # so compare in camera space).
    vm = scene["viewmat"].double()
    z = scene["means"].double() @ vm[2, :3] + vm[2, 3]
    behind = z <= NEAR * (1 - 1e-6)
    for k in GAUSSIAN_ARGS[:4]:
        assert (leaves[k].grad[behind] == 0).all(), f"grad {k} for a Gaussian behind the camera"


# ---------------------------------------------------------------------------------------------
# Properties.
# ---------------------------------------------------------------------------------------------


@PROPERTY_SETTINGS
@given(scene=edge_scenes())
def test_edge_scenes_render_finite_with_finite_gradients(scene: dict) -> None:
    check_backward(scene)


@settings(max_examples=15, deadline=None, database=None)
@given(scene=edge_scenes(max_n=8), tall=st.booleans(), length=st.sampled_from([1, 2, 300]))
def test_one_pixel_strips(scene: dict, tall: bool, length: int) -> None:
    """1x1, 1x2, 2x1, 1x300 and 300x1 images: the clamped frustum and tile edges."""
    w, h = (1, length) if tall else (length, 1)
    s = dict(scene, width=w, height=h)
    f = float(scene["K"][0, 0]) / max(scene["width"], scene["height"]) * max(w, h)
    s["K"] = torch.tensor([[f, 0.0, 0.52 * w], [0.0, 1.05 * f, 0.47 * h], [0.0, 0.0, 1.0]])
    check_backward(s)


def test_one_by_one_image_with_edge_cases() -> None:
    """A 1x1 image under a stack of coincident opaque Gaussians plus edge cases."""
    means = torch.tensor(
        [[0.0, 0.0, 2.0]] * 50
        + [[0.0, 0.0, NEAR], [0.0, 0.0, JUST_IN_FRONT], [0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
        + [[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.1, 0.0, 1e20]]
    )
    n = means.shape[0]
    scales = torch.full((n, 3), 0.3)
    scales[50:54] = 0.05
    scales[54] = torch.tensor([0.0, 0.0, 0.0])
    scales[55] = torch.tensor([1e30, 1e-30, F32_MAX])
    opacities = torch.ones(n)
    opacities[55] = 0.0
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    quats[54] = 0.0
    scene = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "features": torch.rand(n, 3, generator=torch.Generator().manual_seed(0)),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]]),
        "width": 1,
        "height": 1,
        "near": NEAR,
        "background": torch.tensor([0.2, 0.4, 0.6]),
    }
    check_backward(scene)
    out = render(scene)
    assert 0.99 - 1e-6 <= float(out.alpha) <= 1.0


def test_4096_square_render_is_finite() -> None:
    """One 4096x4096 render of a handful of Gaussians (one channel, no autograd: ~0.5 GB)."""
    w = h = 4096
    f = 0.9 * w
    means = torch.tensor(
        [[0.0, 0.0, 3.0], [0.0, 0.0, 3.0], [0.3, -0.2, 2.0], [-0.5, 0.4, 4.0], [0.1, 0.1, 0.0]]
    )
    scales = torch.tensor(
        [[0.2, 0.1, 0.05], [0.2, 0.1, 0.05], [0.0, 0.0, 0.0], [1e30, 1e30, 1e30], [0.1] * 3]
    )
    scene = {
        "means": means,
        "quats": torch.tensor([[0.9, 0.1, -0.2, 0.3]]).repeat(5, 1),
        "scales": scales,
        "opacities": torch.tensor([0.8, 1.0, 1.0, 0.5, 1.0]),
        "features": torch.tensor([[0.2], [0.9], [0.5], [0.1], [0.7]]),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]]),
        "width": w,
        "height": h,
        "background": torch.tensor([0.25]),
    }
    with torch.no_grad():
        out = render(scene)
    check_output(out, scene)
    assert out.counters["visible"] == 4  # all but the one on the camera plane


def test_long_diagonal_needle_is_culled_not_nan() -> None:
    """Regression: a needle so long that float64 loses its width (its conic came out ~4e37 and
    indefinite, and its means2d gradient NaN) now gets no projection; shorter needles and a
    Gaussian enclosing the camera are still drawn."""
    scene = {
        "means": torch.tensor([[-0.249, 0.0, 0.657], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]]),
        "quats": torch.tensor([[0.453, 0.562, 0.0, 0.0], [0.9, 0.1, -0.2, 0.3], [1.0, 0, 0, 0]]),
        "scales": torch.tensor([[0.5, 1.0, 1.49e11], [0.0, 0.0, 40.0], [1e30, 1e30, 1e30]]),
        "opacities": torch.tensor([1.0, 1.0, 0.5]),
        "features": torch.rand(3, 1, generator=torch.Generator().manual_seed(0)),
        "viewmat": torch.eye(4),
        "K": torch.tensor([[270.0, 0.0, 156.0], [0.0, 283.5, 0.47], [0.0, 0.0, 1.0]]),
        "width": 300,
        "height": 1,
    }
    check_backward(scene)
    out = render(scene)
    assert out.radii[0].tolist() == [0, 0]
    assert (out.radii[1:] > 0).all()


# ---------------------------------------------------------------------------------------------
# NaN/inf rejection (test_raster_op.py covers NaN and +inf in the Gaussians and a NaN viewmat).
# ---------------------------------------------------------------------------------------------

BAD = [float("nan"), float("inf"), float("-inf")]


@pytest.mark.parametrize("arg", GAUSSIAN_ARGS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_negative_infinity_in_gaussians_is_rejected(arg: str, dtype: torch.dtype) -> None:
    s = raster_scene(6, 20, 16, dtype=dtype)
    t = s[arg].clone()
    t.view(-1)[1] = float("-inf")
    with pytest.raises(ValueError, match=f"^{arg}: "):
        render(dict(s, **{arg: t}))


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("entry", [(0, 0), (1, 1), (0, 2), (1, 2)])
def test_non_finite_intrinsics_are_rejected(bad: float, entry: tuple) -> None:
    s = raster_scene(6, 20, 16)
    k = s["K"].clone()
    k[entry] = bad
    with pytest.raises(ValueError, match="^K: "):
        render(dict(s, K=k))


@pytest.mark.parametrize("bad", BAD)
def test_non_finite_viewmat_translation_and_background_are_rejected(bad: float) -> None:
    s = raster_scene(6, 20, 16)
    vm = torch.eye(4, dtype=torch.float64)
    vm[2, 3] = bad
    with pytest.raises(ValueError, match="^viewmat: "):
        render(dict(s, viewmat=vm))
    bg = torch.tensor([0.1, bad, 0.3])
    with pytest.raises(ValueError, match="^background: "):
        render(s, background=bg)


# far = +inf is a valid setting (no far plane), so it is not among the bad cases.
NON_FINITE_SETTINGS = [
    (name, bad)
    for name in ("near", "far", "eps2d", "alpha_max")
    for bad in BAD
    if not (name == "far" and bad == float("inf"))
]


@pytest.mark.parametrize("name,bad", NON_FINITE_SETTINGS)
def test_non_finite_settings_are_rejected(name: str, bad: float) -> None:
    s = raster_scene(6, 20, 16)
    with pytest.raises(ValueError, match=f"^{name}: "):
        render(s, **{name: bad})


SPLAT_ARGS = ("means2d", "conics", "depths", "opacities", "features", "background")


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("arg", SPLAT_ARGS)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_finite_splats_are_rejected(bad: float, arg: str, dtype: torch.dtype) -> None:
    s = raster_scene(6, 20, 16, dtype=dtype)
    p = raster.project_gaussians(*(s[k] for k in GAUSSIAN_ARGS[:4]), s["viewmat"], s["K"], 20, 16)
    args = {
        "means2d": p.means2d,
        "conics": p.conics,
        "depths": p.depths,
        "opacities": p.opacities,
        "features": s["features"],
        "background": torch.full((3,), 0.5, dtype=dtype),
    }
    t = args[arg].clone()
    t.view(-1)[1] = bad
    args[arg] = t
    bg = args.pop("background")
    with pytest.raises(ValueError, match=f"^{arg}: "):
        raster.rasterize_to_pixels(
            args["means2d"], args["conics"], args["depths"], args["opacities"], p.radii,
            args["features"], 20, 16, background=bg,
        )  # fmt: skip


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("which", [0, 1, 2])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_finite_upstream_gradients_are_rejected(
    bad: float, which: int, dtype: torch.dtype
) -> None:
    """A NaN/inf gradient reaching the compositor's backward names its output, on both paths."""
    s = raster_scene(6, 20, 16, dtype=dtype)
    p = raster.project_gaussians(*(s[k] for k in GAUSSIAN_ARGS[:4]), s["viewmat"], s["K"], 20, 16)
    feats = s["features"].clone().requires_grad_(True)
    outs = raster.rasterize_to_pixels(
        p.means2d, p.conics, p.depths, p.opacities, p.radii, feats, 20, 16
    )
    grads = [torch.ones_like(o) for o in outs]
    grads[which].view(-1)[5] = bad
    name = ("v_features", "v_alpha", "v_depth")[which]
    with pytest.raises(ValueError, match=f"^{name}: "):
        torch.autograd.grad(outs, feats, grad_outputs=grads)


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("arg", ["dirs", "coeffs", "v_out"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_finite_sh_inputs_are_rejected(bad: float, arg: str, dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    dirs = torch.randn(4, 3, generator=g, dtype=dtype)
    coeffs = torch.randn(4, 9, 3, generator=g, dtype=dtype, requires_grad=True)
    v = torch.ones(4, 3, dtype=dtype)
    {"dirs": dirs, "coeffs": coeffs.data, "v_out": v}[arg].view(-1)[2] = bad
    with pytest.raises(ValueError, match=f"^{arg}: "):
        out = raster.spherical_harmonics(2, dirs, coeffs)
        torch.autograd.grad(out, coeffs, grad_outputs=v)


@settings(max_examples=25, deadline=None, database=None)
@given(
    degree=st.integers(0, 3),
    dirs=st.lists(
        st.one_of(
            st.tuples(UNIT, UNIT, UNIT),
            st.just((0.0, 0.0, 0.0)),
            st.tuples(UNIT, UNIT, UNIT).map(lambda d: tuple(v * 1e-30 for v in d)),
            st.tuples(UNIT, UNIT, UNIT).map(lambda d: tuple(v * 1e30 for v in d)),
            st.just((F32_MAX, -F32_MAX, F32_MAX)),
        ),
        max_size=6,
    ),
)
def test_sh_at_zero_tiny_and_huge_directions_is_finite(degree: int, dirs: list) -> None:
    n = len(dirs)
    d = torch.tensor(dirs, dtype=torch.float32).reshape(n, 3).requires_grad_(True)
    coeffs = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(n)).requires_grad_(True)
    out = raster.sh_features(torch.zeros(n, 3), coeffs, torch.eye(4), degree)
    out2 = raster.spherical_harmonics(degree, d, coeffs)
    assert torch.isfinite(out).all() and torch.isfinite(out2).all()
    (out.sum() + out2.sum()).backward()
    assert torch.isfinite(d.grad).all() and torch.isfinite(coeffs.grad).all()
