//! The rasterizer on a wgpu device: the same stages, inputs, outputs and validation as
//! sync4d-raster's CPU path (projection, depth sort, tile binning, compositing), with host
//! slices in and out. Buffers grow as needed and are reused across calls.
//!
//! One file per concern: `rasterizer` ([`GpuRasterizer`], [`GpuRasterState`]: depth sort,
//! binning, compositing forward and backward), `project` (projection forward and backward),
//! `layout` (the compositing layout policy: [`BlendLayout`], [`ColumnHalves`]), `kernels` (WGSL
//! sources, shader assembly, pipelines), `params` (the host side of the kernels' interface),
//! `buffers` (buffer pool, limits, uploads and readbacks), `window` (compositing in windows:
//! [`CompositingWindow`]) and `profile` (per-stage timings).

mod buffers;
mod kernels;
mod layout;
mod params;
mod profile;
mod project;
mod rasterizer;
mod window;

pub use layout::{BlendLayout, ColumnHalves};
pub use rasterizer::{GpuRasterState, GpuRasterizer};
pub use window::CompositingWindow;
