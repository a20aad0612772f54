//! The element types the kernels accept: f32 (training) and f64 (reference, gradient checks).

/// A float element type of the kernels.
pub trait Real: num_traits::Float + Send + Sync + std::fmt::Debug + 'static {
    /// `exp(x)` for `x <= 0` (the softmax's shifted logits): for f32 a branch-free polynomial
    /// (Cephes, within 2 ulp), 0 below -87 (exp(x) turns denormal below -87.3, and denormal
    /// arithmetic is slow on x86; torch's exp gives a denormal or 0 there); the exact function
    /// for f64. NaN stays NaN.
    fn exp_neg(self) -> Self;
}

impl Real for f32 {
    #[inline(always)]
    fn exp_neg(self) -> Self {
        // Comparisons rather than max / min, so that a NaN stays NaN.
        let x = if self < LO { LO } else { self };
        let x = if x > HI { HI } else { x };
        // Round to nearest by the 1.5 * 2^23 trick (no call to floorf on baseline x86-64).
        let n = (x * std::f32::consts::LOG2_E + ROUND) - ROUND;
        let r = x - n * LN2_HI - n * LN2_LO;
        let mut p = P[0];
        for c in &P[1..] {
            p = p * r + c;
        }
        let poly = p * r * r + r + 1.0;
        // n is an integer in [-126, 126] (0 for a NaN, whose poly is NaN).
        let e = poly * f32::from_bits(((n as i32 + 127) as u32) << 23);
        // 0 below LO, so that no denormal weight reaches the arithmetic downstream.
        if self < LO {
            0.0
        } else {
            e
        }
    }
}

impl Real for f64 {
    #[inline(always)]
    fn exp_neg(self) -> Self {
        self.exp()
    }
}

const LO: f32 = -87.0;
const HI: f32 = 87.0;
const ROUND: f32 = 12_582_912.0;
const LN2_HI: f32 = 0.693_359_4;
const LN2_LO: f32 = -2.121_944_4e-4;
const P: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

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
