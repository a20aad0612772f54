//! The photometric training loss (paper Appendix A) with its exact gradient, fused in one pass:
//!
//! ```text
//! L = l1 * mean|x - y| + dssim * (1 - SSIM(x, y)) / 2
//! ```
//!
//! SSIM is the mean of the per-pixel, per-channel SSIM map computed from `window` x `window` box
//! means with reflect padding (the border pixel is not repeated: index -1 reads index 1), with
//! C1 = 0.01^2 and C2 = 0.03^2. Images are row-major `[height, width, channels]`; `x` is the
//! rendered image (the gradient is taken with respect to it), `y` the target.
//!
//! The gradient of the mean SSIM with respect to `x` at pixel q is
//! `sum_p w(p, q) * (A_p + 2 x_q B_p + y_q C_p)` with `A = dS/d mean_x`, `B = dS/d mean_xx`,
//! `C = dS/d mean_xy` and `w` the box weights; it is computed with the transpose of the
//! separable box filter. Both passes are parallel over image rows.
//!
//! Its own crate: the loss reads images, not splats; it shares only sync4d-raster's element
//! types ([`Real`]) and its error ([`RasterError`], so that the bindings map both the same way).

use rayon::prelude::*;

use sync4d_raster::error::{check_finite, check_len, RasterError, Result};
use sync4d_scalar::Real;

const C1: f64 = 0.01 * 0.01;
const C2: f64 = 0.03 * 0.03;

/// Weights of the loss terms and the SSIM window (Appendix A: 0.8, 0.2, 3).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossWeights {
    /// Weight of the mean absolute error.
    pub l1: f64,
    /// Weight of DSSIM = (1 - SSIM) / 2.
    pub dssim: f64,
    /// Side of the square SSIM averaging window, odd, >= 1.
    pub window: usize,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            l1: 0.8,
            dssim: 0.2,
            window: 3,
        }
    }
}

/// The loss value and its two terms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LossTerms {
    /// `l1 * mean_abs + dssim * (1 - ssim) / 2`.
    pub loss: f64,
    /// Mean absolute difference over all pixels and channels.
    pub mean_abs: f64,
    /// Mean SSIM over all pixels and channels.
    pub ssim: f64,
}

/// Reflect-padded box-sum taps along one axis of length `n`: `out[j] = sum_(i, m) m * in[i]`.
/// Positions in `clean` have the plain taps `j - pad ..= j + pad`, each once.
struct Taps {
    lists: Vec<Vec<(usize, f32)>>,
    clean: std::ops::Range<usize>,
    pad: usize,
}

impl Taps {
    /// Taps of the forward box sum (`adjoint = false`) or of its transpose.
    fn new(n: usize, pad: usize, adjoint: bool) -> Taps {
        let reflect = |i: isize| -> usize {
            let n = n as isize;
            let r = if i < 0 {
                -i
            } else if i >= n {
                2 * (n - 1) - i
            } else {
                i
            };
            r as usize
        };
        let mut lists: Vec<Vec<(usize, f32)>> = vec![Vec::new(); n];
        for i in 0..n {
            for k in -(pad as isize)..=(pad as isize) {
                let src = reflect(i as isize + k);
                let (to, from) = if adjoint { (src, i) } else { (i, src) };
                match lists[to].iter_mut().find(|(f, _)| *f == from) {
                    Some(e) => e.1 += 1.0,
                    None => lists[to].push((from, 1.0)),
                }
            }
        }
        let is_clean = |j: usize| {
            j >= pad
                && j + pad < n
                && lists[j].len() == 2 * pad + 1
                && lists[j]
                    .iter()
                    .all(|&(f, m)| m == 1.0 && f + pad >= j && f <= j + pad)
        };
        let mut lo = n / 2;
        let mut hi = lo;
        if is_clean(lo) {
            while lo > 0 && is_clean(lo - 1) {
                lo -= 1;
            }
            while hi < n && is_clean(hi) {
                hi += 1;
            }
        }
        Taps {
            lists,
            clean: lo..hi,
            pad,
        }
    }

    /// `dst[j] = sum_taps src[i]` for positions of `stride` consecutive values (one row).
    fn apply_row<F: Real>(&self, src: &[F], dst: &mut [F], stride: usize) {
        let (lo, hi, p) = (self.clean.start, self.clean.end, self.pad);
        for (j, list) in self.lists.iter().enumerate() {
            if (lo..hi).contains(&j) {
                continue;
            }
            let d = &mut dst[j * stride..(j + 1) * stride];
            d.fill(F::zero());
            for &(i, m) in list {
                let m = F::from_f64(m as f64);
                for (dv, &sv) in d.iter_mut().zip(&src[i * stride..(i + 1) * stride]) {
                    *dv = *dv + m * sv;
                }
            }
        }
        if lo < hi {
            let d = &mut dst[lo * stride..hi * stride];
            d.copy_from_slice(&src[(lo - p) * stride..(hi - p) * stride]);
            for k in 1..=2 * p {
                let s = &src[(lo - p + k) * stride..(hi - p + k) * stride];
                for (dv, &sv) in d.iter_mut().zip(s) {
                    *dv = *dv + sv;
                }
            }
        }
    }

    /// `dst = sum_taps(j) rows of src` for output row `j` (vertical pass).
    fn gather_rows<F: Real>(&self, j: usize, rows: &[&[F]], dst: &mut [F]) {
        dst.fill(F::zero());
        for &(i, m) in &self.lists[j] {
            let m = F::from_f64(m as f64);
            for (dv, &sv) in dst.iter_mut().zip(rows[i]) {
                *dv = *dv + m * sv;
            }
        }
    }
}

/// SSIM and its partials (dS/d mean_x, dS/d mean_xx, dS/d mean_xy) from window sums scaled by
/// `norm` (1 / window area).
#[inline(always)]
fn ssim_terms<F: Real>(sx: F, sy: F, sxx: F, syy: F, sxy: F, norm: F) -> (F, F, F, F) {
    let (mx, my) = (sx * norm, sy * norm);
    let (exx, eyy, exy) = (sxx * norm, syy * norm, sxy * norm);
    let (c1, c2, two) = (F::from_f64(C1), F::from_f64(C2), F::from_f64(2.0));
    let n1 = two * mx * my + c1;
    let n2 = two * (exy - mx * my) + c2;
    let d1 = mx * mx + my * my + c1;
    let d2 = (exx - mx * mx) + (eyy - my * my) + c2;
    let inv_d = F::one() / (d1 * d2);
    let s = n1 * n2 * inv_d;
    let da = (two * my * (n2 - n1) - s * two * mx * (d2 - d1)) * inv_d;
    (s, da, -s / d2, two * n1 * inv_d)
}

/// Row `r` (`row` values) of a row-major image.
#[inline]
fn image_row<F>(img: &[F], r: usize, row: usize) -> &[F] {
    &img[r * row..(r + 1) * row]
}

/// The five consecutive `row`-long maps of a per-row scratch buffer.
#[inline]
fn five_maps<F>(buf: &mut [F], row: usize) -> [&mut [F]; 5] {
    let (a, rest) = buf.split_at_mut(row);
    let (b, rest) = rest.split_at_mut(row);
    let (c, rest) = rest.split_at_mut(row);
    let (d, e) = rest.split_at_mut(row);
    [a, b, c, d, &mut e[..row]]
}

fn check_image<F: Real>(arg: &'static str, v: &[F], len: usize) -> Result<()> {
    check_len(arg, v, len)?;
    check_finite(arg, v)
}

/// Loss value of rendered image `pred` against `target` (both `[height, width, channels]`,
/// row-major); when `grad` is given (same length) it receives dL/d pred.
///
/// Errors (naming the argument) on mismatched lengths, non-finite values, an even or zero
/// window, or an image smaller than the window's reflect padding allows.
// One fused pass (box sums, SSIM map and its adjoint); split, the row buffers it shares
// between the stages would have to travel through every function.
#[allow(clippy::too_many_lines)]
pub fn photometric_loss<F: Real>(
    pred: &[F],
    target: &[F],
    height: usize,
    width: usize,
    channels: usize,
    weights: &LossWeights,
    grad: Option<&mut [F]>,
) -> Result<LossTerms> {
    let win = weights.window;
    if win.is_multiple_of(2) {
        return Err(RasterError::invalid(
            "window",
            format!("expected an odd window >= 1, got {win}"),
        ));
    }
    let pad = win / 2;
    if height <= pad || width <= pad || channels == 0 {
        return Err(RasterError::invalid(
            "pred",
            format!(
                "image {height}x{width}x{channels} is too small for a {win}x{win} SSIM window \
                 (each side must exceed {pad})"
            ),
        ));
    }
    if !(weights.l1.is_finite() && weights.dssim.is_finite()) {
        return Err(RasterError::invalid(
            "weights",
            "loss weights must be finite",
        ));
    }
    let len = height * width * channels;
    check_image("pred", pred, len)?;
    check_image("target", target, len)?;
    if let Some(g) = grad.as_deref() {
        check_len("grad", g, len)?;
    }

    let row = width * channels;
    let (taps_h, taps_v) = (Taps::new(width, pad, false), Taps::new(height, pad, false));
    let norm = F::from_f64(1.0 / (win * win) as f64);

    // Horizontal box sums of x, y, xx, yy, xy: five [height, row] maps.
    let mut hsum = vec![F::zero(); 5 * len];
    hsum.par_chunks_mut(5 * row).enumerate().for_each_init(
        || vec![F::zero(); 5 * row],
        |prod, (r, out)| {
            let (x, y) = (image_row(pred, r, row), image_row(target, r, row));
            let [px, py, pxx, pyy, pxy] = five_maps(prod, row);
            for k in 0..row {
                let (a, b) = (x[k], y[k]);
                px[k] = a;
                py[k] = b;
                pxx[k] = a * a;
                pyy[k] = b * b;
                pxy[k] = a * b;
            }
            for (s, o) in prod.chunks(row).zip(out.chunks_mut(row)) {
                taps_h.apply_row(s, o, channels);
            }
        },
    );
    let hmaps: Vec<Vec<&[F]>> = (0..5)
        .map(|m| {
            hsum.chunks(5 * row)
                .map(|c| &c[m * row..(m + 1) * row])
                .collect()
        })
        .collect();

    // Vertical sums, the SSIM map and its partials A, B, C (per row), plus the loss sums.
    let want_grad = grad.is_some();
    let chunk = if want_grad { 3 * row } else { 1 };
    let mut partials = vec![F::zero(); chunk * height];
    let per_row: Vec<(f64, f64)> = partials
        .par_chunks_mut(chunk)
        .enumerate()
        .map_init(
            || vec![F::zero(); 5 * row],
            |stats, (r, part)| {
                for (m, rows) in hmaps.iter().enumerate() {
                    taps_v.gather_rows(r, rows, &mut stats[m * row..(m + 1) * row]);
                }
                let (x, y) = (image_row(pred, r, row), image_row(target, r, row));
                // The SSIM map overwrites the row's mean-x slot (read before written per k).
                let [mx, my, exx, eyy, exy] = five_maps(stats, row);
                if want_grad {
                    let (pa, rest) = part.split_at_mut(row);
                    let (pb, pc) = rest.split_at_mut(row);
                    for k in 0..row {
                        let t = ssim_terms(mx[k], my[k], exx[k], eyy[k], exy[k], norm);
                        (mx[k], pa[k], pb[k], pc[k]) = t;
                    }
                } else {
                    for k in 0..row {
                        mx[k] = ssim_terms(mx[k], my[k], exx[k], eyy[k], exy[k], norm).0;
                    }
                }
                let ssim_sum: f64 = mx.iter().map(|&v| Real::to_f64(v)).sum();
                let abs_sum: f64 = x
                    .iter()
                    .zip(y)
                    .map(|(&a, &b)| Real::to_f64((a - b).abs()))
                    .sum();
                (ssim_sum, abs_sum)
            },
        )
        .collect();
    let (ssim_sum, abs_sum) = per_row
        .iter()
        .fold((0.0, 0.0), |(a, b), &(s, l)| (a + s, b + l));
    let n = len as f64;
    let terms = LossTerms {
        loss: weights.l1 * abs_sum / n + weights.dssim * (1.0 - ssim_sum / n) / 2.0,
        mean_abs: abs_sum / n,
        ssim: ssim_sum / n,
    };

    if let Some(grad) = grad {
        // Transpose of the box filter on A, B, C: vertical, then horizontal, then combine.
        let (adj_h, adj_v) = (Taps::new(width, pad, true), Taps::new(height, pad, true));
        let pmaps: Vec<Vec<&[F]>> = (0..3)
            .map(|m| {
                partials
                    .chunks(3 * row)
                    .map(|c| &c[m * row..(m + 1) * row])
                    .collect()
            })
            .collect();
        let s_ssim = F::from_f64(-weights.dssim / (2.0 * n) / (win * win) as f64);
        let s_l1 = F::from_f64(weights.l1 / n);
        grad.par_chunks_mut(row).enumerate().for_each_init(
            || (vec![F::zero(); 3 * row], vec![F::zero(); 3 * row]),
            |(vert, horiz), (r, g)| {
                for (m, rows) in pmaps.iter().enumerate() {
                    adj_v.gather_rows(r, rows, &mut vert[m * row..(m + 1) * row]);
                    adj_h.apply_row(
                        &vert[m * row..(m + 1) * row],
                        &mut horiz[m * row..(m + 1) * row],
                        channels,
                    );
                }
                let (x, y) = (image_row(pred, r, row), image_row(target, r, row));
                let two = F::from_f64(2.0);
                for k in 0..row {
                    let diff = x[k] - y[k];
                    let sign = if diff > F::zero() {
                        F::one()
                    } else if diff < F::zero() {
                        -F::one()
                    } else {
                        F::zero()
                    };
                    let a = horiz[k] + two * x[k] * horiz[row + k] + y[k] * horiz[2 * row + k];
                    g[k] = s_ssim * a + s_l1 * sign;
                }
            },
        );
    }
    Ok(terms)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image(seed: u64, len: usize) -> Vec<f64> {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (0..len)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 11) as f64) / ((1u64 << 53) as f64)
            })
            .collect()
    }

    /// Plain per-pixel SSIM with explicit reflect indexing, f64.
    fn reference(x: &[f64], y: &[f64], h: usize, w: usize, c: usize, win: usize) -> (f64, f64) {
        let pad = win as isize / 2;
        let refl = |i: isize, n: usize| -> usize {
            let n = n as isize;
            (if i < 0 {
                -i
            } else if i >= n {
                2 * (n - 1) - i
            } else {
                i
            }) as usize
        };
        let (mut ssim, mut l1) = (0.0, 0.0);
        for r in 0..h {
            for q in 0..w {
                for ch in 0..c {
                    let mut st = [0.0f64; 5];
                    for dr in -pad..=pad {
                        for dq in -pad..=pad {
                            let rr = refl(r as isize + dr, h);
                            let qq = refl(q as isize + dq, w);
                            let (a, b) = (x[(rr * w + qq) * c + ch], y[(rr * w + qq) * c + ch]);
                            st[0] += a;
                            st[1] += b;
                            st[2] += a * a;
                            st[3] += b * b;
                            st[4] += a * b;
                        }
                    }
                    let k = (win * win) as f64;
                    let [mx, my, exx, eyy, exy] = st.map(|v| v / k);
                    let num = (2.0 * mx * my + C1) * (2.0 * (exy - mx * my) + C2);
                    let den = (mx * mx + my * my + C1) * (exx - mx * mx + eyy - my * my + C2);
                    ssim += num / den;
                    let i = (r * w + q) * c + ch;
                    l1 += (x[i] - y[i]).abs();
                }
            }
        }
        let n = (h * w * c) as f64;
        (ssim / n, l1 / n)
    }

    #[test]
    fn value_matches_the_per_pixel_reference() {
        for &(h, w, c, win) in &[(7, 9, 3, 3), (2, 2, 1, 3), (12, 5, 4, 5), (6, 6, 2, 1)] {
            let x = image(1, h * w * c);
            let y = image(2, h * w * c);
            let wts = LossWeights {
                window: win,
                ..Default::default()
            };
            let t = photometric_loss(&x, &y, h, w, c, &wts, None).unwrap();
            let (s, l1) = reference(&x, &y, h, w, c, win);
            assert!(
                (t.ssim - s).abs() < 1e-12,
                "{h}x{w}x{c} w{win}: {} vs {s}",
                t.ssim
            );
            assert!((t.mean_abs - l1).abs() < 1e-12);
            assert!((t.loss - (0.8 * l1 + 0.2 * (1.0 - s) / 2.0)).abs() < 1e-12);
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        for &(h, w, c, win) in &[(6, 7, 3, 3), (2, 3, 1, 3), (9, 8, 2, 5)] {
            let x = image(3, h * w * c);
            let y = image(4, h * w * c);
            let wts = LossWeights {
                window: win,
                ..Default::default()
            };
            let mut g = vec![0.0; x.len()];
            photometric_loss(&x, &y, h, w, c, &wts, Some(&mut g)).unwrap();
            let eps = 1e-6;
            for i in 0..x.len() {
                let (mut xp, mut xm) = (x.clone(), x.clone());
                xp[i] += eps;
                xm[i] -= eps;
                let lp = photometric_loss(&xp, &y, h, w, c, &wts, None).unwrap().loss;
                let lm = photometric_loss(&xm, &y, h, w, c, &wts, None).unwrap().loss;
                let fd = (lp - lm) / (2.0 * eps);
                assert!(
                    (fd - g[i]).abs() < 1e-8,
                    "{h}x{w}x{c} w{win} index {i}: analytic {} vs numeric {fd}",
                    g[i]
                );
            }
        }
    }

    #[test]
    fn f32_agrees_with_f64() {
        let (h, w, c) = (33, 47, 3);
        let x = image(5, h * w * c);
        let y = image(6, h * w * c);
        let (x32, y32): (Vec<f32>, Vec<f32>) = (
            x.iter().map(|&v| v as f32).collect(),
            y.iter().map(|&v| v as f32).collect(),
        );
        let wts = LossWeights::default();
        let (mut g64, mut g32) = (vec![0.0; x.len()], vec![0.0f32; x.len()]);
        let t64 = photometric_loss(&x, &y, h, w, c, &wts, Some(&mut g64)).unwrap();
        let t32 = photometric_loss(&x32, &y32, h, w, c, &wts, Some(&mut g32)).unwrap();
        assert!((t64.loss - t32.loss).abs() < 1e-5);
        let gmax = g64.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (a, b) in g64.iter().zip(&g32) {
            assert!((a - *b as f64).abs() < 1e-3 * gmax);
        }
    }

    #[test]
    fn identical_images_have_zero_dssim() {
        let x = image(7, 10 * 10 * 3);
        let t = photometric_loss(&x, &x, 10, 10, 3, &LossWeights::default(), None).unwrap();
        assert!((t.ssim - 1.0).abs() < 1e-12 && t.loss.abs() < 1e-12);
    }

    #[test]
    fn bad_inputs_name_the_argument() {
        let x = vec![0.5f32; 4 * 4 * 3];
        let w = LossWeights::default();
        let e = photometric_loss(&x, &x[1..], 4, 4, 3, &w, None).unwrap_err();
        assert_eq!(e.arg(), "target");
        let mut nan = x.clone();
        nan[5] = f32::NAN;
        assert_eq!(
            photometric_loss(&nan, &x, 4, 4, 3, &w, None)
                .unwrap_err()
                .arg(),
            "pred"
        );
        let even = LossWeights { window: 4, ..w };
        assert_eq!(
            photometric_loss(&x, &x, 4, 4, 3, &even, None)
                .unwrap_err()
                .arg(),
            "window"
        );
        let one = vec![0.5f32; 3];
        assert_eq!(
            photometric_loss(&one, &one, 1, 1, 3, &w, None)
                .unwrap_err()
                .arg(),
            "pred"
        );
        let mut g = vec![0.0f32; 5];
        assert_eq!(
            photometric_loss(&x, &x, 4, 4, 3, &w, Some(&mut g))
                .unwrap_err()
                .arg(),
            "grad"
        );
    }
}
