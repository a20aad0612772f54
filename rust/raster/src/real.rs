//! The element types the kernels accept: f32 (fast path, training) and f64 (reference path,
//! gradient checks). Per-Gaussian math runs in f64 internally for both, so huge or tiny scales
//! cannot overflow intermediate covariances.

/// A float element type accepted at the crate boundary.
pub trait Real:
    num_traits::Float + Copy + Send + Sync + Default + std::fmt::Debug + 'static
{
    /// Convert from f64 (rounding for f32; may give +-inf for out-of-range values).
    fn from_f64(v: f64) -> Self;
    /// Widen to f64.
    fn to_f64(self) -> f64;
    /// Largest finite value of this type, as f64.
    const MAX_F64: f64;
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
}

/// Whether `v` is finite once stored as `F`.
#[inline(always)]
pub fn fits<F: Real>(v: f64) -> bool {
    v.is_finite() && v.abs() <= F::MAX_F64
}
