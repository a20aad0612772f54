//! sync4d-gpu: the sync4d rasterizer as WGSL compute kernels driven by wgpu, so it runs on any
//! Vulkan, Metal or DX12 adapter, and on CPUs through lavapipe (Mesa's CPU Vulkan driver).
//!
//! Same stages, conventions, inputs and outputs as the CPU crate [`sync4d_raster`]:
//! 1. projection of 3D Gaussians to screen-space splats (f32 on the device);
//! 2. depth order of the visible splats (a stable radix sort of the depth keys in index order:
//!    the (depth, index) order);
//! 3. tile binning (per-chunk tile counts from 2D difference tables, an exclusive scan, an
//!    in-order scatter: a stable counting sort by tile of the depth order, deterministic on any
//!    hardware);
//! 4. per-tile front-to-back compositing, one workgroup per 16x16 tile ([`BlendLayout`]: one
//!    pixel per invocation on GPUs, many on CPU adapters, gradient sums by subgroup operations
//!    where the device has them); long tile lists over several dispatches
//!    ([`CompositingWindow`]), as lavapipe's driver ends a shader's loops after 65,535 trips.
//!
//! [`GpuDevice`] picks the adapter ([`AdapterChoice`]); [`GpuRasterizer`] owns the compiled
//! kernels and reusable buffers. Inputs are validated exactly as on the CPU path and every
//! failure is a [`GpuError`], never a panic.

pub mod device;
pub mod error;
pub mod raster;

pub use device::{list_adapters, AdapterChoice, AdapterSummary, GpuDevice};
pub use error::{GpuError, Result};
pub use raster::{BlendLayout, ColumnHalves, CompositingWindow, GpuRasterState, GpuRasterizer};
