//! Real spherical harmonics up to degree 3 (Sloan's "Efficient Spherical Harmonic Evaluation",
//! the basis and sign convention of 3DGS/gsplat) and their backward, including the
//! view-direction term.
//!
//! The basis is written once, generic over a number type: plain f64 for the forward, and a
//! forward-mode dual number carrying d/d(x, y, z) for the backward, so the direction gradient is
//! exact by construction. Parallel over chunks of Gaussians.

use crate::error::{check_finite, check_len, RasterError, Result};
use rayon::prelude::*;
use std::ops::{Add, Mul, Neg, Sub};
use sync4d_scalar::Real;

/// Highest supported degree.
pub const MAX_SH_DEGREE: u32 = 3;

/// Number of basis functions of degree `d`: `(d + 1)^2`.
pub fn num_bases(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// Arithmetic the basis needs.
trait ShNum:
    Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + Neg<Output = Self>
{
    fn k(v: f64) -> Self;
}

impl ShNum for f64 {
    #[inline(always)]
    fn k(v: f64) -> Self {
        v
    }
}

/// A value with its gradient w.r.t. the three direction components.
#[derive(Debug, Clone, Copy)]
struct Dual3 {
    v: f64,
    d: [f64; 3],
}

impl Add for Dual3 {
    type Output = Dual3;
    #[inline(always)]
    fn add(self, o: Dual3) -> Dual3 {
        Dual3 {
            v: self.v + o.v,
            d: [self.d[0] + o.d[0], self.d[1] + o.d[1], self.d[2] + o.d[2]],
        }
    }
}

impl Sub for Dual3 {
    type Output = Dual3;
    #[inline(always)]
    fn sub(self, o: Dual3) -> Dual3 {
        self + (-o)
    }
}

impl Neg for Dual3 {
    type Output = Dual3;
    #[inline(always)]
    fn neg(self) -> Dual3 {
        Dual3 {
            v: -self.v,
            d: [-self.d[0], -self.d[1], -self.d[2]],
        }
    }
}

impl Mul for Dual3 {
    type Output = Dual3;
    #[inline(always)]
    fn mul(self, o: Dual3) -> Dual3 {
        Dual3 {
            v: self.v * o.v,
            d: [
                self.d[0] * o.v + self.v * o.d[0],
                self.d[1] * o.v + self.v * o.d[1],
                self.d[2] * o.v + self.v * o.d[2],
            ],
        }
    }
}

impl ShNum for Dual3 {
    #[inline(always)]
    fn k(v: f64) -> Self {
        Dual3 { v, d: [0.0; 3] }
    }
}

/// Evaluate the first `out.len()` (1, 4, 9 or 16) basis functions at unit direction (x, y, z).
#[inline(always)]
fn basis<T: ShNum>(x: T, y: T, z: T, out: &mut [T]) {
    let k = T::k;
    out[0] = k(0.282_094_791_773_878_1);
    if out.len() <= 1 {
        return;
    }
    let a1 = k(-0.488_602_511_902_92);
    out[1] = a1 * y;
    out[2] = -(a1 * z);
    out[3] = a1 * x;
    if out.len() <= 4 {
        return;
    }
    let z2 = z * z;
    let b2 = k(-1.092_548_430_592_079) * z;
    let a2 = k(0.546_274_215_296_039_5);
    let c1 = x * x - y * y;
    let s1 = k(2.0) * x * y;
    out[6] = k(0.946_174_695_757_560_1) * z2 - k(0.315_391_565_252_520_1);
    out[7] = b2 * x;
    out[5] = b2 * y;
    out[8] = a2 * c1;
    out[4] = a2 * s1;
    if out.len() <= 9 {
        return;
    }
    let c3 = k(-2.285_228_997_322_329) * z2 + k(0.457_045_799_464_465_8);
    let b3 = k(1.445_305_721_320_277) * z;
    let a3 = k(-0.590_043_589_926_643_5);
    let c2 = x * c1 - y * s1;
    let s2 = x * s1 + y * c1;
    out[12] = z * (k(1.865_881_662_950_577) * z2 - k(1.119_528_997_770_346));
    out[13] = c3 * x;
    out[11] = c3 * y;
    out[14] = b3 * c1;
    out[10] = b3 * s1;
    out[15] = a3 * c2;
    out[9] = a3 * s2;
}

/// Unit direction and the norm used (`max(|d|, 1e-12)`, like `F.normalize`).
#[inline(always)]
fn normalise(d: [f64; 3]) -> ([f64; 3], f64) {
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt().max(1e-12);
    ([d[0] / n, d[1] / n, d[2] / n], n)
}

fn check_sh_args<F: Real>(
    degree: u32,
    dirs: &[F],
    coeffs: &[F],
    bases: usize,
    channels: usize,
) -> Result<usize> {
    if degree > MAX_SH_DEGREE {
        return Err(RasterError::invalid(
            "degree",
            format!("must be 0..={MAX_SH_DEGREE}, got {degree}"),
        ));
    }
    if bases < num_bases(degree) {
        return Err(RasterError::invalid(
            "coeffs",
            format!(
                "degree {degree} needs >= {} coefficients per channel, got {bases}",
                num_bases(degree)
            ),
        ));
    }
    if channels == 0 {
        return Err(RasterError::invalid("coeffs", "need at least one channel"));
    }
    if !dirs.len().is_multiple_of(3) {
        return Err(RasterError::invalid("dirs", "expected shape [N, 3]"));
    }
    let n = dirs.len() / 3;
    check_len("coeffs", coeffs, n * bases * channels)?;
    check_finite("dirs", dirs)?;
    check_finite("coeffs", coeffs)?;
    Ok(n)
}

const CHUNK: usize = 1024;

/// Evaluate SH colours: `dirs` N*3 (any length, normalised inside), `coeffs` N*K*C (K >= (degree
/// + 1)^2 bases per channel), `out` N*C = sum_k basis_k(dir) coeffs[k, c]. No +0.5 offset.
pub fn sh_forward<F: Real>(
    degree: u32,
    dirs: &[F],
    coeffs: &[F],
    bases: usize,
    channels: usize,
    out: &mut [F],
) -> Result<()> {
    let n = check_sh_args(degree, dirs, coeffs, bases, channels)?;
    check_len("out", out, n * channels)?;
    let nb = num_bases(degree);
    out.par_chunks_mut(CHUNK * channels)
        .enumerate()
        .for_each(|(ci, o)| {
            let mut b = [0.0f64; 16];
            for l in 0..o.len() / channels {
                let i = ci * CHUNK + l;
                let (u, _) = normalise([
                    dirs[3 * i].to_f64(),
                    dirs[3 * i + 1].to_f64(),
                    dirs[3 * i + 2].to_f64(),
                ]);
                basis(u[0], u[1], u[2], &mut b[..nb]);
                for c in 0..channels {
                    let mut acc = 0.0;
                    for (kk, bk) in b[..nb].iter().enumerate() {
                        acc += bk * coeffs[(i * bases + kk) * channels + c].to_f64();
                    }
                    o[l * channels + c] = F::from_f64(acc);
                }
            }
        });
    Ok(())
}

/// Backward of [`sh_forward`]: writes dL/d dirs (N*3, through the normalisation) and dL/d coeffs
/// (N*K*C; bases above the degree get zero), overwriting both.
#[allow(clippy::too_many_arguments)]
pub fn sh_backward<F: Real>(
    degree: u32,
    dirs: &[F],
    coeffs: &[F],
    bases: usize,
    channels: usize,
    v_out: &[F],
    v_dirs: &mut [F],
    v_coeffs: &mut [F],
) -> Result<()> {
    let n = check_sh_args(degree, dirs, coeffs, bases, channels)?;
    check_len("v_out", v_out, n * channels)?;
    check_finite("v_out", v_out)?;
    check_len("v_dirs", v_dirs, n * 3)?;
    check_len("v_coeffs", v_coeffs, n * bases * channels)?;
    let nb = num_bases(degree);
    v_dirs
        .par_chunks_mut(CHUNK * 3)
        .zip(v_coeffs.par_chunks_mut(CHUNK * bases * channels))
        .enumerate()
        .for_each(|(ci, (vd, vco))| {
            let mut b = [Dual3::k(0.0); 16];
            for l in 0..vd.len() / 3 {
                let i = ci * CHUNK + l;
                let (u, norm) = normalise([
                    dirs[3 * i].to_f64(),
                    dirs[3 * i + 1].to_f64(),
                    dirs[3 * i + 2].to_f64(),
                ]);
                let seed = |j: usize| {
                    let mut d = [0.0; 3];
                    d[j] = 1.0;
                    Dual3 { v: u[j], d }
                };
                basis(seed(0), seed(1), seed(2), &mut b[..nb]);
                let mut v_u = [0.0f64; 3];
                let row = &mut vco[l * bases * channels..(l + 1) * bases * channels];
                row.fill(F::zero());
                for (kk, bk) in b[..nb].iter().enumerate() {
                    let mut v_b = 0.0;
                    for c in 0..channels {
                        let vo = v_out[i * channels + c].to_f64();
                        row[kk * channels + c] = F::from_f64(bk.v * vo);
                        v_b += vo * coeffs[(i * bases + kk) * channels + c].to_f64();
                    }
                    for j in 0..3 {
                        v_u[j] += v_b * bk.d[j];
                    }
                }
                // u = d / |d|  =>  v_d = (v_u - u (u . v_u)) / |d|.
                let dot = u[0] * v_u[0] + u[1] * v_u[1] + u[2] * v_u[2];
                for j in 0..3 {
                    vd[3 * l + j] = F::from_f64((v_u[j] - u[j] * dot) / norm);
                }
            }
        });
    Ok(())
}
