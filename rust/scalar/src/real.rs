//! The element types the kernels accept: f32 (fast path, training) and f64 (reference path,
//! gradient checks). Per-Gaussian math in the raster runs in f64 internally for both, so huge or
//! tiny scales cannot overflow intermediate covariances; the motion softmax takes its `exp`
//! from [`Real::exp_neg`].

use crate::exp::{exp_poly, EXP_HI, EXP_LO};

/// A float element type of the kernels (accepted at the crate boundaries).
pub trait Real:
    num_traits::Float + Copy + Send + Sync + Default + std::fmt::Debug + 'static
{
    /// Convert from f64 (rounding for f32; may give +-inf for out-of-range values).
    fn from_f64(v: f64) -> Self;
    /// Widen to f64.
    fn to_f64(self) -> f64;
    /// Largest finite value of this type, as f64.
    const MAX_F64: f64;
    /// `exp(x)` for `x <= 0` (the softmax's shifted logits): for f32 a branch-free polynomial
    /// (Cephes, within 2 ulp), 0 below -87 (exp(x) turns denormal below -87.3, and denormal
    /// arithmetic is slow on x86; torch's exp gives a denormal or 0 there); the exact function
    /// for f64. NaN stays NaN.
    fn exp_neg(self) -> Self;
}

impl Real for f32 {
    #[inline(always)]
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self as f64
    }
    const MAX_F64: f64 = f32::MAX as f64;
    #[inline(always)]
    fn exp_neg(self) -> Self {
        // Comparisons rather than max / min, so that a NaN stays NaN.
        let x = if self < EXP_LO { EXP_LO } else { self };
        let x = if x > EXP_HI { EXP_HI } else { x };
        // Round to nearest by the 1.5 * 2^23 trick (no call to floorf on baseline x86-64).
        let n = (x * std::f32::consts::LOG2_E + ROUND) - ROUND;
        let poly = exp_poly(x, n);
        // n is an integer in [-126, 126] (0 for a NaN, whose poly is NaN).
        let e = poly * f32::from_bits(((n as i32 + 127) as u32) << 23);
        // 0 below EXP_LO, so that no denormal weight reaches the arithmetic downstream.
        if self < EXP_LO {
            0.0
        } else {
            e
        }
    }
}

impl Real for f64 {
    #[inline(always)]
    fn from_f64(v: f64) -> Self {
        v
    }
    #[inline(always)]
    fn to_f64(self) -> f64 {
        self
    }
    const MAX_F64: f64 = f64::MAX;
    #[inline(always)]
    fn exp_neg(self) -> Self {
        self.exp()
    }
}

/// 1.5 * 2^23: adding and subtracting it rounds an f32 of magnitude below 2^22 to an integer.
const ROUND: f32 = 12_582_912.0;

/// Whether `v` is finite once stored as `F`.
#[inline(always)]
pub fn fits<F: Real>(v: f64) -> bool {
    v.is_finite() && v.abs() <= F::MAX_F64
}

#[cfg(test)]
mod tests {
    use super::Real;

    #[test]
    fn f32_exp_is_within_two_ulp() {
        let mut worst = 0.0f64;
        for i in 0..=870_000 {
            let x = -(i as f32) * 1e-4;
            let want = (x as f64).exp();
            let got = x.exp_neg() as f64;
            let ulp = (want as f32).abs() * f32::EPSILON;
            worst = worst.max((got - want).abs() / ulp as f64);
        }
        assert!(worst <= 2.0, "worst error {worst} ulp");
        assert_eq!(0.0f32.exp_neg(), 1.0);
        assert!(f32::NAN.exp_neg().is_nan());
        assert_eq!(f32::NEG_INFINITY.exp_neg(), 0.0);
        assert_eq!((-87.5f32).exp_neg(), 0.0);
        assert!((-86.9f32).exp_neg() >= f32::MIN_POSITIVE);
    }
}
