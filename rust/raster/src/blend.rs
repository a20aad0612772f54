//! Front-to-back alpha compositing of splats into 16x16 tiles, and its exact backward (f32).
//!
//! Parallel design: one rayon task per tile; tiles own disjoint pixels, so outputs are written
//! without locks. Within a tile the loop is splat-outer, pixel-inner: a batch of the tile's
//! front-to-back splat list is gathered into contiguous per-worker scratch, then each splat
//! visits only the pixels of its exact alpha-support box (pixels outside it have
//! alpha < 1/255 and would be skipped anyway, so the box changes no result). Per-pixel state
//! (transmittance, accumulators, done flags, last contributor) lives in the scratch, which is
//! allocated once per worker, never per pixel. The tile stops when all its pixels are done.
//!
//! The backward walks each tile's list back to front from the furthest last contributor,
//! recovering each pixel's transmittance by division (`T_i = T_{i+1} / (1 - alpha_i)`, bounded
//! by `1 / (1 - alpha_max)`). A splat's gradient summed over the tile's pixels goes to its own
//! intersection slot; a per-splat pass then adds its slots in a fixed order. No atomics, so the
//! result is bit-identical run to run and for any thread count.
//!
//! Depth is blended as one extra channel (camera z, background 0), so `depth_accum` and its
//! gradient need no separate code path.

use crate::bins::{SharedMut, TileBins};
use crate::error::{check_finite, check_len, RasterError, Result};
use crate::lanes::{
    self, BackwardPixels, ForwardPixels, Limits, RowMasks, RowSplat, LANES, TILE_PIXELS,
};
use crate::TILE_SIZE;
use rayon::prelude::*;
use sync4d_scalar::Real;

/// Alpha below which a splat is skipped at a pixel (3DGS).
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// A pixel stops (excluding the current splat) when its transmittance would drop below this.
pub const T_MIN: f64 = 1e-4;
/// Splats gathered per batch.
const BATCH: usize = 256;

/// Settings of the compositing stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BlendSettings {
    /// Per-splat alpha clamp (0.99 in 3DGS, 0.999 in gsplat).
    pub alpha_max: f64,
}

impl Default for BlendSettings {
    fn default() -> Self {
        BlendSettings { alpha_max: 0.99 }
    }
}

impl BlendSettings {
    /// Check `1/255 <= alpha_max < 1`.
    pub fn validate(&self) -> Result<()> {
        if !(self.alpha_max >= ALPHA_MIN && self.alpha_max < 1.0) {
            return Err(RasterError::invalid(
                "alpha_max",
                format!("must lie in [1/255, 1), got {}", self.alpha_max),
            ));
        }
        Ok(())
    }
}

/// Screen-space splats to composite: the projection outputs plus features. Flat row-major:
/// `means2d` N*2 px, `conics` N*3, `depths` N, `opacities` N, `radii` N*2 (0 = skip),
/// `features` N*C.
#[derive(Debug, Clone, Copy)]
pub struct Splats<'a, F> {
    /// Centres, N*2 pixels.
    pub means2d: &'a [F],
    /// Inverse 2D covariances (a, b, c), N*3.
    pub conics: &'a [F],
    /// Camera depth, N (sort key and the depth channel).
    pub depths: &'a [F],
    /// Opacities in [0, 1], N.
    pub opacities: &'a [F],
    /// Per-axis screen radii, N*2; splats with a zero radius are skipped.
    pub radii: &'a [i32],
    /// Features, N*C.
    pub features: &'a [F],
    /// Feature channels C (>= 1).
    pub channels: usize,
}

impl<F: Real> Splats<'_, F> {
    /// Number of splats.
    pub fn len(&self) -> usize {
        self.depths.len()
    }

    /// Whether there are no splats.
    pub fn is_empty(&self) -> bool {
        self.depths.is_empty()
    }

    /// Check lengths, finiteness and ranges; `background` must have C entries.
    pub fn validate(&self, background: &[F]) -> Result<()> {
        let n = self.len();
        if self.channels == 0 {
            return Err(RasterError::invalid(
                "features",
                "need at least one channel (shape [N, C] with C >= 1)",
            ));
        }
        check_len("means2d", self.means2d, n * 2)?;
        check_len("conics", self.conics, n * 3)?;
        check_len("opacities", self.opacities, n)?;
        check_len("radii", self.radii, n * 2)?;
        check_len("features", self.features, n * self.channels)?;
        check_len("background", background, self.channels)?;
        check_finite("means2d", self.means2d)?;
        check_finite("conics", self.conics)?;
        check_finite("depths", self.depths)?;
        check_finite("opacities", self.opacities)?;
        check_finite("features", self.features)?;
        check_finite("background", background)?;
        if let Some(i) = self
            .opacities
            .iter()
            .position(|o| *o < F::zero() || *o > F::one())
        {
            return Err(RasterError::invalid(
                "opacities",
                format!("must lie in [0, 1]; bad value at index {i}"),
            ));
        }
        if let Some(i) = self.radii.iter().position(|r| *r < 0) {
            return Err(RasterError::invalid(
                "radii",
                format!("must be >= 0; negative at flat index {i}"),
            ));
        }
        Ok(())
    }
}

/// Work counters of one rasterization, for benchmarks.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counters {
    /// Splats with a non-zero radius.
    pub visible: u64,
    /// (tile, splat) pairs.
    pub intersections: u64,
    /// (pixel, splat) pairs whose alpha was evaluated.
    pub evaluated: u64,
    /// (pixel, splat) pairs composited.
    pub blended: u64,
}

impl std::ops::Add for Counters {
    type Output = Counters;
    fn add(self, o: Counters) -> Counters {
        Counters {
            visible: self.visible + o.visible,
            intersections: self.intersections + o.intersections,
            evaluated: self.evaluated + o.evaluated,
            blended: self.blended + o.blended,
        }
    }
}

/// Mutable image outputs: `features` H*W*C, `alpha` H*W, `depth` H*W (sum of z * weight).
#[derive(Debug)]
pub struct ImageMut<'a, F> {
    /// Composited features plus `T_final * background`, H*W*C.
    pub features: &'a mut [F],
    /// Accumulated opacity `1 - T_final`, H*W.
    pub alpha: &'a mut [F],
    /// Accumulated depth `sum_i z_i alpha_i T_i` (not normalised), H*W.
    pub depth: &'a mut [F],
}

impl<F> ImageMut<'_, F> {
    /// Check the output lengths for `npix` pixels of `channels` features.
    pub fn check_len(&self, npix: usize, channels: usize) -> Result<()> {
        check_len("out_features", self.features, npix * channels)?;
        check_len("out_alpha", self.alpha, npix)?;
        check_len("out_depth", self.depth, npix)
    }
}

/// Gradients of the loss w.r.t. the image outputs (layout of [`ImageMut`]).
#[derive(Debug, Clone, Copy)]
pub struct ImageGrads<'a, F> {
    /// dL/d features image, H*W*C.
    pub features: &'a [F],
    /// dL/d alpha, H*W.
    pub alpha: &'a [F],
    /// dL/d accumulated depth, H*W.
    pub depth: &'a [F],
}

impl<F: Real> ImageGrads<'_, F> {
    /// Check lengths for `npix` pixels of `channels` features, and finiteness.
    pub fn validate(&self, npix: usize, channels: usize) -> Result<()> {
        check_len("v_features", self.features, npix * channels)?;
        check_len("v_alpha", self.alpha, npix)?;
        check_len("v_depth", self.depth, npix)?;
        check_finite("v_features", self.features)?;
        check_finite("v_alpha", self.alpha)?;
        check_finite("v_depth", self.depth)
    }
}

/// Gradients w.r.t. the splats (layout of [`Splats`]), overwritten by the backward.
#[derive(Debug)]
pub struct SplatGradsMut<'a, F> {
    /// dL/d means2d, N*2.
    pub means2d: &'a mut [F],
    /// dL/d conics, N*3.
    pub conics: &'a mut [F],
    /// dL/d depths, N.
    pub depths: &'a mut [F],
    /// dL/d opacities, N.
    pub opacities: &'a mut [F],
    /// dL/d features, N*C.
    pub features: &'a mut [F],
}

impl<F> SplatGradsMut<'_, F> {
    /// Check the gradient buffer lengths for `n` splats of `channels` features.
    pub fn check_len(&self, n: usize, channels: usize) -> Result<()> {
        check_len("grad_means2d", self.means2d, n * 2)?;
        check_len("grad_conics", self.conics, n * 3)?;
        check_len("grad_depths", self.depths, n)?;
        check_len("grad_opacities", self.opacities, n)?;
        check_len("grad_features", self.features, n * channels)
    }
}

/// What the forward keeps for the backward, plus reusable buffers. Reuse one state per
/// concurrent render to avoid first-touch page faults on large buffers.
#[derive(Debug, Default, Clone)]
pub struct RasterState {
    /// Tile lists of the last forward.
    pub bins: TileBins,
    /// Per pixel: 1 + index (in its tile's list) of the last composited splat, 0 if none.
    last: Vec<u32>,
    /// Per pixel: final transmittance.
    t_final: Vec<f32>,
    /// Visible splats packed in depth order (see `pack_splats`).
    packed: Vec<f32>,
    /// Per-intersection gradient slots (backward scratch).
    slots: Vec<f32>,
    width: u32,
    height: u32,
    channels: usize,
    forward_done: bool,
}

impl RasterState {
    /// A fresh state with no buffers.
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes held by the buffers of this state (capacity, not length).
    pub fn bytes(&self) -> usize {
        let b = &self.bins;
        4 * (b.tile_offsets.capacity()
            + b.ids.capacity()
            + b.splat_offsets.capacity()
            + b.splat_isects.capacity()
            + self.last.capacity()
            + self.t_final.capacity()
            + self.packed.capacity()
            + self.slots.capacity())
    }
}

/// A splat gathered into tile scratch: centre, conic, opacity and the rows of the tile its
/// alpha support reaches (half-open, tile-local; empty when `y0 >= y1`).
#[derive(Debug, Clone, Copy, Default)]
struct TileSplat {
    mx: f32,
    my: f32,
    ca: f32,
    cb: f32,
    cc: f32,
    op: f32,
    /// Whether the conic is positive definite (else no row culling).
    chord: bool,
    /// `2 a smax`, with smax = ln(255 op) the largest sigma where alpha >= 1/255.
    two_a_s: f64,
    /// `a c - b^2`.
    det: f64,
    /// `1 / a`.
    inv_a: f64,
    /// Row halves its support's bounding box reaches (see [`row_halves`]).
    halves: [bool; 2],
    y0: u32,
    y1: u32,
}

/// Which halves of a tile row (lanes 0-7, 8-15) can hold a pixel where splat `g` has
/// alpha >= 1/255: those its support's bounding box reaches, narrowed for wide splats to the
/// chord `dx = (-b dy +- sqrt(2 a smax - det dy^2)) / a` the row cuts from the support
/// ellipse `sigma <= smax`. (Rows outside the ellipse's vertical extent are never visited.)
/// Conservative (padded): a skipped lane would have been skipped by the alpha test anyway.
#[inline(always)]
fn row_halves(g: &TileSplat, dy: f32, px0: u32) -> [bool; 2] {
    if !(g.chord && g.halves[0] && g.halves[1]) {
        return g.halves;
    }
    let dy = dy as f64;
    let disc = g.two_a_s - g.det * dy * dy;
    let half = disc.max(0.0).sqrt() * g.inv_a;
    let centre = g.mx as f64 - g.cb as f64 * dy * g.inv_a;
    let margin =
        1e-2 + 1e-4 * (half + centre.abs()) + 1e-2 * (g.two_a_s * g.inv_a * g.inv_a).sqrt();
    let (lo, hi) = (centre - half - margin, centre + half + margin);
    let x0 = px0 as f64 + 0.5;
    [
        hi >= x0 && lo <= x0 + 7.0,
        hi >= x0 + 8.0 && lo <= x0 + 15.0,
    ]
}

impl TileSplat {
    /// The fields the row kernels need.
    #[inline(always)]
    fn row_splat(&self) -> RowSplat {
        RowSplat {
            mx: self.mx,
            my: self.my,
            ca: self.ca,
            cb: self.cb,
            cc: self.cc,
            op: self.op,
        }
    }
}

/// Row masks of splat `g` in this tile: for its rows, the halves its support reaches (see
/// [`row_halves`]); in the backward (`half_last` given) only halves where some pixel's last
/// contributor lies behind list index `k`.
#[inline(always)]
fn row_masks(
    g: &TileSplat,
    geom: TileGeom,
    half_last: Option<&[u32; 2 * LANES]>,
    k: u32,
) -> RowMasks {
    let mut m = [0u8; LANES];
    for py in g.y0..g.y1 {
        let dy = (geom.py0 + py) as f32 + 0.5 - g.my;
        let h = row_halves(g, dy, geom.px0);
        let mut bits = u8::from(h[0]) | (u8::from(h[1]) << 1);
        if let Some(hl) = half_last {
            let i = 2 * py as usize;
            if k >= hl[i] {
                bits &= !1;
            }
            if k >= hl[i + 1] {
                bits &= !2;
            }
        }
        m[py as usize] = bits;
    }
    m
}

/// Per-worker scratch, allocated once per rayon job (never per pixel). Per-pixel arrays are
/// structure-of-arrays over the tile's 256 pixels (row-major), channel-major for features.
struct Scratch {
    splats: Vec<TileSplat>,
    feats: Vec<f32>,
    t: Vec<f32>,
    acc: Vec<f32>,
    last: Vec<u32>,
    done: Vec<u32>,
    // Backward only.
    vc: Vec<f32>,
    tail: Vec<f32>,
    vr: Vec<f32>,
    gfl: Vec<[f32; LANES]>,
    gout: Vec<f32>,
}

impl Scratch {
    fn new(c1: usize) -> Self {
        Scratch {
            splats: vec![TileSplat::default(); BATCH],
            feats: vec![0.0; BATCH * c1],
            t: vec![0.0; TILE_PIXELS],
            acc: vec![0.0; TILE_PIXELS * c1],
            last: vec![0; TILE_PIXELS],
            done: vec![0; TILE_PIXELS],
            vc: vec![0.0; TILE_PIXELS * c1],
            tail: vec![0.0; TILE_PIXELS],
            vr: vec![0.0; TILE_PIXELS],
            gfl: vec![[0.0; LANES]; c1],
            gout: vec![0.0; 6 + c1],
        }
    }
}

/// Geometry of one tile: its pixel origin and the number of in-image pixels along x and y.
#[derive(Debug, Clone, Copy)]
struct TileGeom {
    px0: u32,
    py0: u32,
    w: u32,
    h: u32,
}

impl TileGeom {
    fn new(t: usize, tiles_x: u32, width: u32, height: u32) -> Self {
        let tx = t as u32 % tiles_x;
        let ty = t as u32 / tiles_x;
        let px0 = tx * TILE_SIZE;
        let py0 = ty * TILE_SIZE;
        TileGeom {
            px0,
            py0,
            w: TILE_SIZE.min(width - px0),
            h: TILE_SIZE.min(height - py0),
        }
    }

    /// x of each lane's pixel centre.
    #[inline(always)]
    fn lane_x(&self) -> [f32; LANES] {
        std::array::from_fn(|l| (self.px0 + l as u32) as f32 + 0.5)
    }
}

/// Fields of a packed splat record before its channels.
const REC_HEAD: usize = 8;

/// Pack every visible splat, in depth-rank order, into one contiguous record of
/// `REC_HEAD + c1` floats: `[mx, my, a, b, c, opacity, smax, ey, features.., depth]`, so a tile
/// reads one cache line per splat instead of one per input array. `smax = ln(255 o)` bounds
/// sigma where alpha >= 1/255 (rounded up); the ellipse sigma <= smax spans |dy| <= ey =
/// sqrt(2 smax Syy), S = conic^-1, padded outwards, infinite when the conic is not positive
/// definite and negative when the splat can never reach 1/255.
fn pack_splats(sp: &Splats<'_, f32>, bins: &TileBins, c1: usize, out: &mut Vec<f32>) {
    let stride = REC_HEAD + c1;
    let ch = c1 - 1;
    out.resize(bins.visible() * stride, 0.0);
    out.par_chunks_mut(1024 * stride)
        .enumerate()
        .for_each(|(ci, o)| {
            for (l, rec) in o.chunks_exact_mut(stride).enumerate() {
                let g = bins.splat_of_rank(ci * 1024 + l);
                let op = sp.opacities[g] as f64;
                let smax = (op * 255.0).ln();
                let (ca, cb, cc) = (
                    sp.conics[3 * g] as f64,
                    sp.conics[3 * g + 1] as f64,
                    sp.conics[3 * g + 2] as f64,
                );
                let det = ca * cc - cb * cb;
                let ey = if smax.is_nan() || smax < 0.0 {
                    -1.0
                } else if det > 0.0 && ca > 0.0 && cc > 0.0 {
                    ((2.0 * smax * ca / det).sqrt() * (1.0 + 1e-4) + 1e-3) as f32
                } else {
                    f32::INFINITY
                };
                rec[0] = sp.means2d[2 * g];
                rec[1] = sp.means2d[2 * g + 1];
                rec[2..5].copy_from_slice(&sp.conics[3 * g..3 * g + 3]);
                rec[5] = sp.opacities[g];
                rec[6] = (smax * (1.0 + 1e-6) + 1e-6) as f32;
                rec[7] = ey;
                rec[REC_HEAD..REC_HEAD + ch].copy_from_slice(&sp.features[g * ch..(g + 1) * ch]);
                rec[REC_HEAD + ch] = sp.depths[g];
            }
        });
}

/// Gather the packed records of depth ranks `ids` into the scratch, with the tile rows their
/// support reaches.
#[inline(always)]
fn gather(s: &mut Scratch, ids: &[u32], packed: &[f32], geom: TileGeom, c1: usize) {
    let stride = REC_HEAD + c1;
    for (j, &rank) in ids.iter().enumerate() {
        let rec = &packed[rank as usize * stride..(rank as usize + 1) * stride];
        let (my, e) = (rec[1], rec[7]);
        let (y0, y1) = if e < 0.0 {
            (0, 0)
        } else {
            // Pixel row y is reached when |y + 0.5 - my| <= e.
            let lo = (my as f64 - e as f64 - 0.5).ceil() - geom.py0 as f64;
            let hi = (my as f64 + e as f64 - 0.5).floor() - geom.py0 as f64 + 1.0;
            let n = geom.h as f64;
            (lo.clamp(0.0, n) as u32, hi.clamp(0.0, n) as u32)
        };
        let (a, b, c) = (rec[2] as f64, rec[3] as f64, rec[4] as f64);
        let det = a * c - b * b;
        let chord = a > 0.0 && det > 0.0;
        let smax = rec[6] as f64;
        // Horizontal half-extent of the support: sqrt(2 smax Sxx), Sxx = c / det, padded.
        let halves = if chord && e >= 0.0 {
            let ex = (2.0 * smax * c / det).max(0.0).sqrt() * (1.0 + 1e-4) + 1e-2;
            let (lo, hi) = (rec[0] as f64 - ex, rec[0] as f64 + ex);
            let x0 = geom.px0 as f64 + 0.5;
            [
                hi >= x0 && lo <= x0 + 7.0,
                hi >= x0 + 8.0 && lo <= x0 + 15.0,
            ]
        } else {
            [true, true]
        };
        s.splats[j] = TileSplat {
            mx: rec[0],
            my,
            ca: rec[2],
            cb: rec[3],
            cc: rec[4],
            op: rec[5],
            chord,
            two_a_s: 2.0 * a * smax,
            det,
            inv_a: 1.0 / a,
            halves,
            y0,
            y1,
        };
        s.feats[j * c1..(j + 1) * c1].copy_from_slice(&rec[REC_HEAD..]);
    }
}

/// Everything a tile kernel reads besides its scratch.
#[derive(Clone, Copy)]
struct TileInputs<'a> {
    bins: &'a TileBins,
    packed: &'a [f32],
    alpha_max: f32,
}

/// Composite one tile (see the module notes). Returns (evaluated, blended) pair counts.
#[inline(always)]
fn forward_tile<const K: usize, const AVX: bool>(
    s: &mut Scratch,
    inp: TileInputs<'_>,
    t: usize,
    geom: TileGeom,
    c1_dyn: usize,
) -> (u64, u64) {
    let c1 = if K > 0 { K } else { c1_dyn };
    let ids = &inp.bins.ids[inp.bins.tile_range(t)];
    s.t.fill(1.0);
    s.acc.fill(0.0);
    s.last.fill(0);
    // Pixels outside the image start out done.
    for py in 0..TILE_SIZE {
        for px in 0..TILE_SIZE {
            s.done[(py * TILE_SIZE + px) as usize] = u32::from(px >= geom.w || py >= geom.h);
        }
    }
    let active = (geom.w * geom.h) as usize;
    let mut n_done = 0usize;
    let (mut evaluated, mut blended) = (0u64, 0u64);
    let lim = Limits {
        alpha_min: ALPHA_MIN as f32,
        alpha_max: inp.alpha_max,
        t_min: T_MIN as f32,
    };
    let lane_x = geom.lane_x();
    let mut start = 0;
    'batches: while start < ids.len() {
        let end = (start + BATCH).min(ids.len());
        gather(s, &ids[start..end], inp.packed, geom, c1);
        for j in 0..end - start {
            let g = s.splats[j];
            if g.y0 >= g.y1 {
                continue;
            }
            let k1 = (start + j + 1) as u32;
            let rows = row_masks(&g, geom, None, 0);
            let rs = g.row_splat();
            let f = &s.feats[j * c1..(j + 1) * c1];
            let mut px = ForwardPixels {
                t: &mut s.t,
                done: &mut s.done,
                last: &mut s.last,
                acc: &mut s.acc,
            };
            let (n_eval, n_blend, n_term) = if AVX {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: AVX is only true when AVX2 was detected at run time.
                unsafe {
                    lanes::avx2::forward_splat::<K>(
                        c1, &rs, &lim, k1, &lane_x, geom.py0, &rows, f, &mut px,
                    )
                }
                #[cfg(not(target_arch = "x86_64"))]
                unreachable!()
            } else {
                lanes::portable::forward_splat::<K>(
                    c1, &rs, &lim, k1, &lane_x, geom.py0, &rows, f, &mut px,
                )
            };
            evaluated += n_eval as u64;
            blended += n_blend as u64;
            n_done += n_term as usize;
            if n_done >= active {
                break 'batches;
            }
        }
        start = end;
    }
    (evaluated, blended)
}

/// [`forward_tile`] compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn forward_tile_avx2<const K: usize>(
    s: &mut Scratch,
    inp: TileInputs<'_>,
    t: usize,
    geom: TileGeom,
    c1: usize,
) -> (u64, u64) {
    forward_tile::<K, true>(s, inp, t, geom, c1)
}

static SIMD_ENABLED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(true);

/// Allow (default) or forbid the AVX2 row kernels. Both paths give bit-identical results; this
/// switch exists so tests and benchmarks can compare them.
pub fn set_simd_enabled(enabled: bool) {
    SIMD_ENABLED.store(enabled, std::sync::atomic::Ordering::Relaxed);
}

/// Whether the AVX2 kernels will be used: allowed and supported by this CPU.
pub fn simd_active() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        SIMD_ENABLED.load(std::sync::atomic::Ordering::Relaxed)
            && std::is_x86_feature_detected!("avx2")
            && std::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Everything one forward needs, shared by all tile tasks.
struct ForwardJob<'a> {
    inp: TileInputs<'a>,
    width: u32,
    height: u32,
    background: &'a [f32],
    c1: usize,
    o_feat: SharedMut<f32>,
    o_alpha: SharedMut<f32>,
    o_depth: SharedMut<f32>,
    o_last: SharedMut<u32>,
    o_t: SharedMut<f32>,
}

impl ForwardJob<'_> {
    /// Composite every tile; `K` is the channel count (features + depth) when non-zero, so the
    /// per-pixel channel loops unroll for the common cases; `K = 0` reads it at run time.
    fn run<const K: usize>(&self) -> (u64, u64) {
        let c1 = if K > 0 { K } else { self.c1 };
        let ch = c1 - 1;
        let (width, height) = (self.width, self.height);
        let bins = self.inp.bins;
        let num_tiles = (bins.tiles_x * bins.tiles_y) as usize;
        let avx2 = simd_active();
        (0..num_tiles)
            .into_par_iter()
            .map_init(
                || Scratch::new(c1),
                |s, t| {
                    let geom = TileGeom::new(t, bins.tiles_x, width, height);
                    let counts = if avx2 {
                        #[cfg(target_arch = "x86_64")]
                        // SAFETY: AVX2 and FMA were detected at run time.
                        unsafe {
                            forward_tile_avx2::<K>(s, self.inp, t, geom, c1)
                        }
                        #[cfg(not(target_arch = "x86_64"))]
                        unreachable!()
                    } else {
                        forward_tile::<K, false>(s, self.inp, t, geom, c1)
                    };
                    for py in 0..geom.h {
                        for px in 0..geom.w {
                            let p = (py * TILE_SIZE + px) as usize;
                            let pix = ((geom.py0 + py) * width + geom.px0 + px) as usize;
                            let tf = s.t[p];
                            // SAFETY: pixel `pix` belongs to tile `t` only; each tile is handled
                            // by exactly one task.
                            unsafe {
                                for c in 0..ch {
                                    self.o_feat.write(
                                        pix * ch + c,
                                        s.acc[c * TILE_PIXELS + p] + tf * self.background[c],
                                    );
                                }
                                self.o_alpha.write(pix, 1.0 - tf);
                                self.o_depth.write(pix, s.acc[ch * TILE_PIXELS + p]);
                                self.o_last.write(pix, s.last[p]);
                                self.o_t.write(pix, tf);
                            }
                        }
                    }
                    counts
                },
            )
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
    }
}

/// Composite `splats` into a `width` x `height` image (f32 fast path). Keeps what the backward
/// needs in `state`. Returns the work counters.
pub fn rasterize_forward(
    splats: &Splats<'_, f32>,
    width: u32,
    height: u32,
    background: &[f32],
    settings: &BlendSettings,
    state: &mut RasterState,
    out: ImageMut<'_, f32>,
) -> Result<Counters> {
    splats.validate(background)?;
    settings.validate()?;
    check_image_size(width, height)?;
    let npix = (width * height) as usize;
    let ch = splats.channels;
    out.check_len(npix, ch)?;
    state
        .bins
        .build(splats.means2d, splats.radii, splats.depths, width, height)?;
    pack_splats(splats, &state.bins, ch + 1, &mut state.packed);
    state.last.resize(npix, 0);
    state.t_final.resize(npix, 1.0);
    state.width = width;
    state.height = height;
    state.channels = ch;
    state.forward_done = true;

    let c1 = ch + 1;
    let job = ForwardJob {
        inp: TileInputs {
            bins: &state.bins,
            packed: &state.packed,
            alpha_max: settings.alpha_max as f32,
        },
        width,
        height,
        background,
        c1,
        o_feat: SharedMut::new(out.features),
        o_alpha: SharedMut::new(out.alpha),
        o_depth: SharedMut::new(out.depth),
        o_last: SharedMut::new(&mut state.last),
        o_t: SharedMut::new(&mut state.t_final),
    };
    let (evaluated, blended) = match c1 {
        2 => job.run::<2>(),
        4 => job.run::<4>(),
        _ => job.run::<0>(),
    };
    let visible = splats
        .radii
        .chunks_exact(2)
        .filter(|r| r[0] > 0 && r[1] > 0)
        .count() as u64;
    Ok(Counters {
        visible,
        intersections: state.bins.len() as u64,
        evaluated,
        blended,
    })
}

/// Backward of one tile: writes each listed splat's gradient (summed over this tile's pixels)
/// into its intersection slot.
#[inline(always)]
fn backward_tile<const K: usize, const AVX: bool>(
    s: &mut Scratch,
    inp: TileInputs<'_>,
    t: usize,
    geom: TileGeom,
    c1_dyn: usize,
    slots: &SharedMut<f32>,
) {
    let c1 = if K > 0 { K } else { c1_dyn };
    let range = inp.bins.tile_range(t);
    let base = range.start;
    let ids = &inp.bins.ids[range];
    let stride = 6 + c1;
    let max_last = s.last.iter().copied().max().unwrap_or(0) as usize;
    // Per row half: the furthest last contributor, to skip halves a splat cannot affect.
    let mut half_last = [0u32; 2 * LANES];
    for (i, hl) in half_last.iter_mut().enumerate() {
        *hl = s.last[i * 8..i * 8 + 8].iter().copied().max().unwrap_or(0);
    }
    // Slots of splats behind every pixel's last contributor get zero.
    for k in max_last..ids.len() {
        for q in 0..stride {
            // SAFETY: slot ranges of different tiles are disjoint (one tile per task).
            unsafe { slots.write((base + k) * stride + q, 0.0) };
        }
    }
    let lim = Limits {
        alpha_min: ALPHA_MIN as f32,
        alpha_max: inp.alpha_max,
        t_min: T_MIN as f32,
    };
    let lane_x = geom.lane_x();
    // Per-lane feature-gradient accumulators and one splat's summed gradient.
    let mut gfl = std::mem::take(&mut s.gfl);
    let mut out = std::mem::take(&mut s.gout);
    let mut end = max_last;
    while end > 0 {
        let start = end.saturating_sub(BATCH);
        gather(s, &ids[start..end], inp.packed, geom, c1);
        for j in (0..end - start).rev() {
            let k = (start + j) as u32;
            let g = s.splats[j];
            let rows = row_masks(&g, geom, Some(&half_last), k);
            let rs = g.row_splat();
            let f = &s.feats[j * c1..(j + 1) * c1];
            let mut px = BackwardPixels {
                t: &mut s.t,
                vr: &mut s.vr,
                tail: &s.tail,
                last: &s.last,
                vc: &s.vc,
            };
            let o = &mut out[..stride];
            if AVX {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: AVX is only true when AVX2 was detected at run time.
                unsafe {
                    lanes::avx2::backward_splat::<K>(
                        c1, &rs, &lim, k, &lane_x, geom.py0, &rows, f, &mut px, &mut gfl, o,
                    );
                }
            } else {
                lanes::portable::backward_splat::<K>(
                    c1, &rs, &lim, k, &lane_x, geom.py0, &rows, f, &mut px, &mut gfl, o,
                );
            }
            let base_slot = (base + k as usize) * stride;
            for (q, v) in o.iter().enumerate() {
                // SAFETY: slot `base + k` belongs to this tile only.
                unsafe { slots.write(base_slot + q, *v) };
            }
        }
        end = start;
    }
    s.gfl = gfl;
    s.gout = out;
}

/// [`backward_tile`] compiled with AVX2 enabled.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn backward_tile_avx2<const K: usize>(
    s: &mut Scratch,
    inp: TileInputs<'_>,
    t: usize,
    geom: TileGeom,
    c1: usize,
    slots: &SharedMut<f32>,
) {
    backward_tile::<K, true>(s, inp, t, geom, c1, slots);
}

/// Everything one backward needs, shared by all tile tasks.
struct BackwardJob<'a> {
    inp: TileInputs<'a>,
    last: &'a [u32],
    t_final: &'a [f32],
    v: &'a ImageGrads<'a, f32>,
    width: u32,
    height: u32,
    background: &'a [f32],
    c1: usize,
    slots: &'a SharedMut<f32>,
}

impl BackwardJob<'_> {
    /// Back-propagate every tile into the intersection slots (`K` as in [`ForwardJob::run`]).
    fn run<const K: usize>(&self) {
        let c1 = if K > 0 { K } else { self.c1 };
        let ch = c1 - 1;
        let (width, height, v) = (self.width, self.height, self.v);
        let bins = self.inp.bins;
        let num_tiles = (bins.tiles_x * bins.tiles_y) as usize;
        let avx2 = simd_active();
        (0..num_tiles).into_par_iter().for_each_init(
            || Scratch::new(c1),
            |s, t| {
                let geom = TileGeom::new(t, bins.tiles_x, width, height);
                s.last.fill(0);
                s.t.fill(1.0);
                s.vr.fill(0.0);
                s.tail.fill(0.0);
                s.vc.fill(0.0);
                for py in 0..geom.h {
                    for px in 0..geom.w {
                        let p = (py * TILE_SIZE + px) as usize;
                        let pix = ((geom.py0 + py) * width + geom.px0 + px) as usize;
                        let tf = self.t_final[pix];
                        s.last[p] = self.last[pix];
                        s.t[p] = tf;
                        let mut vbg = 0.0f32;
                        for c in 0..ch {
                            let vcv = v.features[pix * ch + c];
                            s.vc[c * TILE_PIXELS + p] = vcv;
                            vbg += vcv * self.background[c];
                        }
                        s.vc[ch * TILE_PIXELS + p] = v.depth[pix];
                        // dL/dalpha_i gains -(T_final (v . bg) - v_alpha T_final) / (1 - alpha_i).
                        s.tail[p] = tf * (vbg - v.alpha[pix]);
                    }
                }
                if avx2 {
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: AVX2 and FMA were detected at run time.
                    unsafe {
                        backward_tile_avx2::<K>(s, self.inp, t, geom, c1, self.slots);
                    }
                } else {
                    backward_tile::<K, false>(s, self.inp, t, geom, c1, self.slots);
                }
            },
        );
    }
}

/// Backward of [`rasterize_forward`] (f32): given dL/d(image outputs), writes dL/d(splats) into
/// `grads` (overwriting). `splats`, `background` and `settings` must be the forward's.
#[allow(clippy::too_many_arguments)]
pub fn rasterize_backward(
    splats: &Splats<'_, f32>,
    width: u32,
    height: u32,
    background: &[f32],
    settings: &BlendSettings,
    state: &mut RasterState,
    v: &ImageGrads<'_, f32>,
    grads: SplatGradsMut<'_, f32>,
) -> Result<()> {
    /// Splats a task of the final per-splat reduction sums.
    const CH: usize = 1024;
    splats.validate(background)?;
    settings.validate()?;
    if !state.forward_done
        || state.width != width
        || state.height != height
        || state.channels != splats.channels
    {
        return Err(RasterError::invalid(
            "state",
            "backward needs the state of a forward call with the same image size and channels",
        ));
    }
    let npix = (width * height) as usize;
    let n = splats.len();
    let ch = splats.channels;
    v.validate(npix, ch)?;
    grads.check_len(n, ch)?;
    let c1 = ch + 1;
    let stride = 6 + c1;
    let m = state.bins.len();
    state.slots.resize(m * stride, 0.0);
    let slots = SharedMut::new(&mut state.slots);
    let bins = &state.bins;
    let job = BackwardJob {
        inp: TileInputs {
            bins,
            packed: &state.packed,
            alpha_max: settings.alpha_max as f32,
        },
        last: &state.last,
        t_final: &state.t_final,
        v,
        width,
        height,
        background,
        c1,
        slots: &slots,
    };
    match c1 {
        2 => job.run::<2>(),
        4 => job.run::<4>(),
        _ => job.run::<0>(),
    }

    // Reduce slots per splat, in CSR order (deterministic).
    let slots = &state.slots;
    let offs = &bins.splat_offsets;
    let isects = &bins.splat_isects;
    grads
        .means2d
        .par_chunks_mut(2 * CH)
        .zip(grads.conics.par_chunks_mut(3 * CH))
        .zip(grads.depths.par_chunks_mut(CH))
        .zip(grads.opacities.par_chunks_mut(CH))
        .zip(grads.features.par_chunks_mut(ch * CH))
        .enumerate()
        .for_each(|(ci, ((((gm, gco), gd), go), gf))| {
            let mut acc = vec![0.0f32; stride];
            for l in 0..gd.len() {
                let g = ci * CH + l;
                acc.fill(0.0);
                for &pos in &isects[offs[g] as usize..offs[g + 1] as usize] {
                    let sl = &slots[pos as usize * stride..(pos as usize + 1) * stride];
                    for q in 0..stride {
                        acc[q] += sl[q];
                    }
                }
                gm[2 * l] = acc[0];
                gm[2 * l + 1] = acc[1];
                gco[3 * l..3 * l + 3].copy_from_slice(&acc[2..5]);
                go[l] = acc[5];
                gf[l * ch..(l + 1) * ch].copy_from_slice(&acc[6..6 + ch]);
                gd[l] = acc[6 + ch];
            }
        });
    Ok(())
}

/// Check an image size (each side in 1..=[`crate::camera::MAX_IMAGE_SIDE`]).
pub fn check_image_size(width: u32, height: u32) -> Result<()> {
    let max = crate::camera::MAX_IMAGE_SIDE;
    for (name, v) in [("width", width), ("height", height)] {
        if v == 0 || v > max {
            return Err(RasterError::invalid(
                name,
                format!("image side must be in 1..={max}, got {v}"),
            ));
        }
    }
    Ok(())
}

/// Element types the compositor accepts: f32 runs the tiled fast path (keeping what its
/// backward needs in the state), f64 runs the plain per-pixel reference (state unused). Lets
/// callers such as the Python bindings write one generic path for both.
pub trait Composite: Real {
    /// Forward compositing; see [`rasterize_forward`].
    fn composite_forward(
        splats: &Splats<'_, Self>,
        width: u32,
        height: u32,
        background: &[Self],
        settings: &BlendSettings,
        state: &mut RasterState,
        out: ImageMut<'_, Self>,
    ) -> Result<Counters>;

    /// Backward compositing; see [`rasterize_backward`].
    #[allow(clippy::too_many_arguments)]
    fn composite_backward(
        splats: &Splats<'_, Self>,
        width: u32,
        height: u32,
        background: &[Self],
        settings: &BlendSettings,
        state: &mut RasterState,
        v: &ImageGrads<'_, Self>,
        grads: SplatGradsMut<'_, Self>,
    ) -> Result<()>;
}

impl Composite for f32 {
    fn composite_forward(
        splats: &Splats<'_, f32>,
        width: u32,
        height: u32,
        background: &[f32],
        settings: &BlendSettings,
        state: &mut RasterState,
        out: ImageMut<'_, f32>,
    ) -> Result<Counters> {
        rasterize_forward(splats, width, height, background, settings, state, out)
    }

    fn composite_backward(
        splats: &Splats<'_, f32>,
        width: u32,
        height: u32,
        background: &[f32],
        settings: &BlendSettings,
        state: &mut RasterState,
        v: &ImageGrads<'_, f32>,
        grads: SplatGradsMut<'_, f32>,
    ) -> Result<()> {
        rasterize_backward(splats, width, height, background, settings, state, v, grads)
    }
}

impl Composite for f64 {
    fn composite_forward(
        splats: &Splats<'_, f64>,
        width: u32,
        height: u32,
        background: &[f64],
        settings: &BlendSettings,
        _state: &mut RasterState,
        out: ImageMut<'_, f64>,
    ) -> Result<Counters> {
        crate::reference::rasterize_forward_reference(
            splats, width, height, background, settings, out,
        )
    }

    fn composite_backward(
        splats: &Splats<'_, f64>,
        width: u32,
        height: u32,
        background: &[f64],
        settings: &BlendSettings,
        _state: &mut RasterState,
        v: &ImageGrads<'_, f64>,
        grads: SplatGradsMut<'_, f64>,
    ) -> Result<()> {
        crate::reference::rasterize_backward_reference(
            splats, width, height, background, settings, v, grads,
        )
    }
}
