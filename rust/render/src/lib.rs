//! sync4d-render: render sync4d checkpoints without Python. [`checkpoint`] reads the
//! safetensors checkpoints Python writes (per-Gaussian or control-node motion), [`deform`]
//! evaluates the deformation MLP at any time (per Gaussian, or per node and then blended),
//! [`render`] draws a camera's view with the CPU or wgpu rasterizer. The `sync4d-render`
//! binary wraps them in a command line (one view, a time sweep or an orbit, as PNGs).

pub mod checkpoint;
pub mod deform;
pub mod render;
