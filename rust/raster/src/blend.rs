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
use crate::real::Real;
use crate::TILE_SIZE;
use rayon::prelude::*;

/// Alpha below which a splat is skipped at a pixel (3DGS).
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// A pixel stops (excluding the current splat) when its transmittance would drop below this.
pub const T_MIN: f64 = 1e-4;
/// Splats gathered per batch.
const BATCH: usize = 256;
const TILE_PIXELS: usize = (TILE_SIZE * TILE_SIZE) as usize;

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
            + self.slots.capacity())
    }
}

/// A splat gathered into tile scratch: centre, conic, opacity and its pixel box within the tile
/// (half-open, tile-local; empty when `x0 >= x1`).
#[derive(Debug, Clone, Copy, Default)]
struct TileSplat {
    mx: f32,
    my: f32,
    ca: f32,
    cb: f32,
    cc: f32,
    op: f32,
    x0: u32,
    x1: u32,
    y0: u32,
    y1: u32,
}

/// Per-worker scratch, allocated once per rayon job (never per pixel).
struct Scratch {
    splats: Vec<TileSplat>,
    feats: Vec<f32>,
    t: Vec<f32>,
    acc: Vec<f32>,
    last: Vec<u32>,
    done: Vec<bool>,
    // Backward only.
    vc: Vec<f32>,
    tail: Vec<f32>,
    vr: Vec<f32>,
    gf: Vec<f32>,
}

impl Scratch {
    fn new(c1: usize) -> Self {
        Scratch {
            splats: vec![TileSplat::default(); BATCH],
            feats: vec![0.0; BATCH * c1],
            t: vec![0.0; TILE_PIXELS],
            acc: vec![0.0; TILE_PIXELS * c1],
            last: vec![0; TILE_PIXELS],
            done: vec![false; TILE_PIXELS],
            vc: vec![0.0; TILE_PIXELS * c1],
            tail: vec![0.0; TILE_PIXELS],
            vr: vec![0.0; TILE_PIXELS],
            gf: vec![0.0; c1],
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
}

/// Gather splats `ids` into the scratch (centre, conic, opacity, features + depth channel) and
/// compute each one's exact alpha-support box clipped to the tile.
#[inline]
fn gather(s: &mut Scratch, ids: &[u32], sp: &Splats<'_, f32>, geom: TileGeom, c1: usize) {
    let ch = sp.channels;
    for (j, &gid) in ids.iter().enumerate() {
        let g = gid as usize;
        let (mx, my) = (sp.means2d[2 * g], sp.means2d[2 * g + 1]);
        let (ca, cb, cc) = (sp.conics[3 * g], sp.conics[3 * g + 1], sp.conics[3 * g + 2]);
        let op = sp.opacities[g];
        let mut ts = TileSplat {
            mx,
            my,
            ca,
            cb,
            cc,
            op,
            ..Default::default()
        };
        // alpha >= 1/255 needs sigma <= ln(255 o); the ellipse sigma <= s spans
        // |dx| <= sqrt(2 s Sxx), |dy| <= sqrt(2 s Syy) with S = inverse(conic).
        let smax = (op as f64 * 255.0).ln();
        if smax >= 0.0 {
            let det = ca as f64 * cc as f64 - cb as f64 * cb as f64;
            let (ex, ey) = if det > 0.0 && ca > 0.0 && cc > 0.0 {
                let ex = (2.0 * smax * cc as f64 / det).sqrt() * (1.0 + 1e-4) + 1e-3;
                let ey = (2.0 * smax * ca as f64 / det).sqrt() * (1.0 + 1e-4) + 1e-3;
                (ex, ey)
            } else {
                (f64::INFINITY, f64::INFINITY)
            };
            let range = |m: f32, e: f64, o: u32, n: u32| -> (u32, u32) {
                // Pixel p (global) is in range when |p + 0.5 - m| <= e.
                let lo = (m as f64 - e - 0.5).ceil() - o as f64;
                let hi = (m as f64 + e - 0.5).floor() - o as f64 + 1.0;
                (
                    lo.clamp(0.0, n as f64) as u32,
                    hi.clamp(0.0, n as f64) as u32,
                )
            };
            let (x0, x1) = range(mx, ex, geom.px0, geom.w);
            let (y0, y1) = range(my, ey, geom.py0, geom.h);
            ts.x0 = x0;
            ts.x1 = x1;
            ts.y0 = y0;
            ts.y1 = y1;
        }
        s.splats[j] = ts;
        let f = &mut s.feats[j * c1..(j + 1) * c1];
        f[..ch].copy_from_slice(&sp.features[g * ch..(g + 1) * ch]);
        f[ch] = sp.depths[g];
    }
}

/// Composite one tile. Returns (evaluated, blended) pair counts.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn forward_tile(
    s: &mut Scratch,
    bins: &TileBins,
    t: usize,
    sp: &Splats<'_, f32>,
    geom: TileGeom,
    c1: usize,
    alpha_max: f32,
) -> (u64, u64) {
    let range = bins.tile_range(t);
    let ids = &bins.ids[range];
    s.t.fill(1.0);
    s.acc.fill(0.0);
    s.last.fill(0);
    s.done.fill(false);
    let active = (geom.w * geom.h) as usize;
    let mut n_done = 0usize;
    let (mut evaluated, mut blended) = (0u64, 0u64);
    let alpha_min = ALPHA_MIN as f32;
    let t_min = T_MIN as f32;
    let mut start = 0;
    'batches: while start < ids.len() && n_done < active {
        let end = (start + BATCH).min(ids.len());
        gather(s, &ids[start..end], sp, geom, c1);
        for j in 0..end - start {
            let g = s.splats[j];
            if g.x0 >= g.x1 || g.y0 >= g.y1 {
                continue;
            }
            let k1 = (start + j + 1) as u32;
            for py in g.y0..g.y1 {
                let dy = (geom.py0 + py) as f32 + 0.5 - g.my;
                let row = (py * TILE_SIZE) as usize;
                for px in g.x0..g.x1 {
                    let p = row + px as usize;
                    if s.done[p] {
                        continue;
                    }
                    let dx = (geom.px0 + px) as f32 + 0.5 - g.mx;
                    evaluated += 1;
                    let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
                    if sigma < 0.0 {
                        continue;
                    }
                    let alpha = (g.op * (-sigma).exp()).min(alpha_max);
                    if alpha < alpha_min {
                        continue;
                    }
                    let tp = s.t[p];
                    let next_t = tp * (1.0 - alpha);
                    if next_t < t_min {
                        s.done[p] = true;
                        n_done += 1;
                        if n_done == active {
                            break 'batches;
                        }
                        continue;
                    }
                    let w = alpha * tp;
                    let f = &s.feats[j * c1..(j + 1) * c1];
                    let acc = &mut s.acc[p * c1..(p + 1) * c1];
                    for c in 0..c1 {
                        acc[c] += f[c] * w;
                    }
                    s.t[p] = next_t;
                    s.last[p] = k1;
                    blended += 1;
                }
            }
        }
        start = end;
    }
    (evaluated, blended)
}

/// Everything one forward needs, shared by all tile tasks.
struct ForwardJob<'a> {
    splats: &'a Splats<'a, f32>,
    bins: &'a TileBins,
    width: u32,
    height: u32,
    background: &'a [f32],
    alpha_max: f32,
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
        let num_tiles = (self.bins.tiles_x * self.bins.tiles_y) as usize;
        (0..num_tiles)
            .into_par_iter()
            .map_init(
                || Scratch::new(c1),
                |s, t| {
                    let geom = TileGeom::new(t, self.bins.tiles_x, width, height);
                    let counts =
                        forward_tile(s, self.bins, t, self.splats, geom, c1, self.alpha_max);
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
                                        s.acc[p * c1 + c] + tf * self.background[c],
                                    );
                                }
                                self.o_alpha.write(pix, 1.0 - tf);
                                self.o_depth.write(pix, s.acc[p * c1 + ch]);
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
    check_len("out_features", out.features, npix * ch)?;
    check_len("out_alpha", out.alpha, npix)?;
    check_len("out_depth", out.depth, npix)?;
    state
        .bins
        .build(splats.means2d, splats.radii, splats.depths, width, height)?;
    state.last.resize(npix, 0);
    state.t_final.resize(npix, 1.0);
    state.width = width;
    state.height = height;
    state.channels = ch;
    state.forward_done = true;

    let c1 = ch + 1;
    let alpha_max = settings.alpha_max as f32;
    let bins = &state.bins;
    let o_feat = SharedMut::new(out.features);
    let o_alpha = SharedMut::new(out.alpha);
    let o_depth = SharedMut::new(out.depth);
    let o_last = SharedMut::new(&mut state.last);
    let o_t = SharedMut::new(&mut state.t_final);
    let job = ForwardJob {
        splats,
        bins,
        width,
        height,
        background,
        alpha_max,
        c1,
        o_feat,
        o_alpha,
        o_depth,
        o_last,
        o_t,
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
#[allow(clippy::too_many_arguments)]
fn backward_tile(
    s: &mut Scratch,
    bins: &TileBins,
    t: usize,
    sp: &Splats<'_, f32>,
    geom: TileGeom,
    c1: usize,
    alpha_max: f32,
    slots: &SharedMut<f32>,
) {
    let range = bins.tile_range(t);
    let base = range.start;
    let ids = &bins.ids[range];
    let stride = 6 + c1;
    let max_last = s.last.iter().copied().max().unwrap_or(0) as usize;
    // Slots of splats behind every pixel's last contributor get zero.
    for k in max_last..ids.len() {
        for q in 0..stride {
            // SAFETY: slot ranges of different tiles are disjoint (one tile per task).
            unsafe { slots.write((base + k) * stride + q, 0.0) };
        }
    }
    let alpha_min = ALPHA_MIN as f32;
    let mut end = max_last;
    while end > 0 {
        let start = end.saturating_sub(BATCH);
        gather(s, &ids[start..end], sp, geom, c1);
        for j in (0..end - start).rev() {
            let k = start + j;
            let g = s.splats[j];
            let (mut gmx, mut gmy, mut ga, mut gb, mut gc, mut go) =
                (0f32, 0f32, 0f32, 0f32, 0f32, 0f32);
            s.gf.fill(0.0);
            if g.x0 < g.x1 && g.y0 < g.y1 {
                let f = &s.feats[j * c1..(j + 1) * c1];
                for py in g.y0..g.y1 {
                    let dy = (geom.py0 + py) as f32 + 0.5 - g.my;
                    let row = (py * TILE_SIZE) as usize;
                    for px in g.x0..g.x1 {
                        let p = row + px as usize;
                        if k as u32 >= s.last[p] {
                            continue;
                        }
                        let dx = (geom.px0 + px) as f32 + 0.5 - g.mx;
                        let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
                        if sigma < 0.0 {
                            continue;
                        }
                        let vis = (-sigma).exp();
                        let raw = g.op * vis;
                        let alpha = raw.min(alpha_max);
                        if alpha < alpha_min {
                            continue;
                        }
                        let one_m = 1.0 - alpha;
                        let ti = s.t[p] / one_m;
                        let w = alpha * ti;
                        let vc = &s.vc[p * c1..(p + 1) * c1];
                        let mut vf = 0.0f32;
                        for c in 0..c1 {
                            vf += vc[c] * f[c];
                            s.gf[c] += w * vc[c];
                        }
                        let v_alpha = ti * vf - (s.vr[p] + s.tail[p]) / one_m;
                        s.vr[p] += w * vf;
                        s.t[p] = ti;
                        if raw <= alpha_max {
                            go += v_alpha * vis;
                            let v_sigma = -v_alpha * alpha;
                            // sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, d = pixel - mean.
                            ga += 0.5 * v_sigma * dx * dx;
                            gb += v_sigma * dx * dy;
                            gc += 0.5 * v_sigma * dy * dy;
                            gmx -= v_sigma * (g.ca * dx + g.cb * dy);
                            gmy -= v_sigma * (g.cc * dy + g.cb * dx);
                        }
                    }
                }
            }
            let o = (base + k) * stride;
            // SAFETY: slot `base + k` belongs to this tile only.
            unsafe {
                slots.write(o, gmx);
                slots.write(o + 1, gmy);
                slots.write(o + 2, ga);
                slots.write(o + 3, gb);
                slots.write(o + 4, gc);
                slots.write(o + 5, go);
                for c in 0..c1 {
                    slots.write(o + 6 + c, s.gf[c]);
                }
            }
        }
        end = start;
    }
}

/// Everything one backward needs, shared by all tile tasks.
struct BackwardJob<'a> {
    splats: &'a Splats<'a, f32>,
    bins: &'a TileBins,
    last: &'a [u32],
    t_final: &'a [f32],
    v: &'a ImageGrads<'a, f32>,
    width: u32,
    height: u32,
    background: &'a [f32],
    alpha_max: f32,
    c1: usize,
    slots: &'a SharedMut<f32>,
}

impl BackwardJob<'_> {
    /// Back-propagate every tile into the intersection slots (`K` as in [`ForwardJob::run`]).
    fn run<const K: usize>(&self) {
        let c1 = if K > 0 { K } else { self.c1 };
        let ch = c1 - 1;
        let (width, height, v) = (self.width, self.height, self.v);
        let num_tiles = (self.bins.tiles_x * self.bins.tiles_y) as usize;
        (0..num_tiles).into_par_iter().for_each_init(
            || Scratch::new(c1),
            |s, t| {
                let geom = TileGeom::new(t, self.bins.tiles_x, width, height);
                s.last.fill(0);
                for py in 0..geom.h {
                    for px in 0..geom.w {
                        let p = (py * TILE_SIZE + px) as usize;
                        let pix = ((geom.py0 + py) * width + geom.px0 + px) as usize;
                        let tf = self.t_final[pix];
                        s.last[p] = self.last[pix];
                        s.t[p] = tf;
                        s.vr[p] = 0.0;
                        let mut vbg = 0.0f32;
                        for c in 0..ch {
                            let vcv = v.features[pix * ch + c];
                            s.vc[p * c1 + c] = vcv;
                            vbg += vcv * self.background[c];
                        }
                        s.vc[p * c1 + ch] = v.depth[pix];
                        // dL/dalpha_i gains -(T_final (v . bg) - v_alpha T_final) / (1 - alpha_i).
                        s.tail[p] = tf * (vbg - v.alpha[pix]);
                    }
                }
                backward_tile(
                    s,
                    self.bins,
                    t,
                    self.splats,
                    geom,
                    c1,
                    self.alpha_max,
                    self.slots,
                );
            },
        )
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
    check_len("v_features", v.features, npix * ch)?;
    check_len("v_alpha", v.alpha, npix)?;
    check_len("v_depth", v.depth, npix)?;
    check_finite("v_features", v.features)?;
    check_finite("v_alpha", v.alpha)?;
    check_finite("v_depth", v.depth)?;
    check_len("grad_means2d", grads.means2d, n * 2)?;
    check_len("grad_conics", grads.conics, n * 3)?;
    check_len("grad_depths", grads.depths, n)?;
    check_len("grad_opacities", grads.opacities, n)?;
    check_len("grad_features", grads.features, n * ch)?;
    let c1 = ch + 1;
    let stride = 6 + c1;
    let alpha_max = settings.alpha_max as f32;
    let m = state.bins.len();
    state.slots.resize(m * stride, 0.0);
    let slots = SharedMut::new(&mut state.slots);
    let bins = &state.bins;
    let last = &state.last;
    let t_final = &state.t_final;
    let job = BackwardJob {
        splats,
        bins,
        last,
        t_final,
        v,
        width,
        height,
        background,
        alpha_max,
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
    const CH: usize = 1024;
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

/// Check an image size.
pub(crate) fn check_image_size(width: u32, height: u32) -> Result<()> {
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
