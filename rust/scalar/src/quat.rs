//! Quaternions `(w, x, y, z)`, w first, as `[F; 4]` over any float type: the Hamilton product
//! and conjugate (sync4d-motion's epilogue, sync4d-render's deformation), the rotation matrix of
//! a unit quaternion and its vector-Jacobian product (sync4d-raster's projection,
//! sync4d-render). Matrices are row-major `[[F; 3]; 3]`.

use num_traits::Float;

/// Hamilton product a (x) b of quaternions (w, x, y, z).
#[inline(always)]
pub fn quat_mul<F: Float>(a: [F; 4], b: [F; 4]) -> [F; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

/// The conjugate (w, -x, -y, -z).
#[inline(always)]
pub fn quat_conj<F: Float>(q: [F; 4]) -> [F; 4] {
    [q[0], -q[1], -q[2], -q[3]]
}

/// Rotation matrix (row-major) of the normalised quaternion `q = (w, x, y, z)` (must already
/// be unit).
#[inline(always)]
pub fn quat_to_rotmat<F: Float>(q: [F; 4]) -> [[F; 3]; 3] {
    let [w, x, y, z] = q;
    let one = F::one();
    let two = one + one;
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
pub fn quat_to_rotmat_vjp<F: Float>(q: [F; 4], v: &[[F; 3]; 3]) -> [F; 4] {
    let [w, x, y, z] = q;
    let two = F::one() + F::one();
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
