//! The linear blend's epilogue: a Gaussian's blended node values applied to its canonical
//! state, and its exact backward.
//!
//! Each Gaussian's row `b_i` of the node-weighted sum ([`crate::blend`]) over the linear
//! blend's 19-column table holds a blended affine map `A` (9, row-major), a translation `t`
//! (3), a rotation quaternion `p` (4, w first) and a log-scale offset `dl` (3). Applied to the
//! Gaussian's canonical mean `x0`, unit quaternion `q0` and log-scales `l0`:
//!
//! ```text
//! x = A x0 + t
//! r = p (x) q0                 Hamilton product (rotate by q0, then by p)
//! q = r / max(|r|, 1e-12)
//! s = exp(l0 + dl)
//! ```
//!
//! Backward, given `gx`, `gq`, `gs`:
//!
//! ```text
//! gA = gx x0^T,  gt = gx,  gx0 = A^T gx
//! gr = (gq - q (q . gq)) / |r|          (gq / 1e-12 where |r| < 1e-12, as torch's clamp)
//! gp = gr (x) conj(q0),  gq0 = conj(p) (x) gr
//! gdl = gl0 = gs s
//! ```
//!
//! Row by row, parallel over chunks of Gaussians in the calling rayon pool: every value is the
//! same operations whatever the pool's size. In torch this is about fifteen elementwise calls
//! forward and thirty backward over [N, 3..19] tensors, each a pass over memory with its
//! autograd bookkeeping; here it is one pass each way.

use crate::error::{check_len, MotionError, Result};
use rayon::prelude::*;
use sync4d_scalar::quat::{quat_conj, quat_mul};
use sync4d_scalar::Real;

/// Columns of a linear blend's row: A (9), t (3), p (4), dl (3).
pub const LINEAR_COLUMNS: usize = 19;
/// Gaussians per parallel task.
const ROWS: usize = 512;
/// The floor of |r| (torch's `clamp_min(1e-12)` in `_normalize`).
const NORM_FLOOR: f64 = 1e-12;

/// Inputs of the epilogue: flat row-major slices of N Gaussians.
#[derive(Debug, Clone, Copy)]
pub struct LinearEpilogue<'a, T> {
    /// Blended node values, [N, 19] (module docstring).
    pub blended: &'a [T],
    /// Canonical means, [N, 3].
    pub x0: &'a [T],
    /// Canonical unit quaternions (w, x, y, z), [N, 4].
    pub q0: &'a [T],
    /// Canonical log-scales, [N, 3].
    pub log_s0: &'a [T],
}

/// Outputs of [`linear_epilogue_forward`]: deformed means [N, 3], unit quaternions [N, 4] and
/// scales [N, 3], overwritten.
#[derive(Debug)]
pub struct LinearEpilogueOut<'a, T> {
    /// Deformed means, [N, 3].
    pub means: &'a mut [T],
    /// Deformed unit quaternions, [N, 4].
    pub quats: &'a mut [T],
    /// Deformed scales (not logs), [N, 3].
    pub scales: &'a mut [T],
}

/// Gradient outputs of [`linear_epilogue_backward`], overwritten.
#[derive(Debug)]
pub struct LinearEpilogueGradsMut<'a, T> {
    /// dL/dblended, [N, 19].
    pub blended: &'a mut [T],
    /// dL/dx0, [N, 3].
    pub x0: &'a mut [T],
    /// dL/dq0, [N, 4].
    pub q0: &'a mut [T],
    /// dL/dlog_s0, [N, 3].
    pub log_s0: &'a mut [T],
}

impl<T: Real> LinearEpilogue<'_, T> {
    /// Check every length; returns N.
    pub fn validate(&self) -> Result<usize> {
        if !self.x0.len().is_multiple_of(3) {
            return Err(MotionError::invalid(
                "x0",
                format!("expected N * 3 values, got {}", self.x0.len()),
            ));
        }
        let n = self.x0.len() / 3;
        check_len("blended", self.blended, n * LINEAR_COLUMNS)?;
        check_len("q0", self.q0, n * 4)?;
        check_len("log_s0", self.log_s0, n * 3)?;
        Ok(n)
    }
}

#[inline(always)]
fn quat<T: Real>(s: &[T]) -> [T; 4] {
    [s[0], s[1], s[2], s[3]]
}

/// Row `i`'s unnormalised rotation r = p (x) q0, |r| and the divisor max(|r|, floor).
#[inline(always)]
fn rotation<T: Real>(b: &[T], q0: &[T]) -> ([T; 4], T, T) {
    let r = quat_mul(quat(&b[12..16]), quat(q0));
    let norm = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]).sqrt();
    let floor = T::from(NORM_FLOOR).unwrap();
    (r, norm, if norm > floor { norm } else { floor })
}

/// The deformed means, quaternions and scales of every Gaussian (module docstring).
pub fn linear_epilogue_forward<T: Real>(
    e: &LinearEpilogue<'_, T>,
    out: LinearEpilogueOut<'_, T>,
) -> Result<()> {
    let n = e.validate()?;
    check_len("means", out.means, n * 3)?;
    check_len("quats", out.quats, n * 4)?;
    check_len("scales", out.scales, n * 3)?;
    out.means
        .par_chunks_mut(ROWS * 3)
        .zip(out.quats.par_chunks_mut(ROWS * 4))
        .zip(out.scales.par_chunks_mut(ROWS * 3))
        .enumerate()
        .for_each(|(chunk, ((xs, qs), ss))| {
            let i0 = chunk * ROWS;
            for (r, ((x, q), s)) in xs
                .chunks_exact_mut(3)
                .zip(qs.chunks_exact_mut(4))
                .zip(ss.chunks_exact_mut(3))
                .enumerate()
            {
                let i = i0 + r;
                let b = &e.blended[i * LINEAR_COLUMNS..(i + 1) * LINEAR_COLUMNS];
                let x0 = &e.x0[3 * i..3 * i + 3];
                for a in 0..3 {
                    let row = &b[3 * a..3 * a + 3];
                    x[a] = ((row[0] * x0[0] + row[1] * x0[1]) + row[2] * x0[2]) + b[9 + a];
                }
                let (rq, _, div) = rotation(b, &e.q0[4 * i..4 * i + 4]);
                for a in 0..4 {
                    q[a] = rq[a] / div;
                }
                for a in 0..3 {
                    s[a] = (e.log_s0[3 * i + a] + b[16 + a]).exp();
                }
            }
        });
    Ok(())
}

/// The exact gradients of [`linear_epilogue_forward`] given dL/d(means, quats, scales)
/// `grad_means` [N, 3], `grad_quats` [N, 4], `grad_scales` [N, 3].
///
/// # Panics
/// Never for f32 or f64: the only fallible step is converting the norm floor (1e-12) to `T`.
pub fn linear_epilogue_backward<T: Real>(
    e: &LinearEpilogue<'_, T>,
    grad_means: &[T],
    grad_quats: &[T],
    grad_scales: &[T],
    grads: LinearEpilogueGradsMut<'_, T>,
) -> Result<()> {
    let n = e.validate()?;
    check_len("grad_means", grad_means, n * 3)?;
    check_len("grad_quats", grad_quats, n * 4)?;
    check_len("grad_scales", grad_scales, n * 3)?;
    check_len("grad_blended", grads.blended, n * LINEAR_COLUMNS)?;
    check_len("grad_x0", grads.x0, n * 3)?;
    check_len("grad_q0", grads.q0, n * 4)?;
    check_len("grad_log_s0", grads.log_s0, n * 3)?;
    grads
        .blended
        .par_chunks_mut(ROWS * LINEAR_COLUMNS)
        .zip(grads.x0.par_chunks_mut(ROWS * 3))
        .zip(grads.q0.par_chunks_mut(ROWS * 4))
        .zip(grads.log_s0.par_chunks_mut(ROWS * 3))
        .enumerate()
        .for_each(|(chunk, (((gbs, gxs), gqs), gls))| {
            let i0 = chunk * ROWS;
            for (r, (((gb, gx0), gq0), gl0)) in gbs
                .chunks_exact_mut(LINEAR_COLUMNS)
                .zip(gxs.chunks_exact_mut(3))
                .zip(gqs.chunks_exact_mut(4))
                .zip(gls.chunks_exact_mut(3))
                .enumerate()
            {
                let i = i0 + r;
                let b = &e.blended[i * LINEAR_COLUMNS..(i + 1) * LINEAR_COLUMNS];
                let x0 = &e.x0[3 * i..3 * i + 3];
                let q0 = quat(&e.q0[4 * i..4 * i + 4]);
                let gx = &grad_means[3 * i..3 * i + 3];
                // x = A x0 + t
                for a in 0..3 {
                    for c in 0..3 {
                        gb[3 * a + c] = gx[a] * x0[c];
                    }
                    gb[9 + a] = gx[a];
                }
                for c in 0..3 {
                    gx0[c] = (b[c] * gx[0] + b[3 + c] * gx[1]) + b[6 + c] * gx[2];
                }
                // q = r / max(|r|, floor), r = p (x) q0
                let (rq, norm, div) = rotation(b, &q0);
                let gq = quat(&grad_quats[4 * i..4 * i + 4]);
                let gr = if norm > T::from(NORM_FLOOR).unwrap() {
                    let q = [rq[0] / div, rq[1] / div, rq[2] / div, rq[3] / div];
                    let dot = (q[0] * gq[0] + q[1] * gq[1]) + (q[2] * gq[2] + q[3] * gq[3]);
                    [0, 1, 2, 3].map(|a| (gq[a] - q[a] * dot) / div)
                } else {
                    [0, 1, 2, 3].map(|a| gq[a] / div)
                };
                gb[12..16].copy_from_slice(&quat_mul(gr, quat_conj(q0)));
                gq0.copy_from_slice(&quat_mul(quat_conj(quat(&b[12..16])), gr));
                // s = exp(l0 + dl)
                for a in 0..3 {
                    let s = (e.log_s0[3 * i + a] + b[16 + a]).exp();
                    let g = grad_scales[3 * i + a] * s;
                    gb[16 + a] = g;
                    gl0[a] = g;
                }
            }
        });
    Ok(())
}
