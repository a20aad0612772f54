//! The f32 `exp` of the kernels (Cephes' `expf`): `exp(x) = 2^n * p(r)` with `n` the integer
//! nearest `x / ln 2` and `r = x - n ln 2` (ln 2 split in two for an exact product), `p` a
//! degree-7 polynomial. The constants and the polynomial of `r` live here once; each caller
//! chooses how to clamp, round `n` and scale by `2^n` (sync4d-raster's `fast_exp` and its AVX2
//! lanes, sync4d-motion's softmax through [`crate::Real::exp_neg`]).

/// Lower clamp of the argument (exp turns denormal below -87.3).
pub const EXP_LO: f32 = -87.0;
/// Upper clamp of the argument.
pub const EXP_HI: f32 = 87.0;
/// High part of ln 2 (exact in f32 times any `n` in range).
pub const LN2_HI: f32 = 0.693_359_4;
/// Low part of ln 2.
pub const LN2_LO: f32 = -2.121_944_4e-4;
/// Coefficients of the polynomial, highest degree first.
pub const EXP_P: [f32; 6] = [
    1.987_569_1e-4,
    1.398_199_9e-3,
    8.333_452e-3,
    4.166_579_6e-2,
    1.666_666_5e-1,
    0.5,
];

/// `p(r)` for `r = x - n ln 2`: the factor of `exp(x)` beside `2^n` (`n` already rounded).
#[inline(always)]
pub fn exp_poly(x: f32, n: f32) -> f32 {
    let r = x - n * LN2_HI - n * LN2_LO;
    let mut p = EXP_P[0];
    for c in &EXP_P[1..] {
        p = p * r + c;
    }
    p * r * r + r + 1.0
}
