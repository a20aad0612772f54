//! The per-row compositing kernels: one tile row of 16 pixels against one splat, forward and
//! backward. Two implementations with the same arithmetic, operation for operation: a portable
//! one (plain loops) and an AVX2 one (explicit 8-lane intrinsics, two halves per row). Keeping
//! the order of every floating-point operation identical makes the two bit-identical, which a
//! test checks. Explicit intrinsics avoid what auto-vectorisation produced here: masked stores
//! (`vmaskmovps`), which are microcoded and slow on AMD cores.
// The portable kernels combine per-lane conditions with `&` as the AVX2 ones combine masks:
// branch-free, and the same operations in the same order on both paths.
#![allow(clippy::needless_bitwise_bool)]

use crate::TILE_SIZE;
use sync4d_scalar::exp::{exp_poly, EXP_HI, EXP_LO, EXP_P, LN2_HI, LN2_LO};

/// Pixels per tile row.
pub(crate) const LANES: usize = TILE_SIZE as usize;
/// Pixels per tile.
pub(crate) const TILE_PIXELS: usize = LANES * LANES;

/// The kernels take `K`, the channel count (features + depth) when non-zero, so their channel
/// loops unroll; `K = 0` reads `c1_dyn` at run time.
///
/// One splat as the row kernels see it: centre, conic, opacity.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RowSplat {
    pub mx: f32,
    pub my: f32,
    pub ca: f32,
    pub cb: f32,
    pub cc: f32,
    pub op: f32,
}

/// Which tile rows a splat visits and, per row, which halves (bit 0: lanes 0-7, bit 1: 8-15).
pub(crate) type RowMasks = [u8; LANES];

/// Per-pixel state of a tile in the forward (each `TILE_PIXELS` long; `acc` channel-major).
pub(crate) struct ForwardPixels<'a> {
    pub t: &'a mut [f32],
    pub done: &'a mut [u32],
    pub last: &'a mut [u32],
    pub acc: &'a mut [f32],
}

/// Per-pixel state of a tile in the backward (each `TILE_PIXELS` long; `vc` channel-major).
pub(crate) struct BackwardPixels<'a> {
    pub t: &'a mut [f32],
    pub vr: &'a mut [f32],
    pub tail: &'a [f32],
    pub last: &'a [u32],
    pub vc: &'a [f32],
}

impl ForwardPixels<'_> {
    fn check(&self, c1: usize, f: &[f32]) {
        assert!(
            self.t.len() == TILE_PIXELS
                && self.done.len() == TILE_PIXELS
                && self.last.len() == TILE_PIXELS
                && self.acc.len() >= c1 * TILE_PIXELS
                && f.len() >= c1
        );
    }
}

impl BackwardPixels<'_> {
    fn check(&self, c1: usize, f: &[f32], out: &[f32]) {
        assert!(
            self.t.len() == TILE_PIXELS
                && self.vr.len() == TILE_PIXELS
                && self.tail.len() == TILE_PIXELS
                && self.last.len() == TILE_PIXELS
                && self.vc.len() >= c1 * TILE_PIXELS
                && f.len() >= c1
                && out.len() >= 6 + c1
        );
    }
}

/// Row offset `y + 0.5 - my` of tile row `py` (tile origin `py0`).
#[inline(always)]
fn row_dy(py0: u32, py: usize, my: f32) -> f32 {
    (py0 + py as u32) as f32 + 0.5 - my
}

/// Compositing thresholds.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Limits {
    pub alpha_min: f32,
    pub alpha_max: f32,
    pub t_min: f32,
}

/// `exp(x)` for f32, branch-free (Cephes polynomial, ~1 ulp on the range used). Forward and
/// backward both use it, so their alpha cut-off decisions agree exactly.
#[inline(always)]
pub fn fast_exp(x: f32) -> f32 {
    // max/min rather than clamp: a NaN maps to EXP_LO (as `_mm256_max_ps` does in the AVX2
    // kernel) instead of reaching `to_int_unchecked`, where it would be undefined behaviour.
    #[allow(clippy::manual_clamp)]
    let x = x.max(EXP_LO).min(EXP_HI);
    let n = (x * LOG2E + 0.5).floor();
    let poly = exp_poly(x, n);
    // SAFETY: after the clamp (NaN included), n lies in [-126, 126], so the conversion is
    // exact and in range.
    let ni: i32 = unsafe { n.to_int_unchecked() };
    poly * f32::from_bits(((ni + 127) as u32) << 23)
}

const LOG2E: f32 = std::f32::consts::LOG2_E;

/// Portable kernels.
pub(crate) mod portable {
    use super::*;

    /// Composite splat `g` (list index `k1 - 1`, channel values `f`) over the rows and halves
    /// of `rows`. Returns (evaluated, blended, terminated) pixel counts.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_splat<const K: usize>(
        c1_dyn: usize,
        g: &RowSplat,
        lim: &Limits,
        k1: u32,
        lane_x: &[f32; LANES],
        py0: u32,
        rows: &RowMasks,
        f: &[f32],
        px: &mut ForwardPixels<'_>,
    ) -> (u32, u32, u32) {
        let c1 = if K > 0 { K } else { c1_dyn };
        px.check(c1, f);
        let (mut n_eval, mut n_blend, mut n_term) = (0u32, 0u32, 0u32);
        for (py, &mask) in rows.iter().enumerate() {
            for h in 0..2 {
                let row = py * LANES + 8 * h;
                if mask & (1 << h) == 0 || px.done[row..row + 8].iter().all(|d| *d != 0) {
                    continue;
                }
                let dy = row_dy(py0, py, g.my);
                for l in 0..8 {
                    let p = row + l;
                    let dx = lane_x[8 * h + l] - g.mx;
                    let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
                    let alpha = (g.op * fast_exp(-sigma)).min(lim.alpha_max);
                    let live = px.done[p] == 0;
                    let valid = live & (sigma >= 0.0) & (alpha >= lim.alpha_min);
                    let tp = px.t[p];
                    let next_t = tp * (1.0 - alpha);
                    let term = valid & (next_t < lim.t_min);
                    let blend = valid & !term;
                    let w = if blend { alpha * tp } else { 0.0 };
                    px.t[p] = if blend { next_t } else { tp };
                    px.last[p] = if blend { k1 } else { px.last[p] };
                    px.done[p] |= u32::from(term);
                    n_eval += u32::from(live);
                    n_blend += u32::from(blend);
                    n_term += u32::from(term);
                    for c in 0..c1 {
                        px.acc[c * TILE_PIXELS + p] += f[c] * w;
                    }
                }
            }
        }
        (n_eval, n_blend, n_term)
    }

    /// Back-propagate through splat `g` (list index `k`) over the rows and halves of `rows`:
    /// updates the pixels' transmittance and behind-sums, and writes the splat's summed
    /// gradient `[mean x, mean y, conic a, b, c, opacity, channels..]` into `out`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn backward_splat<const K: usize>(
        c1_dyn: usize,
        g: &RowSplat,
        lim: &Limits,
        k: u32,
        lane_x: &[f32; LANES],
        py0: u32,
        rows: &RowMasks,
        f: &[f32],
        px: &mut BackwardPixels<'_>,
        gfl: &mut [[f32; LANES]],
        out: &mut [f32],
    ) {
        let c1 = if K > 0 { K } else { c1_dyn };
        px.check(c1, f, out);
        let mut gl = [[0.0f32; LANES]; 6];
        for a in &mut gfl[..c1] {
            *a = [0.0; LANES];
        }
        for (py, &mask) in rows.iter().enumerate() {
            let dy = row_dy(py0, py, g.my);
            for h in 0..2 {
                if mask & (1 << h) == 0 {
                    continue;
                }
                for l in 8 * h..8 * h + 8 {
                    let p = py * LANES + l;
                    let mut vf = 0.0f32;
                    for c in 0..c1 {
                        vf += px.vc[c * TILE_PIXELS + p] * f[c];
                    }
                    let dx = lane_x[l] - g.mx;
                    let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
                    let vis = fast_exp(-sigma);
                    let raw = g.op * vis;
                    let alpha = raw.min(lim.alpha_max);
                    let valid = (k < px.last[p]) & (sigma >= 0.0) & (alpha >= lim.alpha_min);
                    let one_m = 1.0 - alpha;
                    let ti = px.t[p] / one_m;
                    let w = if valid { alpha * ti } else { 0.0 };
                    let v_alpha = ti * vf - (px.vr[p] + px.tail[p]) / one_m;
                    px.vr[p] += w * vf;
                    px.t[p] = if valid { ti } else { px.t[p] };
                    let on = valid & (raw <= lim.alpha_max);
                    let va = if on { v_alpha } else { 0.0 };
                    let v_sigma = -va * alpha;
                    gl[5][l] += va * vis;
                    gl[2][l] += 0.5 * v_sigma * dx * dx;
                    gl[3][l] += v_sigma * dx * dy;
                    gl[4][l] += 0.5 * v_sigma * dy * dy;
                    // sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = pixel - mean.
                    // Masked, so a huge user conic cannot give 0 * inf off the splat.
                    if on {
                        gl[0][l] -= v_sigma * (g.ca * dx + g.cb * dy);
                        gl[1][l] -= v_sigma * (g.cc * dy + g.cb * dx);
                    }
                    for c in 0..c1 {
                        gfl[c][l] += w * px.vc[c * TILE_PIXELS + p];
                    }
                }
            }
        }
        for q in 0..6 {
            out[q] = gl[q].iter().sum();
        }
        for c in 0..c1 {
            out[6 + c] = gfl[c].iter().sum();
        }
    }
}

/// AVX2 kernels: the portable arithmetic on 8-lane vectors (one row half per vector).
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    #[inline]
    #[target_feature(enable = "avx2")]
    fn splat(v: f32) -> __m256 {
        _mm256_set1_ps(v)
    }

    /// Exact negation (sign flip), like unary minus.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn neg(v: __m256) -> __m256 {
        _mm256_xor_ps(v, splat(-0.0))
    }

    /// [`super::fast_exp`] on 8 lanes.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn exp8(x: __m256) -> __m256 {
        let x = _mm256_min_ps(_mm256_max_ps(x, splat(EXP_LO)), splat(EXP_HI));
        let n = _mm256_floor_ps(_mm256_add_ps(_mm256_mul_ps(x, splat(LOG2E)), splat(0.5)));
        let r = _mm256_sub_ps(
            _mm256_sub_ps(x, _mm256_mul_ps(n, splat(LN2_HI))),
            _mm256_mul_ps(n, splat(LN2_LO)),
        );
        let mut p = splat(EXP_P[0]);
        for c in &EXP_P[1..] {
            p = _mm256_add_ps(_mm256_mul_ps(p, r), splat(*c));
        }
        let poly = _mm256_add_ps(
            _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(p, r), r), r),
            splat(1.0),
        );
        let ni = _mm256_cvttps_epi32(n);
        let scale = _mm256_castsi256_ps(_mm256_slli_epi32(
            _mm256_add_epi32(ni, _mm256_set1_epi32(127)),
            23,
        ));
        _mm256_mul_ps(poly, scale)
    }

    /// sigma = 0.5 (a dx^2 + c dy^2) + b dx dy, in the portable operation order.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn sigma8(g: &RowSplat, dx: __m256, dy: f32) -> __m256 {
        let a = _mm256_mul_ps(_mm256_mul_ps(splat(g.ca), dx), dx);
        let c = splat(g.cc * dy * dy);
        let b = _mm256_mul_ps(_mm256_mul_ps(splat(g.cb), dx), splat(dy));
        _mm256_add_ps(_mm256_mul_ps(splat(0.5), _mm256_add_ps(a, c)), b)
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn load(s: &[f32], i: usize) -> __m256 {
        debug_assert!(i + 8 <= s.len());
        // SAFETY: every caller checked the buffer sizes on entry (`check`), and indices are
        // c * TILE_PIXELS + py * 16 + 8 h with c < c1, py < 16, h < 2; unaligned load.
        unsafe { _mm256_loadu_ps(s.as_ptr().add(i)) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn store(s: &mut [f32], i: usize, v: __m256) {
        debug_assert!(i + 8 <= s.len());
        // SAFETY: as for `load`; unaligned store.
        unsafe { _mm256_storeu_ps(s.as_mut_ptr().add(i), v) }
    }

    /// `store(s, i, blendv(load(s, i), v, mask))` for 8 lanes of 4 bytes at `p`, written as a
    /// plain store through inline assembly: LLVM folds that load-blend-store pattern into a
    /// masked store (`vmaskmovps`), microcoded on AMD cores, where it cost ~17 % of a forward
    /// on a real frame (perf, EPYC). An `asm!` store cannot be rewritten.
    ///
    /// # Safety
    /// `p` must be valid for writing 32 bytes.
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn store_blended(p: *mut u8, old: __m256, v: __m256, mask: __m256) {
        let out = _mm256_blendv_ps(old, v, mask);
        // SAFETY: `p` is valid for 32 bytes (this function's contract); the store touches
        // nothing else (no stack, flags preserved).
        unsafe {
            std::arch::asm!(
                "vmovups ymmword ptr [{p}], {v}",
                p = in(reg) p,
                v = in(ymm_reg) out,
                options(nostack, preserves_flags),
            );
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    // `_mm256_loadu_si256` takes a `__m256i` pointer but needs no alignment.
    #[allow(clippy::cast_ptr_alignment)]
    fn load_u(s: &[u32], i: usize) -> __m256i {
        debug_assert!(i + 8 <= s.len());
        // SAFETY: as for `load`; unaligned load.
        unsafe { _mm256_loadu_si256(s.as_ptr().add(i).cast::<__m256i>()) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    // `_mm256_storeu_si256` takes a `__m256i` pointer but needs no alignment.
    #[allow(clippy::cast_ptr_alignment)]
    fn store_u(s: &mut [u32], i: usize, v: __m256i) {
        debug_assert!(i + 8 <= s.len());
        // SAFETY: as for `load`; unaligned store.
        unsafe { _mm256_storeu_si256(s.as_mut_ptr().add(i).cast::<__m256i>(), v) }
    }

    /// Sum of the 8 lanes.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn hsum_u32(v: __m256i) -> u32 {
        let mut a = [0u32; 8];
        store_u(&mut a, 0, v);
        a.iter().sum()
    }

    /// AVX2 version of [`portable::forward_splat`](super::portable::forward_splat).
    #[inline]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_splat<const K: usize>(
        c1_dyn: usize,
        g: &RowSplat,
        lim: &Limits,
        k1: u32,
        lane_x: &[f32; LANES],
        py0: u32,
        rows: &RowMasks,
        f: &[f32],
        px: &mut ForwardPixels<'_>,
    ) -> (u32, u32, u32) {
        let c1 = if K > 0 { K } else { c1_dyn };
        px.check(c1, f);
        let mut n_term = 0u32;
        // Per-lane counts of evaluated and blended pixels (masks are -1 where true).
        let (mut c_eval, mut c_blend) = (_mm256_setzero_si256(), _mm256_setzero_si256());
        let zero = _mm256_setzero_ps();
        let lx = [load(lane_x, 0), load(lane_x, 8)];
        for (py, &mask) in rows.iter().enumerate() {
            if mask == 0 {
                continue;
            }
            let dy = row_dy(py0, py, g.my);
            for h in 0..2 {
                if mask & (1 << h) == 0 {
                    continue;
                }
                let row = py * LANES + 8 * h;
                let done_v = load_u(px.done, row);
                let live = _mm256_castsi256_ps(_mm256_cmpeq_epi32(done_v, _mm256_setzero_si256()));
                if _mm256_movemask_ps(live) == 0 {
                    continue;
                }
                let dx = _mm256_sub_ps(lx[h], splat(g.mx));
                let sigma = sigma8(g, dx, dy);
                let e = exp8(neg(sigma));
                let alpha = _mm256_min_ps(_mm256_mul_ps(splat(g.op), e), splat(lim.alpha_max));
                let valid = _mm256_and_ps(
                    live,
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GE_OQ>(sigma, zero),
                        _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, splat(lim.alpha_min)),
                    ),
                );
                let tp = load(px.t, row);
                let next_t = _mm256_mul_ps(tp, _mm256_sub_ps(splat(1.0), alpha));
                let term =
                    _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_LT_OQ>(next_t, splat(lim.t_min)));
                let blend = _mm256_andnot_ps(term, valid);
                let w = _mm256_and_ps(blend, _mm256_mul_ps(alpha, tp));
                let last_v = _mm256_castsi256_ps(load_u(px.last, row));
                let k1v = _mm256_castsi256_ps(_mm256_set1_epi32(k1 as i32));
                assert!(row + 8 <= px.t.len() && row + 8 <= px.last.len());
                // SAFETY: both rows of 8 lie inside their buffers (asserted).
                unsafe {
                    store_blended(px.t.as_mut_ptr().add(row).cast(), tp, next_t, blend);
                    store_blended(px.last.as_mut_ptr().add(row).cast(), last_v, k1v, blend);
                }
                let term_bits = _mm256_srli_epi32(_mm256_castps_si256(term), 31);
                store_u(px.done, row, _mm256_or_si256(done_v, term_bits));
                c_eval = _mm256_sub_epi32(c_eval, _mm256_castps_si256(live));
                c_blend = _mm256_sub_epi32(c_blend, _mm256_castps_si256(blend));
                let tm = _mm256_movemask_ps(term);
                if tm != 0 {
                    n_term += (tm as u32).count_ones();
                }
                for c in 0..c1 {
                    let i = c * TILE_PIXELS + row;
                    let a = load(px.acc, i);
                    store(px.acc, i, _mm256_add_ps(a, _mm256_mul_ps(splat(f[c]), w)));
                }
            }
        }
        (hsum_u32(c_eval), hsum_u32(c_blend), n_term)
    }

    /// AVX2 version of [`portable::backward_splat`](super::portable::backward_splat).
    #[inline]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn backward_splat<const K: usize>(
        c1_dyn: usize,
        g: &RowSplat,
        lim: &Limits,
        k: u32,
        lane_x: &[f32; LANES],
        py0: u32,
        rows: &RowMasks,
        f: &[f32],
        px: &mut BackwardPixels<'_>,
        gfl: &mut [[f32; LANES]],
        out: &mut [f32],
    ) {
        let c1 = if K > 0 { K } else { c1_dyn };
        px.check(c1, f, out);
        assert!(gfl.len() >= c1);
        let zero = _mm256_setzero_ps();
        let half = splat(0.5);
        let lx = [load(lane_x, 0), load(lane_x, 8)];
        // Per-lane accumulators, [quantity][half], kept in registers across rows.
        let mut gl = [[zero; 2]; 6];
        for a in &mut gfl[..c1] {
            *a = [0.0; LANES];
        }
        let kv = _mm256_set1_epi32(k as i32);
        for (py, &mask) in rows.iter().enumerate() {
            if mask == 0 {
                continue;
            }
            let dy = row_dy(py0, py, g.my);
            let dyv = splat(dy);
            for h in 0..2 {
                if mask & (1 << h) == 0 {
                    continue;
                }
                let row = py * LANES + 8 * h;
                let mut vf = zero;
                for c in 0..c1 {
                    vf = _mm256_add_ps(
                        vf,
                        _mm256_mul_ps(load(px.vc, c * TILE_PIXELS + row), splat(f[c])),
                    );
                }
                let dx = _mm256_sub_ps(lx[h], splat(g.mx));
                let sigma = sigma8(g, dx, dy);
                let vis = exp8(neg(sigma));
                let raw = _mm256_mul_ps(splat(g.op), vis);
                let alpha = _mm256_min_ps(raw, splat(lim.alpha_max));
                // k < last, as a signed compare (both < 2^31).
                let before = _mm256_castsi256_ps(_mm256_cmpgt_epi32(load_u(px.last, row), kv));
                let valid = _mm256_and_ps(
                    before,
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GE_OQ>(sigma, zero),
                        _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, splat(lim.alpha_min)),
                    ),
                );
                let one_m = _mm256_sub_ps(splat(1.0), alpha);
                let t_old = load(px.t, row);
                let ti = _mm256_div_ps(t_old, one_m);
                let w = _mm256_and_ps(valid, _mm256_mul_ps(alpha, ti));
                let vr_old = load(px.vr, row);
                let v_alpha = _mm256_sub_ps(
                    _mm256_mul_ps(ti, vf),
                    _mm256_div_ps(_mm256_add_ps(vr_old, load(px.tail, row)), one_m),
                );
                store(px.vr, row, _mm256_add_ps(vr_old, _mm256_mul_ps(w, vf)));
                store(px.t, row, _mm256_blendv_ps(t_old, ti, valid));
                let unclamped = _mm256_cmp_ps::<_CMP_LE_OQ>(raw, splat(lim.alpha_max));
                let on = _mm256_and_ps(valid, unclamped);
                let va = _mm256_and_ps(on, v_alpha);
                let v_sigma = _mm256_mul_ps(neg(va), alpha);
                gl[5][h] = _mm256_add_ps(gl[5][h], _mm256_mul_ps(va, vis));
                let hv = _mm256_mul_ps(half, v_sigma);
                gl[2][h] = _mm256_add_ps(gl[2][h], _mm256_mul_ps(_mm256_mul_ps(hv, dx), dx));
                gl[3][h] = _mm256_add_ps(gl[3][h], _mm256_mul_ps(_mm256_mul_ps(v_sigma, dx), dyv));
                gl[4][h] = _mm256_add_ps(gl[4][h], _mm256_mul_ps(_mm256_mul_ps(hv, dyv), dyv));
                let ga = _mm256_add_ps(
                    _mm256_mul_ps(splat(g.ca), dx),
                    _mm256_mul_ps(splat(g.cb), dyv),
                );
                let gc = _mm256_add_ps(
                    _mm256_mul_ps(splat(g.cc), dyv),
                    _mm256_mul_ps(splat(g.cb), dx),
                );
                // Masked, so a huge user conic cannot give 0 * inf off the splat.
                gl[0][h] = _mm256_sub_ps(gl[0][h], _mm256_and_ps(on, _mm256_mul_ps(v_sigma, ga)));
                gl[1][h] = _mm256_sub_ps(gl[1][h], _mm256_and_ps(on, _mm256_mul_ps(v_sigma, gc)));
                for c in 0..c1 {
                    let v = load(px.vc, c * TILE_PIXELS + row);
                    let a = load(&gfl[c], 8 * h);
                    store(&mut gfl[c], 8 * h, _mm256_add_ps(a, _mm256_mul_ps(w, v)));
                }
            }
        }
        // Horizontal sums in lane order, as the portable kernel does.
        let mut lanes = [0.0f32; LANES];
        for q in 0..6 {
            store(&mut lanes, 0, gl[q][0]);
            store(&mut lanes, 8, gl[q][1]);
            out[q] = lanes.iter().sum();
        }
        for c in 0..c1 {
            out[6 + c] = gfl[c].iter().sum();
        }
    }
}
