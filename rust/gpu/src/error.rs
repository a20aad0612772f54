//! Errors of the GPU path: each says what failed and what to do.

use sync4d_raster::RasterError;

/// What went wrong on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// No adapter fits the request (message names what was found and what to install).
    #[error("wgpu: {0}")]
    NoAdapter(String),
    /// The adapter refused to open a device.
    #[error("wgpu: could not open a device: {0}")]
    Device(String),
    /// Invalid input, as the CPU path reports it (argument name and problem).
    #[error(transparent)]
    Raster(#[from] RasterError),
    /// A buffer would exceed the device's limits.
    #[error("wgpu: {0}")]
    TooLarge(String),
    /// Reading results back failed (device lost, out of memory).
    #[error("wgpu: reading results back failed: {0}")]
    Readback(String),
}

/// Result of the GPU path.
pub type Result<T> = std::result::Result<T, GpuError>;
