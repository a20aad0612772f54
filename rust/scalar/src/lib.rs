//! sync4d-scalar: the one home of the scalar vocabulary that sync4d-raster, sync4d-motion,
//! sync4d-loss and sync4d-render (and the bindings) share, so that none of them keeps its own
//! copy.
//!
//! [`real`]: the element trait [`Real`] the kernels are generic over (f32 for the fast path and
//! training, f64 for the reference path and gradient checks) and [`fits`]. [`quat`]: the
//! quaternion helpers (Hamilton product, conjugate, rotation matrix and its vector-Jacobian
//! product), written once over `num_traits::Float`. [`exp`]: the constants and the reduced
//! polynomial of the Cephes-style f32 `exp` that the raster's SIMD kernels and the motion
//! softmax each build on.
//!
//! A leaf crate: it depends on num-traits only, so every other crate may use it without an
//! import circle. Each helper computes the same expressions in the same order as the copies it
//! replaced: results are bit-identical.

pub mod exp;
pub mod quat;
pub mod real;

pub use real::{fits, Real};
