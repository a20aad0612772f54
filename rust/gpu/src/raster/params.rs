//! The host side of the kernels' interface: workgroup sizes, the layouts of the packed splat
//! and counters buffers, and the uniform parameter structs, each matching its WGSL declaration.
//! Kept together so that a change to a shader's bindings has one Rust file to follow.

/// Invocations per workgroup of the 1D kernels.
pub(super) const WG: u32 = 256;
/// Invocations per workgroup of the chunk-serial kernels (radix count and scatter, tile
/// scatter): a few hundred chunks make many small workgroups, which lavapipe spreads evenly
/// over its threads.
pub(super) const CHUNK_WG: u32 = 16;
/// Values per scan block (256 invocations x 4).
pub(super) const SCAN_BLOCK: u32 = 1024;

/// Floats per packed splat: mean x, mean y, conic a, b, c, opacity, depth, padding.
pub(super) const SPLAT_FLOATS: usize = 8;
/// The compositing counters buffer (u32s): evaluated lo/hi, blended lo/hi, the compositing
/// kernels' loop check flag, the deepest list position composited (the forward's largest
/// last contributor), pad, the scatter's loop check flag.
pub(super) const COUNTERS_BYTES: u64 = 32;
/// Its first part, which compositing writes (up to the scatter's flag).
pub(super) const COMPOSITING_COUNTERS_BYTES: u64 = 28;

/// Parameters of the projection kernel (layout of `Params` in project.wgsl).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct ProjectParams {
    pub(super) rot: [[f32; 4]; 3],
    pub(super) intr: [f32; 4],
    pub(super) size: [f32; 4],
    pub(super) lims: [f32; 4],
    pub(super) clip: [f32; 4],
    pub(super) count: [u32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct SortParams {
    pub(super) n: u32,
    pub(super) chunks: u32,
    pub(super) chunk_size: u32,
    pub(super) shift: u32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct ScanParams {
    pub(super) len: u32,
    pub(super) blocks: u32,
    pub(super) pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct BinParams {
    pub(super) visible: u32,
    pub(super) chunks: u32,
    pub(super) chunk_size: u32,
    pub(super) tiles_x: u32,
    pub(super) tiles_y: u32,
    pub(super) num_tiles: u32,
    /// `sum_lines`: 0 along x, 1 along y.
    pub(super) axis: u32,
    /// Trips of the scatter's loop check (2).
    pub(super) canary: u32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct BlendParams {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) tiles_x: u32,
    pub(super) tiles_y: u32,
    pub(super) alpha_min: f32,
    pub(super) alpha_max: f32,
    pub(super) t_min: f32,
    pub(super) n: u32,
    pub(super) canary: u32,
    /// This dispatch's window of each tile's list: list positions [win_lo, win_hi).
    pub(super) win_lo: u32,
    pub(super) win_hi: u32,
    /// FIRST_WINDOW | LAST_WINDOW bits (blend.wgsl).
    pub(super) window: u32,
}

/// `BlendParams::window` bits: the first window walked (fresh state) and the last (final
/// outputs); see blend.wgsl.
pub(super) const FIRST_WINDOW: u32 = 1;
pub(super) const LAST_WINDOW: u32 = 2;
