"""gsplat 1.5.3 as a CPU reference for sync4d's rasterizer.

gsplat ships a pure-PyTorch path (``gsplat.cuda._torch_impl``) whose projection and tiling run
anywhere, but its compositing step ``_rasterize_to_pixels`` calls two things that do not exist
on a CPU-only machine:

* ``gsplat.cuda._wrapper.rasterize_to_indices_in_range`` (a CUDA kernel) to find, per pixel, the
  front-to-back list of Gaussians that are blended, and
* ``nerfacc.render_weight_from_alpha`` / ``nerfacc.accumulate_along_rays`` (CUDA scans) to turn
  those alphas into weights and sum them.

This module provides vectorised torch equivalents of both (:func:`rasterize_to_indices_in_range`,
:func:`render_weight_from_alpha`, :func:`accumulate_along_rays`), a context manager that plugs
them into gsplat (:func:`cpu_substitutes`), a vectorised :func:`isect_tiles_fast` that matches
``_isect_tiles`` exactly, and the end-to-end :func:`gsplat_render`. :func:`brute_force_composite`
is an independent float64 per-pixel loop used to check the substitutes.

gsplat's compositing conventions, as implemented by its CUDA kernels
(``RasterizeToPixels3DGSFwd.cu``, ``RasterizeToIndices3DGS.cu``; ``ALPHA_THRESHOLD`` in
``Common.h``) and mirrored here:

* pixel centre ``(x + 0.5, y + 0.5)``; ``delta = mean2d - centre``;
* ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy`` with conic ``(a, b, c)``;
* ``alpha = min(0.999, opacity * exp(-sigma))``;
* skip the Gaussian when ``sigma < 0`` or ``alpha < 1/255`` (so ``alpha == 1/255`` is blended);
* ``next_T = T (1 - alpha)``; if ``next_T <= 1e-4`` (inclusive) the pixel is done and this
  Gaussian is *not* blended;
* per-tile order: ascending ``isect_id`` = (image, tile, float32 depth bits), ties in Gaussian
  index order (CUDA uses a stable radix sort of ids written in index order).

Where gsplat's CUDA pipeline and its torch reference (followed here and by sync4d) differ:

* CUDA ``fully_fused_projection`` given opacities (as ``gsplat.rasterization`` does) uses an
  opacity-aware extent ``min(3.33, sqrt(2 ln(255 o)))`` for the radii and culls
  ``o < 1/255``; the torch path always uses 3.33. Images agree (the extra pixels have
  ``alpha < 1/255``), radii and tile counts do not.
* CUDA culls ``z < near`` or ``z > far`` (keeps ``z == near``), torch keeps ``near < z < far``;
  CUDA culls ``det(cov2d + eps2d I) <= 0``, torch clamps det to 1e-10 and never culls on it.
* gsplat's torch ``_rasterize_to_pixels`` composites in rounds of ``batch_per_iter`` tile
  batches and carries only the transmittance between rounds, so a pixel that terminated can
  take more Gaussians in a later round; with one round (the default of
  :func:`gsplat_rasterize`) it equals the single-pass CUDA kernel.

Helpers for parity tests live here too: :func:`make_random_scene` and
:func:`ambiguous_pixels` (pixels whose result is ill-conditioned under float rounding).
"""

from __future__ import annotations

import contextlib
import math
import sys
import types
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "ALPHA_MAX",
    "ALPHA_THRESHOLD",
    "TRANSMITTANCE_MIN",
    "TILE_SIZE",
    "GsplatRender",
    "Scene",
    "accumulate_along_rays",
    "ambiguous_pixels",
    "brute_force_composite",
    "cpu_substitutes",
    "gsplat_project",
    "gsplat_rasterize",
    "gsplat_rasterize_full",
    "gsplat_render",
    "gsplat_render_full",
    "isect_tiles_fast",
    "make_random_scene",
    "rasterize_to_indices_in_range",
    "render_weight_from_alpha",
]

#: gsplat's per-Gaussian alpha clamp (hard-coded in its kernels and in ``accumulate``).
ALPHA_MAX: float = 0.999
#: ``ALPHA_THRESHOLD`` in gsplat's ``Common.h``: ``1.f / 255.f``.
ALPHA_THRESHOLD: float = 1.0 / 255.0
#: A pixel is done when ``T * (1 - alpha) <= TRANSMITTANCE_MIN`` (that Gaussian is excluded).
TRANSMITTANCE_MIN: float = 1e-4
#: gsplat's default tile size (pixels per side).
TILE_SIZE: int = 16

# Elements per padded block in the segmented scans (bounds the scratch memory).
_SCAN_BUDGET = 1 << 22
# Candidate (pixel, Gaussian) pairs handled at once when enumerating tiles.
_PAIR_BUDGET = 1 << 22


# --------------------------------------------------------------------------------------------
# Segmented (packed, per-ray) scans
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Segments:
    """Layout of a packed array split into contiguous, non-empty segments."""

    seg: Tensor  # [M] int64, compact segment index of each element
    pos: Tensor  # [M] int64, position of each element inside its segment
    starts: Tensor  # [S] int64, first element of each segment
    lengths: Tensor  # [S] int64, elements per segment

    @staticmethod
    def from_sorted_keys(keys: Tensor) -> _Segments:
        """Segments of equal consecutive values in ``keys`` [M] (must be grouped, e.g. sorted)."""
        m = keys.numel()
        if m == 0:
            empty = torch.zeros(0, dtype=torch.long, device=keys.device)
            return _Segments(empty, empty, empty, empty)
        is_start = torch.ones(m, dtype=torch.bool, device=keys.device)
        is_start[1:] = keys[1:] != keys[:-1]
        starts = torch.nonzero(is_start).flatten()
        seg = torch.cumsum(is_start.long(), 0) - 1
        pos = torch.arange(m, device=keys.device) - starts[seg]
        ends = torch.cat([starts[1:], starts.new_tensor([m])])
        return _Segments(seg, pos, starts, ends - starts)


def _segmented_cumprod(x: Tensor, segs: _Segments, exclusive: bool) -> Tensor:
    """Per-segment cumulative product of the packed ``x`` [M], differentiable.

    Segments are scattered into zero-padded rows (padding 1) and scanned with ``torch.cumprod``
    along the rows, so every product is the plain sequential product of the segment's own
    elements (no global sums, no logs), forward and backward. Rows are processed in blocks of at
    most ``_SCAN_BUDGET`` elements.
    """
    m = x.numel()
    if m == 0:
        return x.clone()
    n_seg = segs.starts.numel()
    max_len = int(segs.lengths.max())
    per_block = max(1, _SCAN_BUDGET // (max_len + 1))
    parts = []
    for s0 in range(0, n_seg, per_block):
        s1 = min(n_seg, s0 + per_block)
        e0 = int(segs.starts[s0])
        e1 = int(segs.starts[s1]) if s1 < n_seg else m
        rows = segs.seg[e0:e1] - s0
        cols = segs.pos[e0:e1] + 1
        width = int(segs.lengths[s0:s1].max()) + 1
        buf = x.new_ones((s1 - s0, width)).index_put((rows, cols), x[e0:e1])
        scan = torch.cumprod(buf, dim=1)
        parts.append(scan[rows, cols - 1] if exclusive else scan[rows, cols])
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _segmented_cumsum_int(x: Tensor, segs: _Segments) -> Tensor:
    """Per-segment inclusive cumulative sum of an integer ``x`` [M] (exact)."""
    if x.numel() == 0:
        return x.clone()
    cs = torch.cumsum(x, 0)
    base = (cs - x)[segs.starts]
    return cs - base[segs.seg]


# --------------------------------------------------------------------------------------------
# nerfacc substitutes
# --------------------------------------------------------------------------------------------


def render_weight_from_alpha(
    alphas: Tensor,
    packed_info: Tensor | None = None,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
    prefix_trans: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """CPU equivalent of ``nerfacc.render_weight_from_alpha``.

    Computes the exclusive transmittance ``trans_i = prod_{j < i on the same ray} (1 - alpha_j)``
    and the weights ``w_i = trans_i * alpha_i``, differentiably.

    Args:
        alphas: packed ``[M]`` (with ``ray_indices`` or ``packed_info``) or dense ``[..., S]``
            (scan along the last axis).
        packed_info: optional ``[n_rays, 2]`` int (start, count) per ray.
        ray_indices: optional ``[M]`` int ray id per sample; samples of one ray must be
            contiguous (nerfacc's requirement; gsplat passes them sorted).
        n_rays: number of rays (accepted for API compatibility).
        prefix_trans: optional transmittance in front of each sample (same shape as ``alphas``),
            multiplied into ``trans``.

    Returns:
        ``(weights, trans)``, both shaped like ``alphas``.
    """
    del n_rays  # implied by ray_indices / packed_info
    if packed_info is not None and ray_indices is None:
        counts = packed_info[:, 1].long()
        ray_indices = torch.repeat_interleave(
            torch.arange(packed_info.shape[0], device=alphas.device), counts
        )
    if ray_indices is not None:
        if alphas.dim() != 1 or ray_indices.shape != alphas.shape:
            raise ValueError("packed mode needs alphas [M] and ray_indices [M]")
        ray_indices = ray_indices.long()
        segs = _Segments.from_sorted_keys(ray_indices)
        if segs.starts.numel() != torch.unique(ray_indices).numel():
            raise ValueError("samples of one ray must be contiguous in ray_indices")
        trans = _segmented_cumprod(1.0 - alphas, segs, exclusive=True)
    else:
        ones = torch.ones_like(alphas[..., :1])
        trans = torch.cat([ones, torch.cumprod(1.0 - alphas, dim=-1)[..., :-1]], dim=-1)
    if prefix_trans is not None:
        trans = trans * prefix_trans
    return trans * alphas, trans


def accumulate_along_rays(
    weights: Tensor,
    values: Tensor | None = None,
    ray_indices: Tensor | None = None,
    n_rays: int | None = None,
) -> Tensor:
    """CPU equivalent of ``nerfacc.accumulate_along_rays``: ``out[r] = sum_{i on r} w_i v_i``.

    Args:
        weights: packed ``[M]`` or dense ``[..., S]``.
        values: ``[M, D]`` / ``[..., S, D]``, or None to accumulate the weights themselves (D=1).
        ray_indices: ``[M]`` ray id per sample (packed mode); needs ``n_rays``.
        n_rays: number of output rays in packed mode.

    Returns:
        ``[n_rays, D]`` (packed) or ``[..., D]`` (dense); differentiable in weights and values.
    """
    src = weights[..., None] if values is None else weights[..., None] * values
    if ray_indices is None:
        return src.sum(dim=-2)
    if n_rays is None:
        raise ValueError("n_rays is required with ray_indices")
    out = torch.zeros((n_rays, src.shape[-1]), dtype=src.dtype, device=src.device)
    return out.index_add(0, ray_indices.long(), src)


# --------------------------------------------------------------------------------------------
# Tile -> pixel candidate enumeration (shared by the indices kernel and the ambiguity mask)
# --------------------------------------------------------------------------------------------


@dataclass
class _Block:
    """Candidate (pixel, Gaussian) pairs of whole tiles, as dense ``[P, K]`` arrays.

    Rows are the ``P = tile_size**2`` pixel slots of a tile (row-major inside the tile); columns
    are the selected entries of the tiles' sorted Gaussian lists, tile after tile, front to back
    within a tile. Pixel slots outside the image have ``inside == False``.
    """

    gid: Tensor  # [K] int64 flat Gaussian id in [images * N]
    pix: Tensor  # [P, K] int64 global pixel id (image * H * W + y * W + x); 0 where outside
    inside: Tensor  # [P, K] bool
    sigma: Tensor  # [P, K] input dtype
    raw_alpha: Tensor  # [P, K] opacity * exp(-sigma), before the clamp


def _iter_blocks(
    range_start: int,
    range_end: int,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
) -> Iterator[_Block]:
    """Yield the candidate pairs of tile batches [range_start, range_end), whole tiles per
    block, at most about ``_PAIR_BUDGET`` pairs per block."""
    tile_h, tile_w = isect_offsets.shape[-2:]
    device = means2d.device
    n_isects = flatten_ids.numel()
    block = tile_size * tile_size

    offsets = isect_offsets.reshape(-1).long()
    ends = torch.cat([offsets[1:], offsets.new_tensor([n_isects])])
    num_batches = (ends - offsets + block - 1) // block
    r_end = int(min(range_end, 1 << 40))
    lo = offsets + block * range_start
    hi = torch.minimum(ends, offsets + block * torch.clamp(num_batches, max=r_end))
    length = torch.clamp(hi - lo, min=0)

    tiles = torch.nonzero(length > 0).flatten()
    if tiles.numel() == 0:
        return
    counts = length[tiles]
    tile_cum = torch.cumsum(counts, 0)
    total = int(tile_cum[-1])
    which = torch.repeat_interleave(torch.arange(tiles.numel(), device=device), counts)
    tile_of = tiles[which]
    k_all = lo[tile_of] + (torch.arange(total, device=device) - (tile_cum - counts)[which])
    per_image = tile_h * tile_w
    img_of = tile_of // per_image
    ty_of = (tile_of % per_image) // tile_w
    tx_of = (tile_of % per_image) % tile_w

    slot = torch.arange(block, device=device)
    ly = (slot // tile_size)[:, None]
    lx = (slot % tile_size)[:, None]
    hw = image_height * image_width
    flat_means = means2d.reshape(-1, 2)
    flat_conics = conics.reshape(-1, 3)
    flat_opac = opacities.reshape(-1)
    fids = flatten_ids.long()
    budget_cols = max(1, _PAIR_BUDGET // block)

    t0 = 0
    while t0 < tiles.numel():
        e0 = int(tile_cum[t0 - 1]) if t0 > 0 else 0
        t1 = int(torch.searchsorted(tile_cum, e0 + budget_cols, right=True))
        t1 = min(max(t1, t0 + 1), tiles.numel())
        e1 = int(tile_cum[t1 - 1])
        g = fids[k_all[e0:e1]]
        x = (tx_of[e0:e1] * tile_size)[None, :] + lx
        y = (ty_of[e0:e1] * tile_size)[None, :] + ly
        inside = (x < image_width) & (y < image_height)
        pix = torch.where(inside, img_of[e0:e1][None, :] * hw + y * image_width + x, 0)
        mean = flat_means[g]
        con = flat_conics[g]
        dx = mean[:, 0][None, :] - (x.to(mean.dtype) + 0.5)
        dy = mean[:, 1][None, :] - (y.to(mean.dtype) + 0.5)
        sigma = 0.5 * (con[:, 0] * dx * dx + con[:, 2] * dy * dy) + con[:, 1] * dx * dy
        raw = flat_opac[g][None, :] * torch.exp(-sigma)
        yield _Block(g, pix, inside, sigma, raw)
        t0 = t1


@dataclass
class _Blended:
    """Outcome of gsplat's per-pixel rules on one :class:`_Block` (all ``[P, K]``)."""

    keep: Tensor  # bool: the pair is blended
    alpha: Tensor  # clamped alpha, input dtype
    next_t: Tensor  # float64 T (1 - alpha) for evaluated pairs (blended + terminating), NaN else
    terminating: Tensor  # bool: the pair that stopped its pixel (not blended)


def _apply_rules(
    blk: _Block, transmittances: Tensor, alpha_max: float, with_next_t: bool = False
) -> _Blended:
    """Skip rule (``sigma < 0`` or ``alpha < 1/255``) and termination (``T (1 - alpha) <= 1e-4``,
    exclusive), evaluated per pixel front to back starting from ``transmittances``.
    ``next_t`` is only filled when ``with_next_t`` (it is empty otherwise)."""
    alpha = torch.clamp_max(blk.raw_alpha, alpha_max)
    valid = blk.inside & (blk.sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
    shape = valid.shape
    keep = torch.zeros(shape, dtype=torch.bool)
    term = torch.zeros(shape, dtype=torch.bool)
    next_t = torch.full(shape if with_next_t else (0,), float("nan"), dtype=torch.float64)
    # Row-major nonzero: pixel slot major, then column; a pixel's pairs are contiguous.
    flat = torch.nonzero(valid.reshape(-1)).flatten()
    if flat.numel() == 0:
        return _Blended(keep, alpha, next_t, term)
    pv = blk.pix.reshape(-1)[flat]
    segs = _Segments.from_sorted_keys(pv)
    t0 = transmittances.reshape(-1)[pv].double()
    tn = t0 * _segmented_cumprod(1.0 - alpha.reshape(-1)[flat].double(), segs, exclusive=False)
    done = (tn <= TRANSMITTANCE_MIN).long()
    n_done = _segmented_cumsum_int(done, segs)  # > 0: this pair or an earlier one ended it
    blended = n_done == 0
    first = (n_done == 1) & (done == 1)
    keep.view(-1)[flat[blended]] = True
    term.view(-1)[flat[first]] = True
    if with_next_t:
        live = blended | first
        next_t.view(-1)[flat[live]] = tn[live]
    return _Blended(keep, alpha, next_t, term)


@torch.no_grad()
def rasterize_to_indices_in_range(
    range_start: int,
    range_end: int,
    transmittances: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """CPU equivalent of ``gsplat.cuda._wrapper.rasterize_to_indices_in_range`` (3DGS).

    For every tile, walks the tile's depth-sorted Gaussian list in batches of
    ``tile_size ** 2``, batches ``[range_start, range_end)`` only, starting from the given
    per-pixel transmittances, and returns the (Gaussian, pixel) pairs that would be blended:
    ``alpha = min(0.999, o exp(-sigma)) >= 1/255`` and ``sigma >= 0``; a pixel stops at the
    first Gaussian with ``T (1 - alpha) <= 1e-4``, which is itself excluded. (Transmittance
    products are taken in float64.)

    Args:
        range_start, range_end: batch range (inclusive, exclusive), as in gsplat.
        transmittances: ``[..., H, W]`` current transmittance per pixel.
        means2d: ``[..., N, 2]``; conics: ``[..., N, 3]``; opacities: ``[..., N]``.
        image_width, image_height, tile_size: image and tile geometry.
        isect_offsets: ``[..., tile_height, tile_width]`` from ``isect_offset_encode``.
        flatten_ids: ``[n_isects]`` flat Gaussian ids (into ``[images * N]``), sorted by tile
            then depth.

    Returns:
        ``(gaussian_ids, pixel_ids, image_ids)``, int64 ``[M]`` each, ordered by global pixel
        (image, row-major pixel) and then front to back, like gsplat's output.
    """
    n = means2d.shape[-2]
    tile_h, tile_w = isect_offsets.shape[-2:]
    assert tile_h * tile_size >= image_height and tile_w * tile_size >= image_width
    hw = image_height * image_width
    gs, ps = [], []
    for blk in _iter_blocks(
        range_start,
        range_end,
        means2d,
        conics,
        opacities,
        image_width,
        image_height,
        tile_size,
        isect_offsets,
        flatten_ids,
    ):
        res = _apply_rules(blk, transmittances, ALPHA_MAX)
        rows, cols = torch.nonzero(res.keep, as_tuple=True)
        gs.append(blk.gid[cols] % n)
        ps.append(blk.pix[rows, cols])
    if not gs:
        empty = torch.zeros(0, dtype=torch.long, device=means2d.device)
        return empty, empty.clone(), empty.clone()
    g = torch.cat(gs)
    p = torch.cat(ps)
    # Reorder pixel-major without a sort: each pixel's pairs are already contiguous and front to
    # back, so place them at (start of the pixel's run) + (rank inside its run).
    rank = _Segments.from_sorted_keys(p).pos
    counts = torch.bincount(p, minlength=transmittances.numel())
    dest = (torch.cumsum(counts, 0) - counts)[p] + rank
    g_out = torch.empty_like(g)
    p_out = torch.empty_like(p)
    g_out[dest] = g
    p_out[dest] = p
    return g_out, p_out % hw, p_out // hw


# --------------------------------------------------------------------------------------------
# Plugging the substitutes into gsplat
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def cpu_substitutes() -> Iterator[None]:
    """Run gsplat's torch reference on the CPU.

    Inside the ``with`` block ``gsplat.cuda._wrapper.rasterize_to_indices_in_range`` is this
    module's :func:`rasterize_to_indices_in_range`, and ``import nerfacc`` yields a stand-in
    module exposing :func:`render_weight_from_alpha` and :func:`accumulate_along_rays`. Both
    are restored on exit (also on error); nesting is fine.
    """
    from gsplat.cuda import _wrapper

    saved_fn = _wrapper.rasterize_to_indices_in_range
    had_nerfacc = "nerfacc" in sys.modules
    saved_mod = sys.modules.get("nerfacc")
    fake = types.ModuleType("nerfacc")
    fake.__doc__ = "sync4d CPU stand-in for nerfacc (render_weight_from_alpha, accumulate)."
    fake.render_weight_from_alpha = render_weight_from_alpha  # type: ignore[attr-defined]
    fake.accumulate_along_rays = accumulate_along_rays  # type: ignore[attr-defined]
    _wrapper.rasterize_to_indices_in_range = rasterize_to_indices_in_range
    sys.modules["nerfacc"] = fake
    try:
        yield
    finally:
        _wrapper.rasterize_to_indices_in_range = saved_fn
        if had_nerfacc:
            sys.modules["nerfacc"] = saved_mod  # type: ignore[assignment]
        else:
            sys.modules.pop("nerfacc", None)


# --------------------------------------------------------------------------------------------
# Tile intersection
# --------------------------------------------------------------------------------------------


def _tile_rects(
    means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> tuple[Tensor, Tensor]:
    """gsplat's tile rectangle per Gaussian: (mins [..., 2], maxs [..., 2]) int32, clamped."""
    tile_means = means2d / tile_size
    tile_radii = radii / tile_size  # int / int -> default float dtype, as in gsplat
    mins = torch.floor(tile_means - tile_radii).int()
    maxs = torch.ceil(tile_means + tile_radii).int()
    lim = torch.tensor([tile_width, tile_height], dtype=torch.int32, device=means2d.device)
    mins = torch.minimum(torch.clamp(mins, min=0), lim)
    maxs = torch.minimum(torch.clamp(maxs, min=0), lim)
    return mins, maxs


@torch.no_grad()
def isect_tiles_fast(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    tile_size: int,
    tile_width: int,
    tile_height: int,
    sort: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Vectorised equivalent of ``gsplat.cuda._torch_impl._isect_tiles`` (identical outputs).

    Each visible Gaussian (both radii > 0) covers tiles ``floor((m - r) / ts) ..
    ceil((m + r) / ts)`` (exclusive max), clamped to the tile grid. Intersection ids are
    ``image_id << (tile_bits + 32) | tile_id << 32 | float32_bits(depth)``.

    Args:
        means2d: ``[..., N, 2]``; radii: ``[..., N, 2]`` int; depths: ``[..., N]``.
        tile_size, tile_width, tile_height: tile geometry.
        sort: sort by intersection id (stable, so ties keep Gaussian index order).

    Returns:
        ``(tiles_per_gauss [..., N] int32, isect_ids [n_isects] int64,
        flatten_ids [n_isects] int32)``.
    """
    image_dims = means2d.shape[:-2]
    n = means2d.shape[-2]
    n_images = math.prod(image_dims)
    device = means2d.device
    means2d = means2d.reshape(n_images, n, 2)
    radii = radii.reshape(n_images, n, 2)
    depths = depths.reshape(n_images, n)

    mins, maxs = _tile_rects(means2d, radii, tile_size, tile_width, tile_height)
    extent = (maxs - mins).long()
    tiles_per_gauss = extent.prod(dim=-1) * (radii > 0).all(dim=-1)

    image_n_bits = n_images.bit_length()
    tile_n_bits = (tile_width * tile_height).bit_length()
    assert image_n_bits + tile_n_bits + 32 <= 64

    counts = tiles_per_gauss.reshape(-1)
    total = int(counts.sum())
    idx = torch.repeat_interleave(torch.arange(n_images * n, device=device), counts)
    local = torch.arange(total, device=device) - (torch.cumsum(counts, 0) - counts)[idx]
    ext_x = extent[..., 0].reshape(-1)[idx]
    tx = mins[..., 0].reshape(-1).long()[idx] + local % torch.clamp(ext_x, min=1)
    ty = mins[..., 1].reshape(-1).long()[idx] + local // torch.clamp(ext_x, min=1)
    tile_id = ty * tile_width + tx
    image_id = idx // n
    depth_bits = depths.reshape(-1).to(torch.float32).view(torch.int32).long() & 0xFFFFFFFF
    isect_ids = (image_id << (tile_n_bits + 32)) | (tile_id << 32) | depth_bits[idx]
    flatten_ids = idx.int()
    if sort:
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return tiles_per_gauss.reshape(image_dims + (n,)).int(), isect_ids, flatten_ids


# --------------------------------------------------------------------------------------------
# The gsplat pipeline on the CPU
# --------------------------------------------------------------------------------------------


@dataclass
class GsplatRender:
    """Outputs and intermediates of :func:`gsplat_render_full` (single camera).

    ``means2d``, ``conics``, ``opacities`` are the tensors the compositor consumed; when they
    require grad, ``retain_grad()`` has been called on them so ``.grad`` is filled by backward.
    """

    image: Tensor  # [H, W, C]
    alpha: Tensor  # [H, W, 1]
    depth_accum: Tensor | None  # [H, W, 1] sum_i z_i a_i T_i (if requested)
    means2d: Tensor  # [N, 2]
    conics: Tensor  # [N, 3]
    depths: Tensor  # [N]
    opacities: Tensor  # [N] effective (times the compensation when antialiased)
    radii: Tensor  # [N, 2] int32
    compensations: Tensor | None  # [N]
    tiles_per_gauss: Tensor  # [N] int32
    isect_ids: Tensor  # [n_isects] int64
    flatten_ids: Tensor  # [n_isects] int32
    isect_offsets: Tensor  # [tile_height, tile_width] int32
    width: int
    height: int
    tile_size: int = TILE_SIZE
    near: float = 0.01
    far: float = 1e10
    extras: dict = field(default_factory=dict)


def gsplat_project(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near: float = 0.01,
    far: float = 1e10,
    antialiased: bool = False,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor | None]:
    """gsplat's torch projection (``_quat_scale_to_covar_preci`` + ``_fully_fused_projection``).

    Args:
        means ``[N, 3]``, quats ``[N, 4]`` (w, x, y, z; unnormalised), scales ``[N, 3]``,
        opacities ``[N]``, viewmat ``[4, 4]`` world-to-camera, K ``[3, 3]``.

    Returns:
        ``(means2d [N, 2], conics [N, 3], depths [N], opacities_eff [N], radii [N, 2] int32,
        compensations [N] or None)``; ``opacities_eff = opacities * compensations`` when
        antialiased. Differentiable through means2d, conics, depths and opacities_eff.
    """
    from gsplat.cuda._torch_impl import _fully_fused_projection, _quat_scale_to_covar_preci

    covars, _ = _quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False)
    radii, means2d, depths, conics, comps = _fully_fused_projection(
        means,
        covars,
        viewmat[None],
        K[None],
        width,
        height,
        eps2d=eps2d,
        near_plane=near,
        far_plane=far,
        calc_compensations=antialiased,
    )
    comp = comps[0] if comps is not None else None
    opac = opacities * comp if comp is not None else opacities
    return means2d[0], conics[0], depths[0], opac, radii[0], comp


def gsplat_rasterize(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    tile_size: int = TILE_SIZE,
    fast_isect: bool = True,
    batch_per_iter: int | None = None,
) -> tuple[Tensor, Tensor, dict[str, Tensor]]:
    """gsplat's tiling and compositing (``isect`` + ``_isect_offset_encode`` +
    ``_rasterize_to_pixels``) on projected Gaussians, run through :func:`cpu_substitutes`.

    Args:
        means2d ``[N, 2]``, conics ``[N, 3]``, opacities ``[N]`` (effective), colors ``[N, C]``,
        depths ``[N]`` (sort key only), radii ``[N, 2]`` int, background ``[C]`` or None.
        fast_isect: use :func:`isect_tiles_fast` instead of gsplat's per-Gaussian Python loop.
        batch_per_iter: gsplat's tile-batches per compositing round. None (default) takes
            enough batches to composite every tile in one round, which is what gsplat's CUDA
            rasterizer computes. With several rounds gsplat's torch path differs from it on
            terminated pixels: the kernel only sees the carried transmittance, not that the
            pixel was done, so a later round can blend more Gaussians into it.

    Returns:
        ``(image [H, W, C], alpha [H, W, 1], isect)`` with ``isect`` holding
        ``tiles_per_gauss``, ``isect_ids``, ``flatten_ids``, ``isect_offsets`` ([th, tw]).
        Differentiable w.r.t. means2d, conics, opacities, colors (and background).
    """
    from gsplat.cuda._torch_impl import _isect_offset_encode, _isect_tiles, _rasterize_to_pixels

    tile_w = math.ceil(width / tile_size)
    tile_h = math.ceil(height / tile_size)
    isect = isect_tiles_fast if fast_isect else _isect_tiles
    tiles_per_gauss, isect_ids, flatten_ids = isect(
        means2d[None].detach(), radii[None], depths[None].detach(), tile_size, tile_w, tile_h
    )
    isect_offsets = _isect_offset_encode(isect_ids, 1, tile_w, tile_h)
    if batch_per_iter is None:
        bounds = torch.cat([isect_offsets.flatten().long(), isect_ids.new_tensor([len(isect_ids)])])
        longest = int(torch.diff(bounds).max()) if len(isect_ids) else 0
        batch_per_iter = max(1, -(-longest // (tile_size * tile_size)))
    bg = background[None] if background is not None else None
    with cpu_substitutes():
        image, alpha = _rasterize_to_pixels(
            means2d[None],
            conics[None],
            colors[None],
            opacities[None],
            width,
            height,
            tile_size,
            isect_offsets,
            flatten_ids,
            backgrounds=bg,
            batch_per_iter=batch_per_iter,
        )
    info = {
        "tiles_per_gauss": tiles_per_gauss[0],
        "isect_ids": isect_ids,
        "flatten_ids": flatten_ids,
        "isect_offsets": isect_offsets[0],
    }
    return image[0], alpha[0], info


def _retain(t: Tensor) -> Tensor:
    if t.requires_grad:
        t.retain_grad()
    return t


def gsplat_rasterize_full(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    render_depth: bool = False,
    fast_isect: bool = True,
    near: float = -math.inf,
    far: float = math.inf,
    compensations: Tensor | None = None,
) -> GsplatRender:
    """:func:`gsplat_rasterize` on projected Gaussians, returning a :class:`GsplatRender`.

    With ``render_depth`` the depths are composited as an extra channel (background 0), giving
    ``depth_accum = sum_i z_i a_i T_i`` (differentiable in ``depths`` too). ``near`` / ``far``
    / ``compensations`` are only recorded (for :func:`ambiguous_pixels`). ``retain_grad`` is
    set on means2d / conics / opacities / depths when they require grad.
    """
    means2d, conics, opacities = _retain(means2d), _retain(conics), _retain(opacities)
    depths = _retain(depths)
    feats = colors
    bg = background
    if render_depth:
        feats = torch.cat([colors, depths[:, None].to(colors.dtype)], dim=-1)
        if bg is not None:
            bg = torch.cat([bg, bg.new_zeros(1)])
    image, alpha, isect = gsplat_rasterize(
        means2d, conics, opacities, feats, depths, radii, width, height, bg, TILE_SIZE, fast_isect
    )
    depth_accum = None
    if render_depth:
        image, depth_accum = image[..., :-1], image[..., -1:]
    return GsplatRender(
        image=image,
        alpha=alpha,
        depth_accum=depth_accum,
        means2d=means2d,
        conics=conics,
        depths=depths,
        opacities=opacities,
        radii=radii,
        compensations=compensations,
        width=width,
        height=height,
        near=near,
        far=far,
        **isect,
    )


def gsplat_render_full(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    eps2d: float = 0.3,
    near: float = 0.01,
    far: float = 1e10,
    antialiased: bool = False,
    fast_isect: bool = True,
    render_depth: bool = False,
) -> GsplatRender:
    """Render one camera with gsplat's torch reference on the CPU; all intermediates returned.

    Same inputs as :func:`gsplat_render`. With ``render_depth`` the camera depth is composited
    as an extra channel (background 0), giving ``depth_accum = sum_i z_i a_i T_i``.
    The projected ``means2d`` / ``conics`` / ``opacities`` / ``depths`` in the result have
    ``retain_grad`` set when they require grad.
    """
    means2d, conics, depths, opac, radii, comp = gsplat_project(
        means, quats, scales, opacities, viewmat, K, width, height, eps2d, near, far, antialiased
    )
    return gsplat_rasterize_full(
        means2d,
        conics,
        opac,
        colors,
        depths,
        radii,
        width,
        height,
        background,
        render_depth=render_depth,
        fast_isect=fast_isect,
        near=near,
        far=far,
        compensations=comp,
    )


def gsplat_render(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    eps2d: float = 0.3,
    near: float = 0.01,
    far: float = 1e10,
    antialiased: bool = False,
    fast_isect: bool = True,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render one pinhole camera with gsplat 1.5.3's pure-torch pipeline on the CPU.

    Pipeline: ``_quat_scale_to_covar_preci`` -> ``_fully_fused_projection`` (with
    ``calc_compensations`` and ``opacities *= compensation`` when antialiased) -> tile
    intersection (:func:`isect_tiles_fast` or gsplat's ``_isect_tiles``) ->
    ``_isect_offset_encode`` -> ``_rasterize_to_pixels`` (via :func:`cpu_substitutes`).
    Works in float32 or float64 (the dtype of the inputs).

    Args:
        means ``[N, 3]`` world, quats ``[N, 4]`` (w, x, y, z), scales ``[N, 3]`` (std devs),
        opacities ``[N]`` in [0, 1], colors ``[N, C]``, viewmat ``[4, 4]`` world-to-camera
        (OpenCV axes), K ``[3, 3]``, background ``[C]`` or None.

    Returns:
        ``(image [H, W, C], alpha [H, W, 1], means2d [N, 2])``; differentiable w.r.t. means,
        quats, scales, opacities, colors (``means2d`` has ``retain_grad`` set).
    """
    out = gsplat_render_full(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmat,
        K,
        width,
        height,
        background,
        eps2d,
        near,
        far,
        antialiased,
        fast_isect,
    )
    return out.image, out.alpha, out.means2d


# --------------------------------------------------------------------------------------------
# Independent brute-force compositor (numpy float64)
# --------------------------------------------------------------------------------------------


def brute_force_composite(
    means2d: np.ndarray | Tensor,
    conics: np.ndarray | Tensor,
    opacities: np.ndarray | Tensor,
    colors: np.ndarray | Tensor,
    radii: np.ndarray | Tensor,
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
    background: np.ndarray | Tensor | None = None,
    alpha_max: float = ALPHA_MAX,
    *,
    depths: np.ndarray | Tensor,
    return_info: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Plain per-pixel front-to-back compositing with gsplat's rules, in numpy float64.

    For each pixel, the Gaussians whose tile rectangle (gsplat's rule, computed in the dtype of
    ``means2d``) contains the pixel's tile are visited in (float32 depth, index) order; a
    Gaussian is skipped when ``sigma < 0`` or ``alpha < 1/255`` with
    ``alpha = min(alpha_max, o exp(-sigma))``; the pixel stops at the first Gaussian with
    ``T (1 - alpha) <= 1e-4`` (excluded).

    Args:
        means2d ``[N, 2]``, conics ``[N, 3]``, opacities ``[N]``, colors ``[N, C]``,
        radii ``[N, 2]`` (Gaussians with a zero radius are ignored), background ``[C]`` or None,
        depths ``[N]`` (keyword-only: the sort key).
        return_info: also return a dict with the blended pairs in order (``gaussian_ids``,
            ``pixel_ids`` row-major), ``terminated`` ``[H, W]`` bool and ``transmittance``
            ``[H, W]``.

    Returns:
        ``(image [H, W, C], alpha [H, W, 1])`` float64, plus the info dict if requested.
    """

    def arr(x: np.ndarray | Tensor) -> np.ndarray:
        return x.detach().cpu().numpy() if isinstance(x, Tensor) else np.asarray(x)

    m_in = arr(means2d)
    m = m_in.astype(np.float64)
    con = arr(conics).astype(np.float64)
    op = arr(opacities).astype(np.float64)
    col = arr(colors).astype(np.float64)
    rad = arr(radii).astype(np.int64)
    dep = arr(depths)
    channels = col.shape[1]
    bg = np.zeros(channels) if background is None else arr(background).astype(np.float64)
    tile_w = math.ceil(width / tile_size)
    tile_h = math.ceil(height / tile_size)

    # Tile rectangles exactly as gsplat computes them (dtype of means2d; radii / ts in float32).
    fdt = m_in.dtype if np.issubdtype(m_in.dtype, np.floating) else np.float64
    tmeans = m_in.astype(fdt) / fdt.type(tile_size)
    trad = rad.astype(np.float32) / np.float32(tile_size)
    tmin = np.floor(tmeans - trad).astype(np.int64)
    tmax = np.ceil(tmeans + trad).astype(np.int64)
    tmin = np.minimum(np.maximum(tmin, 0), [tile_w, tile_h])
    tmax = np.minimum(np.maximum(tmax, 0), [tile_w, tile_h])
    visible = (rad > 0).all(axis=1)

    key = dep.astype(np.float32).view(np.uint32)
    order = np.lexsort((np.arange(len(key)), key))

    image = np.zeros((height, width, channels))
    trans = np.ones((height, width))
    terminated = np.zeros((height, width), dtype=bool)
    pair_g: list[int] = []
    pair_p: list[int] = []
    for ty in range(tile_h):
        for tx in range(tile_w):
            inside = (
                visible
                & (tmin[:, 0] <= tx)
                & (tx < tmax[:, 0])
                & (tmin[:, 1] <= ty)
                & (ty < tmax[:, 1])
            )
            cand = order[inside[order]]
            if cand.size == 0:
                continue
            for y in range(ty * tile_size, min(height, (ty + 1) * tile_size)):
                for x in range(tx * tile_size, min(width, (tx + 1) * tile_size)):
                    dx = m[cand, 0] - (x + 0.5)
                    dy = m[cand, 1] - (y + 0.5)
                    sig = 0.5 * (con[cand, 0] * dx * dx + con[cand, 2] * dy * dy)
                    sig = sig + con[cand, 1] * dx * dy
                    alphas = np.minimum(alpha_max, op[cand] * np.exp(-sig))
                    ok = (sig >= 0) & (alphas >= ALPHA_THRESHOLD)
                    t = 1.0
                    acc = np.zeros(channels)
                    for j in np.nonzero(ok)[0]:
                        a = alphas[j]
                        nt = t * (1.0 - a)
                        if nt <= TRANSMITTANCE_MIN:
                            terminated[y, x] = True
                            break
                        acc += col[cand[j]] * (a * t)
                        t = nt
                        if return_info:
                            pair_g.append(int(cand[j]))
                            pair_p.append(y * width + x)
                    image[y, x] = acc + t * bg
                    trans[y, x] = t
    alpha_img = (1.0 - trans)[..., None]
    if not return_info:
        return image, alpha_img
    g = np.asarray(pair_g, dtype=np.int64)
    p = np.asarray(pair_p, dtype=np.int64)
    srt = np.argsort(p, kind="stable")  # pixel-major; per-pixel order already front to back
    info = {
        "gaussian_ids": g[srt],
        "pixel_ids": p[srt],
        "terminated": terminated,
        "transmittance": trans,
    }
    return image, alpha_img, info


# --------------------------------------------------------------------------------------------
# Parity-test helpers: random scenes and ill-conditioned pixels
# --------------------------------------------------------------------------------------------


@dataclass
class Scene:
    """A random single-camera scene (float64 master copy; use :meth:`to` for other dtypes)."""

    means: Tensor  # [N, 3]
    quats: Tensor  # [N, 4]
    scales: Tensor  # [N, 3]
    opacities: Tensor  # [N]
    colors: Tensor  # [N, C]
    viewmat: Tensor  # [4, 4]
    K: Tensor  # [3, 3]
    width: int
    height: int
    background: Tensor | None = None  # [C]

    def to(self, dtype: torch.dtype, requires_grad: bool = False) -> Scene:
        """Copy with tensors cast to ``dtype``; the Gaussian parameters optionally as leaves
        requiring grad (viewmat, K and background never require grad)."""

        def cast(t: Tensor, grad: bool) -> Tensor:
            out = t.detach().to(dtype).clone().contiguous()
            return out.requires_grad_(grad)

        return Scene(
            means=cast(self.means, requires_grad),
            quats=cast(self.quats, requires_grad),
            scales=cast(self.scales, requires_grad),
            opacities=cast(self.opacities, requires_grad),
            colors=cast(self.colors, requires_grad),
            viewmat=cast(self.viewmat, False),
            K=cast(self.K, False),
            width=self.width,
            height=self.height,
            background=None if self.background is None else cast(self.background, False),
        )


def _random_rotation(gen: torch.Generator) -> Tensor:
    q = torch.randn(4, generator=gen, dtype=torch.float64)
    w, x, y, z = (q / q.norm()).tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


def make_random_scene(
    seed: int,
    n: int = 1200,
    width: int = 133,
    height: int = 97,
    channels: int = 3,
    signed_features: bool = False,
    opacity_range: tuple[float, float] = (0.05, 0.99),
    cluster_fraction: float = 0.3,
    n_clusters: int = 3,
    max_sigma_px: float = 12.0,
    full_opacity_fraction: float = 0.0,
    n_frustum_edge: int = 12,
    n_culled: int = 8,
    background: bool = False,
) -> Scene:
    """Random scene in front of a pinhole camera with an arbitrary world pose (float64).

    Gaussians are drawn in camera space and mapped to world space. Camera depths lie in
    [2, 12] on a jittered grid, so any two differ by at least ``2.5 / n`` (no near-ties in the
    depth sort under float32 rounding). Screen-space std devs are log-uniform in
    [0.3, ``max_sigma_px``] px with up to 3x anisotropy and random (unnormalised) quaternions.
    ``cluster_fraction`` of them are packed around ``n_clusters`` centres with high opacity so
    pixels terminate (T < 1e-4); ``n_frustum_edge`` large ones sit just beyond gsplat's
    frustum clamp (|x/z| > lim) yet reach into the image; ``n_culled`` lie behind the camera or
    before the near plane. ``full_opacity_fraction`` of them get opacity exactly 1, half of
    those centred on a pixel centre so the 0.999 alpha clamp is reached.
    """
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64

    def uni(lo: float, hi: float, size: int | tuple[int, ...]) -> Tensor:
        shape = (size,) if isinstance(size, int) else size
        return lo + (hi - lo) * torch.rand(shape, generator=gen, dtype=f64)

    fx = 0.85 * width
    fy = 0.9 * width
    cx = 0.47 * width
    cy = 0.53 * height
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=f64)
    lim_xp = (width - cx) / fx + 0.3 * 0.5 * width / fx
    lim_xn = cx / fx + 0.3 * 0.5 * width / fx
    lim_yp = (height - cy) / fy + 0.3 * 0.5 * height / fy
    lim_yn = cy / fy + 0.3 * 0.5 * height / fy

    n_main = n - n_culled
    slots = torch.randperm(n_main, generator=gen).to(f64)
    z = 2.0 + 10.0 * (slots + 0.5 + uni(-0.25, 0.25, n_main)) / n_main
    # Normalised image-plane coordinates u = x / z, v = y / z.
    u = uni(-cx / fx * 1.1, (width - cx) / fx * 1.1, n_main)
    v = uni(-cy / fy * 1.1, (height - cy) / fy * 1.1, n_main)
    sig_px = torch.exp(uni(math.log(0.3), math.log(max_sigma_px), n_main))
    opac = uni(opacity_range[0], opacity_range[1], n_main)

    n_cl = int(cluster_fraction * n_main)
    if n_cl > 0:
        centres_u = uni(-0.6 * cx / fx, 0.6 * (width - cx) / fx, n_clusters)
        centres_v = uni(-0.6 * cy / fy, 0.6 * (height - cy) / fy, n_clusters)
        which = torch.randint(0, n_clusters, (n_cl,), generator=gen)
        spread = 6.0 / fx
        u[:n_cl] = centres_u[which] + spread * torch.randn(n_cl, generator=gen, dtype=f64)
        v[:n_cl] = centres_v[which] + spread * torch.randn(n_cl, generator=gen, dtype=f64)
        sig_px[:n_cl] = uni(2.0, max_sigma_px * 0.75, n_cl)
        opac[:n_cl] = uni(max(0.6, opacity_range[0]), opacity_range[1], n_cl)

    n_edge = min(n_frustum_edge, n_main - n_cl)
    if n_edge > 0:
        sl = slice(n_cl, n_cl + n_edge)
        side = torch.randint(0, 4, (n_edge,), generator=gen)
        beyond = uni(1.02, 1.12, n_edge)
        u_e = torch.where(side == 0, lim_xp * beyond, torch.where(side == 1, -lim_xn * beyond, 0.0))
        v_e = torch.where(side == 2, lim_yp * beyond, torch.where(side == 3, -lim_yn * beyond, 0.0))
        u_e = torch.where(side >= 2, uni(-0.3, 0.3, n_edge), u_e)
        v_e = torch.where(side < 2, uni(-0.3, 0.3, n_edge), v_e)
        u[sl], v[sl] = u_e, v_e
        sig_px[sl] = uni(0.6 * max_sigma_px, max_sigma_px, n_edge)

    n_full = int(full_opacity_fraction * n_main)
    if n_full > 0:
        full = torch.randperm(n_main, generator=gen)[:n_full]
        opac[full] = 1.0
        # Half of them project exactly onto a pixel centre, where o exp(-sigma) > 0.999: the
        # alpha clamp is only reached within ~0.03 sigma of a Gaussian's centre.
        snap = full[: (n_full + 1) // 2]
        px = torch.randint(0, width, (snap.numel(),), generator=gen).to(f64) + 0.5
        py = torch.randint(0, height, (snap.numel(),), generator=gen).to(f64) + 0.5
        u[snap] = (px - cx) / fx
        v[snap] = (py - cy) / fy

    aniso = torch.exp(uni(-math.log(3.0) / 2, math.log(3.0) / 2, (n_main, 3)))
    aniso[torch.rand(n_main, generator=gen) < 0.4] = 1.0  # some stay isotropic
    scales = (sig_px * z / fx)[:, None] * aniso
    p_cam = torch.stack([u * z, v * z, z], dim=-1)

    if n_culled > 0:
        zc = torch.cat([uni(-2.0, -0.5, n_culled - n_culled // 2), uni(1e-3, 8e-3, n_culled // 2)])
        pc = torch.stack([uni(-0.3, 0.3, n_culled) * zc, uni(-0.3, 0.3, n_culled) * zc, zc], -1)
        p_cam = torch.cat([p_cam, pc])
        scales = torch.cat([scales, uni(0.01, 0.2, (n_culled, 3))])
        opac = torch.cat([opac, uni(opacity_range[0], opacity_range[1], n_culled)])

    quats = torch.randn(n, 4, generator=gen, dtype=f64)
    quats = quats * uni(0.5, 2.0, n)[:, None]  # unnormalised on purpose

    rot = _random_rotation(gen)
    trans = uni(-1.0, 1.0, 3)
    viewmat = torch.eye(4, dtype=f64)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = trans
    means = (p_cam - trans) @ rot  # R^T (p_cam - t), row-vector form

    perm = torch.randperm(n, generator=gen)  # mix the kinds across indices
    if signed_features:
        colors = torch.randn(n, channels, generator=gen, dtype=f64)
    else:
        colors = torch.rand(n, channels, generator=gen, dtype=f64)
    bg = None
    if background:
        bg = uni(-0.5, 1.0, channels) if signed_features else uni(0.2, 0.9, channels)
    return Scene(
        means=means[perm].contiguous(),
        quats=quats[perm].contiguous(),
        scales=scales[perm].contiguous(),
        opacities=opac[perm].contiguous(),
        colors=colors,
        viewmat=viewmat,
        K=K,
        width=width,
        height=height,
        background=bg,
    )


@torch.no_grad()
def ambiguous_pixels(
    render: GsplatRender,
    alpha_max: float = ALPHA_MAX,
    rtol_alpha: float = 5e-4,
    rtol_trans: float = 1e-3,
    rtol_radius: float = 1e-5,
    tol_px: float = 1e-3,
    tol_depth: float = 1e-6,
) -> tuple[Tensor, dict[str, int | Tensor]]:
    """Pixels whose composited value is discontinuous under tiny perturbations of the inputs.

    Two correct implementations in different precisions (or operation orders) can legitimately
    disagree on these pixels by a jump, because a discrete decision flips. From a (preferably
    float64) reference render this flags a pixel when, among the pairs evaluated before it
    stops:

    * some ``alpha`` lies within ``rtol_alpha`` (relative) of ``1/255`` (skip rule);
    * some ``T (1 - alpha)`` lies within ``rtol_trans`` of ``1e-4`` (termination rule);
    * some ``o exp(-sigma)`` lies within ``rtol_alpha`` of ``alpha_max`` (clamp: continuous in
      value, but the gradient jumps);

    and, for a Gaussian whose tile rectangle or visibility could change (pre-ceil radius
    ``3.33 sqrt(cov)`` within ``rtol_radius`` of an integer, ``m +- r`` within ``tol_px`` of a
    tile edge or of the image border, depth within ``tol_depth`` of near/far), every pixel in
    the tiles that may or may not be covered where that Gaussian's alpha reaches
    ``(1 - rtol_alpha) / 255``.

    Depth-order near-ties are not detected (use scenes with separated depths, as
    :func:`make_random_scene` makes).

    Returns:
        ``(mask [H, W] bool, stats)``; ``stats`` counts flagged pixels per reason, the pixels
        that terminate (``terminated_pixels``) and the evaluated pairs whose alpha is clamped
        (``clamped_pairs``), and marks the Gaussians with an ambiguous radius
        (``radius_ambiguous`` [N, 2] bool) or visibility (``visibility_ambiguous`` [N] bool).
    """
    width, height, ts = render.width, render.height, render.tile_size
    means2d = render.means2d.detach()
    conics = render.conics.detach()
    opac = render.opacities.detach()
    hw = height * width
    flag_alpha = torch.zeros(hw, dtype=torch.bool)
    flag_trans = torch.zeros(hw, dtype=torch.bool)
    flag_clamp = torch.zeros(hw, dtype=torch.bool)
    ones = torch.ones(1, height, width, dtype=torch.float64)
    terminated = torch.zeros(hw, dtype=torch.bool)
    n_clamped = 0
    for blk in _iter_blocks(
        0,
        1 << 40,
        means2d[None],
        conics[None],
        opac[None],
        width,
        height,
        ts,
        render.isect_offsets[None],
        render.flatten_ids,
    ):
        res = _apply_rules(blk, ones, alpha_max, with_next_t=True)
        evaluated = ~torch.isnan(res.next_t)  # blended pairs and each pixel's terminating pair
        # Every pair up to a pixel's terminating pair was evaluated (skipped ones included).
        cols = torch.arange(blk.gid.numel())[None, :].expand_as(blk.inside)
        term_col = torch.full((hw,), 1 << 62, dtype=torch.long)
        term_col[blk.pix[res.terminating]] = cols[res.terminating]
        terminated[blk.pix[res.terminating]] = True
        before_end = blk.inside & (cols <= term_col[blk.pix])
        near_a = (res.alpha.double() - ALPHA_THRESHOLD).abs() <= rtol_alpha * ALPHA_THRESHOLD
        flag_alpha[blk.pix[near_a & before_end]] = True
        near_t = (res.next_t - TRANSMITTANCE_MIN).abs() <= rtol_trans * TRANSMITTANCE_MIN
        flag_trans[blk.pix[evaluated & near_t]] = True
        near_c = (blk.raw_alpha.double() - alpha_max).abs() <= rtol_alpha * alpha_max
        flag_clamp[blk.pix[evaluated & near_c]] = True
        n_clamped += int((evaluated & (blk.raw_alpha > alpha_max)).sum())

    # Tile rectangle / visibility ambiguity.
    m64 = means2d.double()
    con64 = conics.double()
    det_c = con64[:, 0] * con64[:, 2] - con64[:, 1] ** 2
    cov_diag = torch.stack([con64[:, 2] / det_c, con64[:, 0] / det_c], dim=-1)
    ext = 3.33 * torch.sqrt(torch.clamp(cov_diag, min=0))
    r_lo = torch.ceil(ext * (1 - rtol_radius))
    r_hi = torch.ceil(ext * (1 + rtol_radius))
    radius_amb = (r_lo != r_hi) & torch.isfinite(ext)
    z = render.depths.detach().double()
    depth_ok_hi = (z > render.near - tol_depth) & (z < render.far + tol_depth)
    depth_ok_lo = (z > render.near + tol_depth) & (z < render.far - tol_depth)
    size = torch.tensor([width, height], dtype=torch.float64)

    def inside(m: Tensor, r: Tensor, grow: float) -> Tensor:
        return ((m + r > -grow) & (m - r < size + grow)).all(dim=-1)

    vis_hi = depth_ok_hi & inside(m64, r_hi, tol_px)
    vis_lo = depth_ok_lo & inside(m64, r_lo, -tol_px)
    grid = torch.tensor([math.ceil(width / ts), math.ceil(height / ts)], dtype=torch.float64)

    def rect(m: Tensor, r: Tensor, sign: float) -> tuple[Tensor, Tensor]:
        lo = torch.clamp(torch.floor((m + sign * tol_px - r) / ts), min=0)
        hi = torch.clamp(torch.ceil((m - sign * tol_px + r) / ts), min=0)
        return torch.minimum(lo, grid), torch.minimum(hi, grid)

    out_lo, out_hi = rect(m64, r_hi, -1.0)  # largest possible rectangle
    in_lo, in_hi = rect(m64, r_lo, +1.0)  # smallest possible rectangle
    rect_amb = (out_lo != in_lo).any(-1) | (out_hi != in_hi).any(-1)
    amb = vis_hi & (rect_amb | (vis_hi != vis_lo))
    flag_rect = torch.zeros(height, width, dtype=torch.bool)
    thr = ALPHA_THRESHOLD * (1 - rtol_alpha)
    for g in torch.nonzero(amb).flatten().tolist():
        x0, y0 = (int(v) * ts for v in out_lo[g])
        x1 = min(width, int(out_hi[g, 0]) * ts)
        y1 = min(height, int(out_hi[g, 1]) * ts)
        if x1 <= x0 or y1 <= y0:
            continue
        ys, xs = torch.meshgrid(
            torch.arange(y0, y1, dtype=torch.float64) + 0.5,
            torch.arange(x0, x1, dtype=torch.float64) + 0.5,
            indexing="ij",
        )
        dx, dy = m64[g, 0] - xs, m64[g, 1] - ys
        sig = 0.5 * (con64[g, 0] * dx * dx + con64[g, 2] * dy * dy) + con64[g, 1] * dx * dy
        reach = opac[g].double() * torch.exp(-sig) >= thr
        if bool(vis_lo[g]):  # certainly visible: only the tiles outside the inner rectangle
            tx = (torch.arange(x0, x1) // ts)[None, :]
            ty = (torch.arange(y0, y1) // ts)[:, None]
            in_inner = (
                (tx >= int(in_lo[g, 0]))
                & (tx < int(in_hi[g, 0]))
                & (ty >= int(in_lo[g, 1]))
                & (ty < int(in_hi[g, 1]))
            )
            reach &= ~in_inner
        flag_rect[y0:y1, x0:x1] |= reach

    mask = (flag_alpha | flag_trans | flag_clamp).reshape(height, width) | flag_rect
    stats: dict[str, int | Tensor] = {
        "alpha_threshold": int(flag_alpha.sum()),
        "termination": int(flag_trans.sum()),
        "alpha_clamp": int(flag_clamp.sum()),
        "tile_rect": int(flag_rect.sum()),
        "total": int(mask.sum()),
        "terminated_pixels": int(terminated.sum()),
        "clamped_pairs": n_clamped,
        "radius_ambiguous": radius_amb,
        "visibility_ambiguous": vis_hi != vis_lo,
        "rect_ambiguous_gaussians": int(amb.sum()),
    }
    return mask, stats
