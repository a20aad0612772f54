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

/// Rotation matrix of the normalised quaternion `q = (w, x, y, z)` (must already be unit).
#[inline(always)]
pub fn quat_to_rotmat<F: Float>(q: [F; 4]) -> Mat3<F> {
    let [w, x, y, z] = q;
    let one = F::one();
    let two = c::<F>(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Gradient w.r.t. the unit quaternion `q` of a loss whose gradient w.r.t. `quat_to_rotmat(q)` is
/// `v` (element-wise, row-major).
#[inline(always)]
pub fn quat_to_rotmat_vjp<F: Float>(q: [F; 4], v: &Mat3<F>) -> [F; 4] {
    let [w, x, y, z] = q;
    let two = c::<F>(2.0);
    let gw = -z * v[0][1] + y * v[0][2] + z * v[1][0] - x * v[1][2] - y * v[2][0] + x * v[2][1];
    let gx = y * v[0][1] + z * v[0][2] + y * v[1][0] - two * x * v[1][1] - w * v[1][2]
        + z * v[2][0]
        + w * v[2][1]
        - two * x * v[2][2];
    let gy = -two * y * v[0][0] + x * v[0][1] + w * v[0][2] + x * v[1][0] + z * v[1][2]
        - w * v[2][0]
        + z * v[2][1]
        - two * y * v[2][2];
    let gz = -two * z * v[0][0] - w * v[0][1] + x * v[0][2] + w * v[1][0] - two * z * v[1][1]
        + y * v[1][2]
        + x * v[2][0]
        + y * v[2][1];
    [two * gw, two * gx, two * gy, two * gz]
}
