//! sync4d-raster: a multithreaded CPU rasterizer for 3D Gaussian splats with exact gradients.
//!
//! Pipeline (each stage has a forward and an exact backward):
//! 1. [`project::project_forward`]: 3D Gaussians + pinhole camera → screen-space splats
//!    (centre, conic, depth, opacity, radius). Parallel per Gaussian.
//! 2. [`bins::TileBins`]: splats → per-16x16-tile lists in depth order. Parallel counting sort.
//! 3. [`blend::rasterize_forward`]: front-to-back compositing of any number of feature channels,
//!    accumulated alpha and depth. Parallel per tile.
//!
//! [`sh`] evaluates view-dependent colour from spherical harmonics (the training loss on the
//! rendered image is the sync4d-loss crate). [`reference`] is the plain
//! f64 per-pixel compositor the fast path is tested against. The crate knows nothing of Python;
//! all inputs are flat row-major slices and every bad input is a [`RasterError`] naming the
//! argument.
// Index loops mirror the maths (row/column indices) in the small fixed-size kernels.
#![allow(clippy::needless_range_loop)]

pub mod bins;
pub mod blend;
pub mod camera;
pub mod error;
mod lanes;
pub mod linalg;
pub mod project;
pub use sync4d_scalar::real;
pub mod reference;
pub mod sh;

pub use blend::{
    rasterize_backward, rasterize_forward, BlendSettings, Composite, Counters, ImageGrads,
    ImageMut, RasterState, SplatGradsMut, Splats, ALPHA_MIN, T_MIN,
};
pub use camera::Camera;
pub use error::{RasterError, Result};
pub use lanes::fast_exp;
pub use project::{
    project_backward, project_forward, GaussianGradsMut, Gaussians, ProjectSettings, Projection,
    ProjectionGrads, ProjectionMut,
};
pub use reference::{rasterize_backward_reference, rasterize_forward_reference};
pub use sh::{sh_backward, sh_forward};

/// Side of a square screen tile, pixels.
pub const TILE_SIZE: u32 = 16;
