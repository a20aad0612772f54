//! The per-row compositing kernels: one tile row of 16 pixels against one splat, forward and
//! backward. Two implementations with the same arithmetic, operation for operation: a portable
//! one (plain loops) and an AVX2 one (explicit 8-lane intrinsics, two halves per row). Keeping
//! the order of every floating-point operation identical makes the two bit-identical, which a
//! test checks. Explicit intrinsics avoid what auto-vectorisation produced here: masked stores
//! (`vmaskmovps`), which are microcoded and slow on AMD cores.

use crate::TILE_SIZE;

/// Pixels per tile row.
pub(crate) const LANES: usize = TILE_SIZE as usize;
/// Pixels per tile.
pub(crate) const TILE_PIXELS: usize = LANES * LANES;

/// One splat's parameters for a row: centre x, row offset `dy = y + 0.5 - my`, conic, opacity.
#[derive(Debug, Clone, Copy)]
pub(crate) struct RowSplat {
    pub mx: f32,
    pub dy: f32,
    pub ca: f32,
    pub cb: f32,
    pub cc: f32,
    pub op: f32,
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
    let x = x.clamp(EXP_LO, EXP_HI);
    let n = (x * LOG2E + 0.5).floor();
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = EXP_P[0];
    for c in &EXP_P[1..] {
        p = p * r + c;
    }
    let poly = p * r * r + r + 1.0;
    // SAFETY: after the clamp, n lies in [-126, 126], so the conversion is exact and in range.
    let ni: i32 = unsafe { n.to_int_unchecked() };
    poly * f32::from_bits(((ni + 127) as u32) << 23)
}

const EXP_LO: f32 = -87.0;
const EXP_HI: f32 = 87.0;
const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const EXP_P: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

/// Portable row kernels.
pub(crate) mod portable {
    use super::*;

    /// The lanes of the selected row halves.
    #[inline(always)]
    fn active_lanes(halves: [bool; 2]) -> impl Iterator<Item = usize> {
        let lo = if halves[0] { 0 } else { 8 };
        let hi = if halves[1] { 16 } else { 8 };
        lo..hi
    }

    /// Composite splat `g` (list index `k1 - 1`) over one row. `f` holds its C+1 channel values,
    /// `acc` the tile's channel-major accumulators. Returns (evaluated, blended, terminated).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_row(
        c1: usize,
        g: &RowSplat,
        lim: &Limits,
        halves: [bool; 2],
        k1: u32,
        lane_x: &[f32; LANES],
        f: &[f32],
        t_row: &mut [f32; LANES],
        done: &mut [u32; LANES],
        last: &mut [u32; LANES],
        acc: &mut [f32],
        row: usize,
    ) -> (u32, u32, u32) {
        let dy = g.dy;
        let mut w = [0.0f32; LANES];
        let (mut n_eval, mut n_blend, mut n_term) = (0u32, 0u32, 0u32);
        for l in active_lanes(halves) {
            let dx = lane_x[l] - g.mx;
            let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
            let alpha = (g.op * fast_exp(-sigma)).min(lim.alpha_max);
            let live = done[l] == 0;
            let valid = live & (sigma >= 0.0) & (alpha >= lim.alpha_min);
            let tp = t_row[l];
            let next_t = tp * (1.0 - alpha);
            let term = valid & (next_t < lim.t_min);
            let blend = valid & !term;
            w[l] = if blend { alpha * tp } else { 0.0 };
            t_row[l] = if blend { next_t } else { tp };
            last[l] = if blend { k1 } else { last[l] };
            done[l] |= u32::from(term);
            n_eval += u32::from(live);
            n_blend += u32::from(blend);
            n_term += u32::from(term);
        }
        for c in 0..c1 {
            let a = &mut acc[c * TILE_PIXELS + row..c * TILE_PIXELS + row + LANES];
            for l in active_lanes(halves) {
                a[l] += f[c] * w[l];
            }
        }
        (n_eval, n_blend, n_term)
    }

    /// Back-propagate through splat `g` (list index `k`) over one row: updates the row's
    /// transmittance `t_row` and behind-sum `vr`, and adds to the per-lane gradient
    /// accumulators `gl` (mean x, mean y, conic a, b, c, opacity) and `gfl` (channels).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn backward_row(
        c1: usize,
        g: &RowSplat,
        lim: &Limits,
        halves: [bool; 2],
        k: u32,
        lane_x: &[f32; LANES],
        f: &[f32],
        t_row: &mut [f32; LANES],
        vr: &mut [f32; LANES],
        tail: &[f32; LANES],
        last: &[u32; LANES],
        vc: &[f32],
        row: usize,
        gl: &mut [[f32; LANES]; 6],
        gfl: &mut [[f32; LANES]],
    ) {
        let dy = g.dy;
        let mut vf = [0.0f32; LANES];
        for c in 0..c1 {
            let v = &vc[c * TILE_PIXELS + row..c * TILE_PIXELS + row + LANES];
            for l in active_lanes(halves) {
                vf[l] += v[l] * f[c];
            }
        }
        let mut wl = [0.0f32; LANES];
        for l in active_lanes(halves) {
            let dx = lane_x[l] - g.mx;
            let sigma = 0.5 * (g.ca * dx * dx + g.cc * dy * dy) + g.cb * dx * dy;
            let vis = fast_exp(-sigma);
            let raw = g.op * vis;
            let alpha = raw.min(lim.alpha_max);
            let valid = (k < last[l]) & (sigma >= 0.0) & (alpha >= lim.alpha_min);
            let one_m = 1.0 - alpha;
            let ti = t_row[l] / one_m;
            let w = if valid { alpha * ti } else { 0.0 };
            let v_alpha = ti * vf[l] - (vr[l] + tail[l]) / one_m;
            vr[l] += w * vf[l];
            t_row[l] = if valid { ti } else { t_row[l] };
            wl[l] = w;
            let va = if valid & (raw <= lim.alpha_max) {
                v_alpha
            } else {
                0.0
            };
            let v_sigma = -va * alpha;
            gl[5][l] += va * vis;
            gl[2][l] += 0.5 * v_sigma * dx * dx;
            gl[3][l] += v_sigma * dx * dy;
            gl[4][l] += 0.5 * v_sigma * dy * dy;
            // sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = pixel - mean.
            gl[0][l] -= v_sigma * (g.ca * dx + g.cb * dy);
            gl[1][l] -= v_sigma * (g.cc * dy + g.cb * dx);
        }
        for c in 0..c1 {
            let v = &vc[c * TILE_PIXELS + row..c * TILE_PIXELS + row + LANES];
            for l in active_lanes(halves) {
                gfl[c][l] += wl[l] * v[l];
            }
        }
    }
}

/// AVX2 row kernels: the portable arithmetic on 8-lane vectors, two halves per row.
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
    fn sigma8(g: &RowSplat, dx: __m256) -> __m256 {
        let dy = splat(g.dy);
        let a = _mm256_mul_ps(_mm256_mul_ps(splat(g.ca), dx), dx);
        let c = splat(g.cc * g.dy * g.dy);
        let b = _mm256_mul_ps(_mm256_mul_ps(splat(g.cb), dx), dy);
        _mm256_add_ps(_mm256_mul_ps(splat(0.5), _mm256_add_ps(a, c)), b)
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn load(s: &[f32], i: usize) -> __m256 {
        assert!(i + 8 <= s.len());
        // SAFETY: bounds checked above; unaligned load.
        unsafe { _mm256_loadu_ps(s.as_ptr().add(i)) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn store(s: &mut [f32], i: usize, v: __m256) {
        assert!(i + 8 <= s.len());
        // SAFETY: bounds checked above; unaligned store.
        unsafe { _mm256_storeu_ps(s.as_mut_ptr().add(i), v) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn load_u(s: &[u32], i: usize) -> __m256i {
        assert!(i + 8 <= s.len());
        // SAFETY: bounds checked above; unaligned load.
        unsafe { _mm256_loadu_si256(s.as_ptr().add(i) as *const __m256i) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn store_u(s: &mut [u32], i: usize, v: __m256i) {
        assert!(i + 8 <= s.len());
        // SAFETY: bounds checked above; unaligned store.
        unsafe { _mm256_storeu_si256(s.as_mut_ptr().add(i) as *mut __m256i, v) }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn count(mask: __m256) -> u32 {
        (_mm256_movemask_ps(mask) as u32).count_ones()
    }

    /// AVX2 version of [`portable::forward_row`](super::portable::forward_row).
    #[inline]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_row(
        c1: usize,
        g: &RowSplat,
        lim: &Limits,
        halves: [bool; 2],
        k1: u32,
        lane_x: &[f32; LANES],
        f: &[f32],
        t_row: &mut [f32; LANES],
        done: &mut [u32; LANES],
        last: &mut [u32; LANES],
        acc: &mut [f32],
        row: usize,
    ) -> (u32, u32, u32) {
        let (mut n_eval, mut n_blend, mut n_term) = (0u32, 0u32, 0u32);
        let zero = _mm256_setzero_ps();
        for h in [0usize, 8] {
            if !halves[h / 8] {
                continue;
            }
            let dx = _mm256_sub_ps(load(lane_x, h), splat(g.mx));
            let sigma = sigma8(g, dx);
            let e = exp8(neg(sigma));
            let alpha = _mm256_min_ps(_mm256_mul_ps(splat(g.op), e), splat(lim.alpha_max));
            let done_v = load_u(done, h);
            let live = _mm256_castsi256_ps(_mm256_cmpeq_epi32(done_v, _mm256_setzero_si256()));
            let valid = _mm256_and_ps(
                live,
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(sigma, zero),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, splat(lim.alpha_min)),
                ),
            );
            let tp = load(t_row, h);
            let next_t = _mm256_mul_ps(tp, _mm256_sub_ps(splat(1.0), alpha));
            let term = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_LT_OQ>(next_t, splat(lim.t_min)));
            let blend = _mm256_andnot_ps(term, valid);
            let w = _mm256_and_ps(blend, _mm256_mul_ps(alpha, tp));
            store(t_row, h, _mm256_blendv_ps(tp, next_t, blend));
            let last_v = load_u(last, h);
            let k1v = _mm256_set1_epi32(k1 as i32);
            store_u(
                last,
                h,
                _mm256_castps_si256(_mm256_blendv_ps(
                    _mm256_castsi256_ps(last_v),
                    _mm256_castsi256_ps(k1v),
                    blend,
                )),
            );
            let term_bits = _mm256_srli_epi32(_mm256_castps_si256(term), 31);
            store_u(done, h, _mm256_or_si256(done_v, term_bits));
            n_eval += count(live);
            n_blend += count(blend);
            n_term += count(term);
            for c in 0..c1 {
                let i = c * TILE_PIXELS + row + h;
                let a = load(acc, i);
                store(acc, i, _mm256_add_ps(a, _mm256_mul_ps(splat(f[c]), w)));
            }
        }
        (n_eval, n_blend, n_term)
    }

    /// AVX2 version of [`portable::backward_row`](super::portable::backward_row).
    #[inline]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn backward_row(
        c1: usize,
        g: &RowSplat,
        lim: &Limits,
        halves: [bool; 2],
        k: u32,
        lane_x: &[f32; LANES],
        f: &[f32],
        t_row: &mut [f32; LANES],
        vr: &mut [f32; LANES],
        tail: &[f32; LANES],
        last: &[u32; LANES],
        vc: &[f32],
        row: usize,
        gl: &mut [[f32; LANES]; 6],
        gfl: &mut [[f32; LANES]],
    ) {
        let zero = _mm256_setzero_ps();
        let dy = splat(g.dy);
        let half = splat(0.5);
        for h in [0usize, 8] {
            if !halves[h / 8] {
                continue;
            }
            let mut vf = zero;
            for c in 0..c1 {
                vf = _mm256_add_ps(
                    vf,
                    _mm256_mul_ps(load(vc, c * TILE_PIXELS + row + h), splat(f[c])),
                );
            }
            let dx = _mm256_sub_ps(load(lane_x, h), splat(g.mx));
            let sigma = sigma8(g, dx);
            let vis = exp8(neg(sigma));
            let raw = _mm256_mul_ps(splat(g.op), vis);
            let alpha = _mm256_min_ps(raw, splat(lim.alpha_max));
            // k < last, as signed compare (both < 2^31).
            let before = _mm256_castsi256_ps(_mm256_cmpgt_epi32(
                load_u(last, h),
                _mm256_set1_epi32(k as i32),
            ));
            let valid = _mm256_and_ps(
                before,
                _mm256_and_ps(
                    _mm256_cmp_ps::<_CMP_GE_OQ>(sigma, zero),
                    _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, splat(lim.alpha_min)),
                ),
            );
            let one_m = _mm256_sub_ps(splat(1.0), alpha);
            let t_old = load(t_row, h);
            let ti = _mm256_div_ps(t_old, one_m);
            let w = _mm256_and_ps(valid, _mm256_mul_ps(alpha, ti));
            let vr_old = load(vr, h);
            let v_alpha = _mm256_sub_ps(
                _mm256_mul_ps(ti, vf),
                _mm256_div_ps(_mm256_add_ps(vr_old, load(tail, h)), one_m),
            );
            store(vr, h, _mm256_add_ps(vr_old, _mm256_mul_ps(w, vf)));
            store(t_row, h, _mm256_blendv_ps(t_old, ti, valid));
            let unclamped = _mm256_cmp_ps::<_CMP_LE_OQ>(raw, splat(lim.alpha_max));
            let va = _mm256_and_ps(_mm256_and_ps(valid, unclamped), v_alpha);
            let v_sigma = _mm256_mul_ps(neg(va), alpha);
            let add = |acc: &mut [f32; LANES], v: __m256| {
                let a = load(acc, h);
                store(acc, h, _mm256_add_ps(a, v));
            };
            add(&mut gl[5], _mm256_mul_ps(va, vis));
            add(
                &mut gl[2],
                _mm256_mul_ps(_mm256_mul_ps(_mm256_mul_ps(half, v_sigma), dx), dx),
            );
            add(&mut gl[3], _mm256_mul_ps(_mm256_mul_ps(v_sigma, dx), dy));
            add(
                &mut gl[4],
                _mm256_mul_ps(_mm256_mul_ps(_mm256_mul_ps(half, v_sigma), dy), dy),
            );
            let sub = |acc: &mut [f32; LANES], v: __m256| {
                let a = load(acc, h);
                store(acc, h, _mm256_sub_ps(a, v));
            };
            let ga = _mm256_add_ps(
                _mm256_mul_ps(splat(g.ca), dx),
                _mm256_mul_ps(splat(g.cb), dy),
            );
            let gc = _mm256_add_ps(
                _mm256_mul_ps(splat(g.cc), dy),
                _mm256_mul_ps(splat(g.cb), dx),
            );
            sub(&mut gl[0], _mm256_mul_ps(v_sigma, ga));
            sub(&mut gl[1], _mm256_mul_ps(v_sigma, gc));
            for c in 0..c1 {
                let v = load(vc, c * TILE_PIXELS + row + h);
                add(&mut gfl[c], _mm256_mul_ps(w, v));
            }
        }
    }
}
