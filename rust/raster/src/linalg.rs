//! Tiny fixed-size linear algebra over any float type (f32 for the fast path, f64 for the
//! reference and gradient checks). Row-major `[[F; 3]; 3]` matrices.

use num_traits::Float;

/// Row-major 3x3 matrix.
pub type Mat3<F> = [[F; 3]; 3];
/// Row-major 2x3 matrix.
pub type Mat23<F> = [[F; 3]; 2];

/// Convert an f64 to `F`.
///
/// # Panics
/// If `F` cannot represent `v` (never for f32 or f64, which convert every f64).
#[inline(always)]
pub fn c<F: Float>(v: f64) -> F {
    F::from(v).unwrap()
}

/// `a * b` for 3x3 matrices.
#[inline(always)]
pub fn mul33<F: Float>(a: &Mat3<F>, b: &Mat3<F>) -> Mat3<F> {
    let mut out = [[F::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    out
}

/// Transpose of a 3x3 matrix.
#[inline(always)]
pub fn transpose<F: Float>(a: &Mat3<F>) -> Mat3<F> {
    let mut out = [[F::zero(); 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            out[i][j] = a[j][i];
        }
    }
    out
}

/// `a * v` for a 3x3 matrix and a 3-vector.
#[inline(always)]
pub fn mul3v<F: Float>(a: &Mat3<F>, v: [F; 3]) -> [F; 3] {
    [
        a[0][0] * v[0] + a[0][1] * v[1] + a[0][2] * v[2],
        a[1][0] * v[0] + a[1][1] * v[1] + a[1][2] * v[2],
        a[2][0] * v[0] + a[2][1] * v[1] + a[2][2] * v[2],
    ]
}

/// `a^T * v` for a 3x3 matrix and a 3-vector.
#[inline(always)]
pub fn mul3tv<F: Float>(a: &Mat3<F>, v: [F; 3]) -> [F; 3] {
    [
        a[0][0] * v[0] + a[1][0] * v[1] + a[2][0] * v[2],
        a[0][1] * v[0] + a[1][1] * v[1] + a[2][1] * v[2],
        a[0][2] * v[0] + a[1][2] * v[1] + a[2][2] * v[2],
    ]
}
