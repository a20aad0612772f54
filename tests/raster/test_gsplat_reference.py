"""Checks of the gsplat CPU reference harness (``sync4d.reference.gsplat``).

The harness runs gsplat 1.5.3's pure-torch rasterizer on the CPU by substituting its CUDA-only
pieces. These tests pin the substitutes to an independent float64 per-pixel loop
(``brute_force_composite``) and ``isect_tiles_fast`` to gsplat's own ``_isect_tiles``, so the
parity tests against sync4d (tests/raster/test_parity_gsplat.py) compare against gsplat itself.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.reference

gsplat = pytest.importorskip("gsplat")

from gsplat.cuda import _torch_impl  # noqa: E402

from sync4d.reference import gsplat as gr  # noqa: E402

SMALL = dict(width=48, height=40)


def harness_scene(seed: int, n: int = 150, **kw) -> gr.Scene:
    """50-200 Gaussians on a 48x40 image: overlapping, some opaque (opacity 1), some culled."""
    args = dict(
        n=n,
        max_sigma_px=6.0,
        full_opacity_fraction=0.15,
        cluster_fraction=0.4,
        n_frustum_edge=4,
        n_culled=4,
    )
    args.update(SMALL)
    args.update(kw)
    return gr.make_random_scene(seed, **args)


def render(scene: gr.Scene, dtype=torch.float64, grad=False, **kw) -> gr.GsplatRender:
    s = scene.to(dtype, requires_grad=grad)
    return gr.gsplat_render_full(
        s.means,
        s.quats,
        s.scales,
        s.opacities,
        s.colors,
        s.viewmat,
        s.K,
        s.width,
        s.height,
        background=s.background,
        **kw,
    )


def brute(r: gr.GsplatRender, colors, background=None, tile_size=16, info=False):
    return gr.brute_force_composite(
        r.means2d,
        r.conics,
        r.opacities,
        colors,
        r.radii,
        r.width,
        r.height,
        tile_size=tile_size,
        background=background,
        depths=r.depths,
        return_info=info,
    )


# ------------------------------------------------------------------------------------------
# isect_tiles_fast == gsplat _isect_tiles
# ------------------------------------------------------------------------------------------


def random_isect_inputs(seed: int, n_images: int, n: int, dtype: torch.dtype):
    gen = torch.Generator().manual_seed(seed)
    width, height = 70, 45
    means2d = torch.rand(n_images, n, 2, generator=gen, dtype=torch.float64)
    means2d = means2d * torch.tensor([1.6 * width, 1.6 * height]) - torch.tensor(
        [0.3 * width, 0.3 * height]
    )
    radii = torch.randint(0, 30, (n_images, n, 2), generator=gen, dtype=torch.int32)
    radii[torch.rand(n_images, n, generator=gen) < 0.1] = 0  # culled
    radii[torch.rand(n_images, n, generator=gen) < 0.05, 0] = 0  # one axis zero
    # Distinct float32 depths (ties would make gsplat's unstable sort order arbitrary).
    depths = (torch.randperm(n_images * n, generator=gen).reshape(n_images, n) + 1.0) * 0.37
    return means2d.to(dtype), radii, depths.to(dtype), width, height


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("n_images", [1, 3])
@pytest.mark.parametrize("tile_size", [16, 8])
@pytest.mark.parametrize("sort", [True, False])
def test_isect_tiles_fast_matches_gsplat(dtype, n_images, tile_size, sort):
    means2d, radii, depths, width, height = random_isect_inputs(
        7 + n_images + tile_size, n_images, 120, dtype
    )
    tile_w = -(-width // tile_size)
    tile_h = -(-height // tile_size)
    ref = _torch_impl._isect_tiles(means2d, radii, depths, tile_size, tile_w, tile_h, sort=sort)
    got = gr.isect_tiles_fast(means2d, radii, depths, tile_size, tile_w, tile_h, sort=sort)
    for name, a, b in zip(("tiles_per_gauss", "isect_ids", "flatten_ids"), got, ref, strict=True):
        assert a.dtype == b.dtype, name
        assert a.shape == b.shape, name
        assert torch.equal(a, b), name
    assert int(got[0].sum()) > 0
    # The offsets built from them are gsplat's too.
    offs = _torch_impl._isect_offset_encode(got[1], n_images, tile_w, tile_h)
    assert torch.equal(offs, _torch_impl._isect_offset_encode(ref[1], n_images, tile_w, tile_h))


def test_isect_tiles_fast_on_projected_scene():
    r = render(harness_scene(3))
    tw, th = 3, 3
    args = (r.means2d[None].detach(), r.radii[None], r.depths[None].detach(), 16, tw, th)
    for a, b in zip(gr.isect_tiles_fast(*args), _torch_impl._isect_tiles(*args), strict=True):
        assert torch.equal(a, b)


def test_isect_tiles_fast_empty():
    means2d = torch.zeros(1, 5, 2)
    radii = torch.zeros(1, 5, 2, dtype=torch.int32)
    depths = torch.ones(1, 5)
    tpg, ids, fids = gr.isect_tiles_fast(means2d, radii, depths, 16, 2, 2)
    assert tpg.shape == (1, 5) and int(tpg.sum()) == 0
    assert ids.numel() == 0 and fids.numel() == 0


# ------------------------------------------------------------------------------------------
# rasterize_to_indices_in_range / nerfacc substitutes vs the brute-force loop
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_indices_match_brute_force_exactly(seed):
    """Float64: the (Gaussian, pixel) pairs, in order, equal the brute-force loop's."""
    scene = harness_scene(seed, n=(120, 150, 200)[seed])
    r = render(scene)
    _, _, info = brute(r, scene.colors, info=True)
    assert info["terminated"].sum() >= 50, "scene must exercise termination"
    trans = torch.ones(1, r.height, r.width, dtype=torch.float64)
    g, p, i = gr.rasterize_to_indices_in_range(
        0,
        10**10,
        trans,
        r.means2d[None].detach(),
        r.conics[None].detach(),
        r.opacities[None].detach(),
        r.width,
        r.height,
        16,
        r.isect_offsets[None],
        r.flatten_ids,
    )
    assert g.dtype == p.dtype == i.dtype == torch.int64
    assert torch.all(i == 0)
    np.testing.assert_array_equal(p.numpy(), info["pixel_ids"])
    np.testing.assert_array_equal(g.numpy(), info["gaussian_ids"])


def kernel_loop(rng, trans, r, ts, offs, fids):
    """Direct loop over gsplat's rasterize_to_indices kernel semantics for one batch range:
    per tile, per pixel, entries [lo, hi) of the tile list, starting from ``trans``."""
    start, end = rng
    block = ts * ts
    bounds = offs.flatten().tolist() + [len(fids)]
    m = r.means2d.detach().numpy()
    c = r.conics.detach().numpy()
    o = r.opacities.detach().numpy()
    t_in = trans.reshape(-1).numpy()
    tw = offs.shape[-1]
    pairs = []
    for tile in range(len(bounds) - 1):
        lo = bounds[tile] + block * start
        hi = min(bounds[tile + 1], bounds[tile] + block * end)
        ty, tx = divmod(tile, tw)
        for y in range(ty * ts, min(r.height, (ty + 1) * ts)):
            for x in range(tx * ts, min(r.width, (tx + 1) * ts)):
                t = t_in[y * r.width + x]
                for k in range(lo, hi):
                    g = int(fids[k])
                    dx, dy = m[g, 0] - (x + 0.5), m[g, 1] - (y + 0.5)
                    sig = 0.5 * (c[g, 0] * dx * dx + c[g, 2] * dy * dy) + c[g, 1] * dx * dy
                    a = min(gr.ALPHA_MAX, o[g] * np.exp(-sig))
                    if sig < 0 or a < gr.ALPHA_THRESHOLD:
                        continue
                    if t * (1 - a) <= gr.TRANSMITTANCE_MIN:
                        break
                    t *= 1 - a
                    pairs.append((y * r.width + x, k, g))
    pairs.sort()  # pixel-major, then list position (front to back)
    return [p for p, _, _ in pairs], [g for _, _, g in pairs]


def test_indices_batch_ranges_match_kernel_loop():
    """Batch ranges [start, end) with carried transmittances (tile_size 4 -> batches of 16,
    many per tile) match a direct loop over the kernel's semantics."""
    scene = harness_scene(5, n=180)
    r = render(scene)
    ts = 4
    tw, th = -(-r.width // ts), -(-r.height // ts)
    _, ids, fids = gr.isect_tiles_fast(
        r.means2d[None].detach(), r.radii[None], r.depths[None].detach(), ts, tw, th
    )
    offs = _torch_impl._isect_offset_encode(ids, 1, tw, th)
    args = (r.means2d[None].detach(), r.conics[None].detach(), r.opacities[None].detach())
    geo = (r.width, r.height, ts, offs, fids)
    bounds = torch.cat([offs.flatten(), torch.tensor([len(fids)])])
    max_batches = -(-int(torch.diff(bounds).max()) // (ts * ts))
    assert max_batches >= 4
    gen = torch.Generator().manual_seed(0)
    trans = torch.ones(1, r.height, r.width, dtype=torch.float64)
    for rng in [(0, 1), (1, 3), (2, max_batches + 5), (max_batches, max_batches + 1)]:
        g, p, i = gr.rasterize_to_indices_in_range(*rng, trans, *args, *geo)
        ref_p, ref_g = kernel_loop(rng, trans, r, ts, offs, fids)
        assert p.tolist() == ref_p and g.tolist() == ref_g and torch.all(i == 0)
        # Next range starts from some partially transparent pixels.
        trans = torch.rand(1, r.height, r.width, generator=gen, dtype=torch.float64) * 0.5
    assert len(ref_p) == 0  # range past every list


@pytest.mark.parametrize(
    "kind", ["plain", "background", "antialiased", "tile4_batch1", "slow_isect"]
)
def test_gsplat_pipeline_matches_brute_force(kind):
    """gsplat's ``_rasterize_to_pixels`` + ``accumulate`` with the CPU substitutes equals the
    brute-force float64 loop to rounding."""
    scene = harness_scene(10 + len(kind), background=(kind == "background"))
    kw = dict(antialiased=(kind == "antialiased"), fast_isect=(kind != "slow_isect"))
    r = render(scene, **kw)
    done = None
    if kind == "tile4_batch1":  # many compositing rounds carrying T between them
        image, alpha, _ = gr.gsplat_rasterize(
            r.means2d,
            r.conics,
            r.opacities,
            scene.colors,
            r.depths,
            r.radii,
            r.width,
            r.height,
            tile_size=4,
            batch_per_iter=1,
        )
        ref_img, ref_alpha, info = brute(r, scene.colors, tile_size=4, info=True)
        # gsplat's multi-round torch path does not carry "pixel done" between rounds (only T),
        # so terminated pixels may take more Gaussians in later rounds; compare the others.
        done = info["terminated"]
    else:
        image, alpha = r.image, r.alpha
        ref_img, ref_alpha, info = brute(r, scene.colors, scene.background, info=True)
    assert info["terminated"].sum() > 0
    assert image.dtype == torch.float64
    keep = np.ones((r.height, r.width), dtype=bool) if done is None else ~done
    np.testing.assert_allclose(image.detach().numpy()[keep], ref_img[keep], rtol=0, atol=1e-12)
    np.testing.assert_allclose(alpha.detach().numpy()[keep], ref_alpha[keep], rtol=0, atol=1e-12)


def test_gsplat_pipeline_float32_close_to_brute_force():
    """Float32 run: equal to the float64 loop up to float32 rounding, except on pixels whose
    result hinges on a threshold decision (flagged by ``ambiguous_pixels``)."""
    scene = harness_scene(21, n=200)
    r32 = render(scene, torch.float32)
    r64 = render(scene)
    mask, _ = gr.ambiguous_pixels(r64)
    assert torch.equal(r32.radii, r64.radii)
    ref_img, ref_alpha = brute(r32, scene.colors.float())
    ok = ~mask.numpy()
    assert ok.mean() > 0.95
    err_img = np.abs(r32.image.detach().double().numpy() - ref_img)[ok].max()
    err_alpha = np.abs(r32.alpha.detach().double().numpy() - ref_alpha)[ok].max()
    assert err_img < 1e-5 and err_alpha < 1e-5, (err_img, err_alpha)


def test_depth_channel():
    scene = harness_scene(4)
    r = render(scene, render_depth=True)
    ref_depth, _ = brute(r, r.depths[:, None])
    np.testing.assert_allclose(r.depth_accum.detach().numpy(), ref_depth, rtol=0, atol=1e-12)


def test_gradcheck_tiny_scene():
    """The substituted pipeline is differentiable end to end (float64 gradcheck)."""
    scene = harness_scene(30, n=10, width=24, height=20, n_frustum_edge=0, n_culled=1)
    s = scene.to(torch.float64, requires_grad=True)

    def fn(means, quats, scales, opacities, colors):
        image, alpha, _ = gr.gsplat_render(
            means, quats, scales, opacities, colors, s.viewmat, s.K, s.width, s.height
        )
        return image, alpha

    inputs = (s.means, s.quats, s.scales, s.opacities, s.colors)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-7, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gsplat_render_returns_means2d_with_grad():
    scene = harness_scene(8)
    s = scene.to(torch.float32, requires_grad=True)
    image, alpha, means2d = gr.gsplat_render(
        s.means, s.quats, s.scales, s.opacities, s.colors, s.viewmat, s.K, s.width, s.height
    )
    assert image.shape == (s.height, s.width, 3) and alpha.shape == (s.height, s.width, 1)
    assert means2d.shape == (s.means.shape[0], 2)
    (image.sum() + alpha.sum()).backward()
    assert means2d.grad is not None and means2d.grad.abs().sum() > 0
    for t in (s.means, s.quats, s.scales, s.opacities, s.colors):
        assert t.grad is not None and torch.isfinite(t.grad).all() and t.grad.abs().sum() > 0


# ------------------------------------------------------------------------------------------
# nerfacc substitutes on their own
# ------------------------------------------------------------------------------------------


def packed_rays(seed: int, n_rays: int = 40):
    gen = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 9, (n_rays,), generator=gen)
    counts[3] = 0
    ray_indices = torch.repeat_interleave(torch.arange(n_rays), counts)
    alphas = torch.rand(ray_indices.numel(), generator=gen, dtype=torch.float64) * 0.999
    values = torch.randn(ray_indices.numel(), 3, generator=gen, dtype=torch.float64)
    return alphas, values, ray_indices, counts


def loop_weights(alphas, ray_indices):
    trans = torch.empty_like(alphas)
    t, prev = 1.0, None
    for k, (a, r) in enumerate(zip(alphas.tolist(), ray_indices.tolist(), strict=True)):
        if r != prev:
            t, prev = 1.0, r
        trans[k] = t
        t *= 1.0 - a
    return trans * alphas, trans


@pytest.mark.parametrize("budget", [None, 8])
def test_render_weight_from_alpha_packed(budget, monkeypatch):
    if budget is not None:  # force the blocked scan path
        monkeypatch.setattr(gr, "_SCAN_BUDGET", budget)
    alphas, _, ray_indices, counts = packed_rays(0)
    w, t = gr.render_weight_from_alpha(alphas, ray_indices=ray_indices, n_rays=len(counts))
    w_ref, t_ref = loop_weights(alphas, ray_indices)
    torch.testing.assert_close(t, t_ref, rtol=1e-14, atol=0)
    torch.testing.assert_close(w, w_ref, rtol=1e-14, atol=0)
    starts = torch.cumsum(counts, 0) - counts
    packed_info = torch.stack([starts, counts], -1).int()
    w2, t2 = gr.render_weight_from_alpha(alphas, packed_info=packed_info)
    torch.testing.assert_close(w2, w, rtol=0, atol=0)
    w3, t3 = gr.render_weight_from_alpha(alphas, ray_indices=ray_indices, prefix_trans=t)
    torch.testing.assert_close(t3, t * t, rtol=0, atol=0)


def test_render_weight_from_alpha_dense_matches_packed():
    gen = torch.Generator().manual_seed(1)
    alphas = torch.rand(5, 7, generator=gen, dtype=torch.float64) * 0.99
    w, t = gr.render_weight_from_alpha(alphas)
    ray_indices = torch.arange(5).repeat_interleave(7)
    wp, tp = gr.render_weight_from_alpha(alphas.flatten(), ray_indices=ray_indices, n_rays=5)
    torch.testing.assert_close(w.flatten(), wp, rtol=1e-15, atol=0)
    torch.testing.assert_close(t.flatten(), tp, rtol=1e-15, atol=0)


def test_render_weight_from_alpha_rejects_unsorted():
    with pytest.raises(ValueError):
        gr.render_weight_from_alpha(
            torch.tensor([0.1, 0.2, 0.3]), ray_indices=torch.tensor([0, 1, 0]), n_rays=2
        )


def test_nerfacc_substitutes_gradcheck():
    alphas, values, ray_indices, counts = packed_rays(2, n_rays=12)
    n_rays = len(counts)

    def fn(a, v):
        w, t = gr.render_weight_from_alpha(a, ray_indices=ray_indices, n_rays=n_rays)
        out = gr.accumulate_along_rays(w, v, ray_indices=ray_indices, n_rays=n_rays)
        acc = gr.accumulate_along_rays(w, None, ray_indices=ray_indices, n_rays=n_rays)
        return out, acc, t

    a = alphas.clone().requires_grad_(True)
    v = values.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (a, v))


def test_accumulate_along_rays():
    alphas, values, ray_indices, counts = packed_rays(3)
    w, _ = gr.render_weight_from_alpha(alphas, ray_indices=ray_indices, n_rays=len(counts))
    out = gr.accumulate_along_rays(w, values, ray_indices=ray_indices, n_rays=len(counts))
    ref = torch.zeros(len(counts), 3, dtype=torch.float64)
    for k, r in enumerate(ray_indices.tolist()):
        ref[r] += w[k] * values[k]
    torch.testing.assert_close(out, ref, rtol=1e-14, atol=1e-15)
    assert torch.all(out[counts == 0] == 0)
    dense = gr.accumulate_along_rays(w[None, :4], values[None, :4])
    torch.testing.assert_close(dense[0], (w[:4, None] * values[:4]).sum(0))


def test_candidate_blocks_are_chunk_invariant(monkeypatch):
    scene = harness_scene(6, n=200)
    r = render(scene)
    trans = torch.ones(1, r.height, r.width, dtype=torch.float64)
    args = (
        0,
        10**10,
        trans,
        r.means2d[None].detach(),
        r.conics[None].detach(),
        r.opacities[None].detach(),
        r.width,
        r.height,
        16,
        r.isect_offsets[None],
        r.flatten_ids,
    )
    ref = gr.rasterize_to_indices_in_range(*args)
    monkeypatch.setattr(gr, "_PAIR_BUDGET", 300)  # about one tile per block
    monkeypatch.setattr(gr, "_SCAN_BUDGET", 64)
    got = gr.rasterize_to_indices_in_range(*args)
    for a, b in zip(got, ref, strict=True):
        assert torch.equal(a, b)


def test_cpu_substitutes_restores_state():
    from gsplat.cuda import _wrapper

    original = _wrapper.rasterize_to_indices_in_range
    had = "nerfacc" in sys.modules
    before = sys.modules.get("nerfacc")
    with gr.cpu_substitutes():
        assert _wrapper.rasterize_to_indices_in_range is gr.rasterize_to_indices_in_range
        import nerfacc

        assert nerfacc.render_weight_from_alpha is gr.render_weight_from_alpha
        assert nerfacc.accumulate_along_rays is gr.accumulate_along_rays
        with gr.cpu_substitutes():  # nesting
            pass
        assert _wrapper.rasterize_to_indices_in_range is gr.rasterize_to_indices_in_range
    assert _wrapper.rasterize_to_indices_in_range is original
    assert ("nerfacc" in sys.modules) == had and sys.modules.get("nerfacc") is before
    with pytest.raises(RuntimeError), gr.cpu_substitutes():
        raise RuntimeError("boom")
    assert _wrapper.rasterize_to_indices_in_range is original
    assert ("nerfacc" in sys.modules) == had


# ------------------------------------------------------------------------------------------
# Ambiguity mask and scene generator
# ------------------------------------------------------------------------------------------


def test_ambiguous_pixels_flags_threshold_cases():
    """A Gaussian whose alpha sits within rounding of 1/255 at a pixel, and a pair of Gaussians
    whose T (1 - alpha) sits within rounding of 1e-4, are flagged; clear pixels are not."""
    f64 = torch.float64
    means2d = torch.tensor([[20.5, 20.5], [8.5, 8.5], [8.5, 8.5]], dtype=f64)
    conics = torch.tensor([[0.1, 0.0, 0.1], [0.01, 0.0, 0.01], [0.01, 0.0, 0.01]], dtype=f64)
    sigma = 0.5 * 0.1 * 25.0  # pixel (25, 20): dx = 5
    a2 = 0.9  # second pair: T after both = (1 - a1)(1 - a2) = 1e-4 (1 + 1e-7)
    a1 = 1.0 - 1e-4 * (1 + 1e-7) / (1 - a2)
    opac = torch.tensor([np.exp(sigma) / 255.0 * (1 + 1e-7), a1, a2], dtype=f64)
    depths = torch.tensor([1.0, 2.0, 3.0], dtype=f64)
    radii = torch.tensor([[11, 11], [6, 6], [6, 6]], dtype=torch.int32)
    colors = torch.ones(3, 1, dtype=f64)
    r = gr.gsplat_rasterize_full(means2d, conics, opac, colors, depths, radii, 40, 32)
    mask, stats = gr.ambiguous_pixels(r)
    assert mask[20, 25] and mask[20, 15] and mask[25, 20] and mask[15, 20]
    assert mask[8, 8]  # termination boundary at the shared centre
    assert not mask[20, 20] and not mask[30, 35]
    assert stats["alpha_threshold"] >= 4 and stats["termination"] >= 1
    assert mask.sum() < 0.1 * mask.numel()


def test_make_random_scene_properties():
    scene = gr.make_random_scene(0, n=400, width=64, height=48, background=True)
    r = render(scene)
    visible = (r.radii > 0).all(-1)
    assert 0.8 * 400 < int(visible.sum()) < 400
    z = r.depths.detach()[visible].sort().values
    assert float(torch.diff(z).min()) > 1e-3  # no depth near-ties
    # Some visible Gaussians sit beyond gsplat's frustum clamp (|x/z| > lim).
    fx, cx = float(scene.K[0, 0]), float(scene.K[0, 2])
    lim = (scene.width - cx) / fx + 0.15 * scene.width / fx
    u = (r.means2d.detach()[:, 0] - cx) / fx
    assert int((visible & (u > lim)).sum()) > 0
    assert scene.background is not None and scene.background.shape == (3,)
    q = scene.quats.norm(dim=-1)
    assert float(q.min()) < 0.9 and float(q.max()) > 1.1  # unnormalised quaternions
