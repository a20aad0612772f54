//! The rasterizer on a wgpu device: the same stages, inputs, outputs and validation as
//! sync4d-raster's CPU path (projection, depth sort, tile binning, compositing), with host
//! slices in and out. Buffers grow as needed and are reused across calls.

use std::collections::HashMap;

use sync4d_raster::blend::check_image_size;
use sync4d_raster::{
    BlendSettings, Camera, Counters, GaussianGradsMut, Gaussians, ImageGrads, ImageMut,
    ProjectSettings, ProjectionGrads, ProjectionMut, RasterError, SplatGradsMut, Splats, TILE_SIZE,
};
use wgpu::util::DeviceExt;

use crate::device::GpuDevice;
use crate::error::{GpuError, Result};

const PROJECT_WGSL: &str = include_str!("shaders/project.wgsl");
const SORT_WGSL: &str = include_str!("shaders/sort.wgsl");
const SCAN_WGSL: &str = include_str!("shaders/scan.wgsl");
const BIN_WGSL: &str = include_str!("shaders/bin.wgsl");
const BLEND_WGSL: &str = include_str!("shaders/blend.wgsl");
/// The loop check of the kernels llvmpipe may cut short, appended to the modules that use it.
const LOOP_CHECK_WGSL: &str = include_str!("shaders/loop_check.wgsl");

/// Invocations per workgroup of the 1D kernels.
const WG: u32 = 256;
/// Invocations per workgroup of the chunk-serial kernels (radix count and scatter, tile
/// scatter): a few hundred chunks make many small workgroups, which lavapipe spreads evenly
/// over its threads.
const CHUNK_WG: u32 = 16;
/// Values per scan block (256 invocations x 4).
const SCAN_BLOCK: u32 = 1024;
/// Tile intersections per visible splat below which lavapipe's backward compositing splits
/// rows into column halves. cpu_vs_wgpu, 100k splats 800x800, medians of interleaved runs,
/// backward compositing time over the CPU path's forward time: with halves 5.1 / 4.1 / 3.0
/// against 6.5 / 5.0 / 2.8 at 4.0 / 4.9 / 7.8 intersections per splat (SYNC4D_SCALE 0.08 /
/// 0.1 / 0.15); 1.67 against 1.33 at 163 (an earlier build). The forward was slower with
/// halves at all four (2.9 / 2.5 / 2.3 against 2.5 / 2.3 / 1.8 at the small ones).
const SMALL_SPLAT_TILES: u32 = 7;
/// Most chunks the binning cuts the depth order into on GPUs (bounds the count table to
/// tiles x this many entries).
const MAX_CHUNKS: u32 = 1024;
/// Chunks per CPU thread on CPU adapters. The chunk-serial kernels' work does not depend on
/// the chunk count, but the count tables and their scans grow with it: at 100k splats 800x800
/// (SYNC4D_SCALE=0.1) on lavapipe, 391 chunks made a 977k-entry tile table, and the depth
/// sort, tile counts and tile scan took 20 / 14 / 24 ms; with 32 chunks (2 threads) 11 / 8 /
/// 3 ms. 16 per thread keep several workgroups per thread.
const CPU_CHUNKS_PER_THREAD: u32 = 16;
/// Fewest entries per chunk.
const MIN_CHUNK: u32 = 256;
/// Loop trips one invocation of a chunk-serial kernel may run (llvmpipe ends a shader's loops
/// after 65,535 trips in all; the rest is margin for the digit loop and the loop check).
const CHUNK_TRIPS: u32 = 60_000;
/// Floats per packed splat: mean x, mean y, conic a, b, c, opacity, depth, padding.
const SPLAT_FLOATS: usize = 8;
/// The compositing counters buffer (u32s): evaluated lo/hi, blended lo/hi, the compositing
/// kernels' loop check flag, the deepest list position composited (the forward's largest
/// last contributor), pad, the scatter's loop check flag.
const COUNTERS_BYTES: u64 = 32;
/// Its first part, which compositing writes (up to the scatter's flag).
const COMPOSITING_COUNTERS_BYTES: u64 = 28;
/// Compositing thresholds, as in sync4d-raster.
const ALPHA_MIN: f32 = 1.0 / 255.0;
const T_MIN: f32 = 1e-4;

/// Parameters of the projection kernel (layout of `Params` in project.wgsl).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ProjectParams {
    rot: [[f32; 4]; 3],
    intr: [f32; 4],
    size: [f32; 4],
    lims: [f32; 4],
    clip: [f32; 4],
    count: [u32; 4],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct SortParams {
    n: u32,
    chunks: u32,
    chunk_size: u32,
    shift: u32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ScanParams {
    len: u32,
    blocks: u32,
    pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct BinParams {
    visible: u32,
    chunks: u32,
    chunk_size: u32,
    tiles_x: u32,
    tiles_y: u32,
    num_tiles: u32,
    /// `sum_lines`: 0 along x, 1 along y.
    axis: u32,
    /// Trips of the scatter's loop check (2).
    canary: u32,
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct BlendParams {
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    alpha_min: f32,
    alpha_max: f32,
    t_min: f32,
    n: u32,
    canary: u32,
    /// This dispatch's window of each tile's list: list positions [win_lo, win_hi).
    win_lo: u32,
    win_hi: u32,
    /// FIRST_WINDOW | LAST_WINDOW bits (blend.wgsl).
    window: u32,
}

/// `BlendParams::window` bits: the first window walked (fresh state) and the last (final
/// outputs); see blend.wgsl.
const FIRST_WINDOW: u32 = 1;
const LAST_WINDOW: u32 = 2;
/// The smallest compositing window the automatic choice halves down to before giving up.
const MIN_WINDOW: u32 = 256;

/// Compiled kernels.
struct Kernels {
    project: wgpu::ComputePipeline,
    project_backward: wgpu::ComputePipeline,
    depth_keys: wgpu::ComputePipeline,
    radix_count: wgpu::ComputePipeline,
    radix_scatter: wgpu::ComputePipeline,
    scan_blocks: wgpu::ComputePipeline,
    scan_sums: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
    count_corners: wgpu::ComputePipeline,
    sum_lines: wgpu::ComputePipeline,
    tile_ranges: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
    scatter_chunks: wgpu::ComputePipeline,
    /// Compositing kernels by (channel count, column halves, forward), each built on first use
    /// (lavapipe compiles for seconds, and a scene may use halves in one direction only).
    blend: HashMap<(usize, bool, bool), wgpu::ComputePipeline>,
}

fn module(dev: &wgpu::Device, label: &str, src: &str) -> wgpu::ShaderModule {
    dev.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(src.into()),
    })
}

fn pipeline(dev: &wgpu::Device, m: &wgpu::ShaderModule, entry: &str) -> wgpu::ComputePipeline {
    dev.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: None,
        module: m,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

impl Kernels {
    fn new(dev: &wgpu::Device) -> Self {
        let project = module(dev, "project", PROJECT_WGSL);
        let sort = module(dev, "sort", SORT_WGSL);
        let scan = module(dev, "scan", SCAN_WGSL);
        let bin = module(dev, "bin", &format!("{BIN_WGSL}\n{LOOP_CHECK_WGSL}"));
        Kernels {
            project: pipeline(dev, &project, "project_forward"),
            project_backward: pipeline(dev, &project, "project_backward"),
            depth_keys: pipeline(dev, &sort, "depth_keys"),
            radix_count: pipeline(dev, &sort, "radix_count"),
            radix_scatter: pipeline(dev, &sort, "radix_scatter"),
            scan_blocks: pipeline(dev, &scan, "scan_blocks"),
            scan_sums: pipeline(dev, &scan, "scan_sums"),
            scan_add: pipeline(dev, &scan, "scan_add"),
            count_corners: pipeline(dev, &bin, "count_corners"),
            sum_lines: pipeline(dev, &bin, "sum_lines"),
            tile_ranges: pipeline(dev, &bin, "tile_ranges"),
            scatter: pipeline(dev, &bin, "scatter"),
            scatter_chunks: pipeline(dev, &bin, "scatter_chunks"),
            blend: HashMap::new(),
        }
    }

    /// The forward (else backward) compositing pipeline for `channels` feature channels, the
    /// row blocks split into column halves or not.
    fn blend(
        &mut self,
        dev: &wgpu::Device,
        layout: BlendLayout,
        channels: usize,
        halves: bool,
        forward: bool,
    ) -> wgpu::ComputePipeline {
        let key = (channels, halves, forward);
        self.blend
            .entry(key)
            .or_insert_with(|| {
                let m = module(dev, "blend", &layout.shader(channels, halves));
                let rows = layout.block_rows > 0;
                let entry = match (forward, rows, rows && layout.partials) {
                    (true, true, _) => "blend_forward_rows",
                    (true, false, _) => "blend_forward",
                    (false, _, true) => "blend_backward_rows",
                    (false, _, false) => "blend_backward",
                };
                pipeline(dev, &m, entry)
            })
            .clone()
    }
}

/// How the compositing kernels map a 16x16 tile onto invocations. GPUs run one pixel per
/// invocation and sum gradients with workgroup float atomics; CPU adapters (lavapipe) execute
/// invocations as SIMD lanes and pay a per-lane loop for every workgroup-memory or storage
/// read and atomic, so there each invocation composites many pixels (splat reads amortised)
/// and writes per-invocation gradient partials that are summed in a fixed order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlendLayout {
    /// Pixels composited by one invocation (a power of two dividing 256).
    pub pixels_per_invocation: u32,
    /// Backward reduction through per-invocation partials instead of compare-and-swap float
    /// adds in workgroup memory.
    pub partials: bool,
    /// Row-block kernels (CPU adapters): the tile is split into blocks of this many rows (a
    /// power of two, 16 = the whole tile, `pixels_per_invocation * block_rows >= 16`) and
    /// each block walks only the splats whose alpha-support ellipse reaches the block; the forward
    /// stops a lane once its pixels in the block are done. 0: the plain kernels, where every
    /// splat of the tile's list visits every pixel (GPUs branch around the ones outside the
    /// box; llvmpipe runs both sides of a divergent branch, so there only loop trips skip).
    /// The backward uses row blocks with `partials` only.
    pub block_rows: u32,
    /// Row-block backward only: sum each visited splat's gradients over the workgroup with
    /// subgroup additions instead of per-invocation partials in workgroup memory (on
    /// llvmpipe every workgroup-memory access is a per-lane loop, a subgroup sum stays in
    /// registers). Needs a device with subgroup operations whose subgroups hold a whole
    /// workgroup (`256 / pixels_per_invocation` invocations).
    pub subgroup_sums: bool,
    /// Row-block kernels with 32 pixels per invocation only: when to split each block of rows
    /// into the tile's left and right halves (8 pixels wide, one SIMD lane group each).
    pub column_halves: ColumnHalves,
    /// Backward: add each splat's gradients into the global sums with `f32` atomic adds
    /// instead of compare-and-swap loops. Needs a device with float atomics
    /// ([`GpuDevice::float_atomics`]). On lavapipe a compare-and-swap loop costs an atomic
    /// load and an exchange, each a per-lane loop; the add is one.
    pub float_atomics: bool,
}

/// When the row-block kernels split each block of rows into the tile's two halves. A batch of
/// splats is then composited either half by half, each half visiting only the splats whose
/// support reaches it, or by the whole tile (the kernel estimates which costs less, per batch).
/// On llvmpipe that pays in the backward for small splats and costs with large ones, where
/// every visit reloads the splat for little skipped work; the forward was slower with halves
/// at every splat size measured.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ColumnHalves {
    /// Blocks span the tile's width.
    Never,
    /// Blocks are halves, forward and backward.
    Always,
    /// Halves in the backward of scenes with fewer tile intersections per visible splat than
    /// this (small splats); blocks of the tile's width elsewhere.
    BackwardBelowTilesPerSplat(u32),
}

impl ColumnHalves {
    /// Whether the forward (`backward` false) or the backward of a scene of `visible` splats
    /// with `intersections` tile intersections uses halves.
    pub fn applies(self, backward: bool, intersections: u64, visible: u64) -> bool {
        match self {
            ColumnHalves::Never => false,
            ColumnHalves::Always => true,
            ColumnHalves::BackwardBelowTilesPerSplat(t) => {
                backward && intersections < u64::from(t) * visible
            }
        }
    }
}

impl BlendLayout {
    /// The layout for an adapter of kind `kind` (see [`crate::AdapterSummary::kind`]).
    pub fn for_adapter(kind: &str) -> Self {
        if kind == "cpu" {
            // Measured on lavapipe (256-bit llvmpipe; cpu_vs_wgpu example): at 10k splats
            // 400x400, 16-32 pixels per invocation composite 5-6x faster forward and ~10x
            // faster backward than one pixel, 64 falls off again; at 100k 800x800, 32 beats 16
            // by 15-30% (one 8-lane SIMD group per tile). The row-block kernels with the whole
            // tile as one block then cut compositing 3.3x forward and 1.9x backward (only the
            // splats whose alpha box reaches the tile, each lane stopping when its pixels are
            // done); blocks of 8, 4 or 2 rows were slower (1.40, ~1.9 and ~2.6 s forward
            // against 1.12 s): each block visit reloads the splat, per lane, on llvmpipe.
            // Testing the support ellipse against the tile instead of its bounding box cut
            // compositing by a further 17-30 % (forward 337 -> 241 ms, backward 595 -> 414 ms
            // with small splats). Blocks smaller than the tile lose to the splat reloads of
            // their visits, except in the backward of small splats with column halves and a
            // per-batch choice between halves and the whole tile (see SMALL_SPLAT_TILES).
            BlendLayout {
                pixels_per_invocation: 32,
                partials: true,
                block_rows: 16,
                subgroup_sums: false,
                column_halves: ColumnHalves::BackwardBelowTilesPerSplat(SMALL_SPLAT_TILES),
                float_atomics: false,
            }
        } else {
            BlendLayout {
                pixels_per_invocation: 1,
                partials: false,
                block_rows: 0,
                subgroup_sums: false,
                column_halves: ColumnHalves::Never,
                float_atomics: false,
            }
        }
    }

    /// The layout for `gpu`: [`BlendLayout::for_adapter`], with subgroup sums where the device
    /// has them (lavapipe: backward compositing 3.1 s -> 1.2-1.7 s on the cpu_vs_wgpu scene).
    pub fn for_device(gpu: &GpuDevice) -> Self {
        let mut layout = Self::for_adapter(gpu.adapter.kind);
        layout.subgroup_sums = layout.can_sum_by_subgroups(gpu);
        layout.float_atomics = gpu.float_atomics;
        layout
    }

    /// Whether this layout may sum the backward's gradients by subgroup operations on `gpu`
    /// (`subgroup_sums`): row-block kernels with partials, on a device whose subgroups hold
    /// one workgroup.
    pub fn can_sum_by_subgroups(&self, gpu: &GpuDevice) -> bool {
        self.block_rows > 0 && self.partials && self.subgroups_fit(gpu)
    }

    /// Whether `gpu`'s subgroups hold one workgroup of this layout.
    fn subgroups_fit(&self, gpu: &GpuDevice) -> bool {
        gpu.subgroup_min_size
            .is_some_and(|m| m >= 256 / self.pixels_per_invocation)
    }

    /// The compositing shader for `channels` channels: template values substituted and the
    /// per-pixel loops (marked `// unroll: pixels`) unrolled, so that every per-pixel array
    /// index is a constant and the arrays live in registers.
    fn shader(&self, channels: usize, halves: bool) -> String {
        let p = self.pixels_per_invocation as usize;
        let stride = channels + 7;
        let invocations = 256 / p;
        let rows = self.block_rows.max(1);
        let halves = if halves { 2 } else { 1 };
        let blocks = halves * 16 / rows as usize;
        // Workgroup memory: 16 KiB guaranteed; the accumulators get up to ~12 KiB.
        let (batch, acc, partial) = if self.subgroup_sums {
            (32, 1, 1)
        } else if self.partials && self.block_rows > 0 {
            // Row blocks: at most 32 splats (one bit each in the block masks).
            let batch = (3072 / (stride * invocations)).clamp(1, 32);
            (batch, 1, batch * stride * invocations)
        } else if self.partials {
            let batch = (3072 / (stride * invocations)).clamp(1, 64);
            (batch, 1, batch * stride * invocations)
        } else {
            let batch = (2048 / stride).clamp(4, 64);
            (batch, batch * stride, 1)
        };
        let mut src = format!("{BLEND_WGSL}\n{LOOP_CHECK_WGSL}");
        if self.block_rows == 0 {
            strip_sections(&mut src, "rows");
        }
        // Subgroup built-ins only compile on devices with the feature: one of the two sections
        // defining the workgroup sums stays.
        strip_sections(
            &mut src,
            if self.subgroup_sums {
                "no-subgroups"
            } else {
                "subgroups"
            },
        );
        strip_sections(
            &mut src,
            if self.float_atomics {
                "no-float-atomics"
            } else {
                "float-atomics"
            },
        );
        let src = src
            .replace(
                "{{GRAD_ATOMIC}}",
                if self.float_atomics { "f32" } else { "u32" },
            )
            .replace(
                "{{SUBGROUP_SUMS}}",
                if self.subgroup_sums { "true" } else { "false" },
            )
            .replace("{{ROWS}}", &rows.to_string())
            .replace("{{HALVES}}", &halves.to_string())
            .replace("{{WALKS}}", &(blocks + usize::from(blocks > 1)).to_string())
            .replace("{{SPANS}}", &stride.div_ceil(invocations).to_string())
            .replace("{{CHANNELS}}", &channels.to_string())
            .replace("{{PIXELS}}", &p.to_string())
            .replace("{{PARTIALS}}", if self.partials { "true" } else { "false" })
            .replace("{{BATCH}}", &batch.to_string())
            .replace("{{ACC}}", &acc.to_string())
            .replace("{{PARTIAL_LEN}}", &partial.to_string());
        let src = unroll_loops(&src, "l", "WG", "lanes", invocations);
        let src = unroll_loops(&src, "c", "C", "channels", channels);
        let src = unroll_loops(&src, "s", "STRIDE", "stride", stride);
        let src = unroll_loops(&src, "h", "SPANS", "spans", stride.div_ceil(invocations));
        let src = unroll_loops(&src, "v", "CV", "feature vectors", channels.div_ceil(4));
        let src = unroll_loops(&src, "w", "NW", "walks", blocks + usize::from(blocks > 1));
        let src = unroll_loops(&src, "b", "NB", "blocks", blocks);
        unroll_loops(&src, "j", "P", "pixels", p)
    }
}

/// Remove every `// <NAME>` ... `// </NAME>` section of `src`.
fn strip_sections(src: &mut String, name: &str) {
    let (open, close) = (format!("// <{name}>\n"), format!("// </{name}>"));
    while let Some(a) = src.find(&open) {
        let b = src[a..].find(&close).expect("blend.wgsl: unclosed section") + a;
        src.replace_range(a..b + close.len(), "");
    }
}

/// Replace every loop `for (var V = 0u; V < N; V++) { // unroll: NAME` ... `}` of `src` by
/// `count` copies of its body, each inside a one-trip loop (so that `continue` keeps its
/// meaning) with `V` a `const` (which subgroup broadcasts need as their lane). Naga and some
/// drivers (llvmpipe) leave such loops rolled; unrolled, every per-pixel and per-channel array
/// index is a constant and the arrays live in registers instead of scratch memory.
fn unroll_loops(src: &str, var: &str, bound: &str, name: &str, count: usize) -> String {
    let head = format!("for (var {var} = 0u; {var} < {bound}; {var}++) {{ // unroll: {name}");
    let mut out = String::with_capacity(src.len() * 2);
    let mut rest = src;
    while let Some(at) = rest.find(&head) {
        out.push_str(&rest[..at]);
        let body_start = at + head.len();
        let open = at + head.rfind('{').expect("the head opens the loop body");
        let end =
            closing_brace(rest, open).expect("blend.wgsl: unbalanced braces in an unrolled loop");
        let body = &rest[body_start..end];
        // A body that jumps (`continue`) stays a loop of one trip; any other is a plain block,
        // which matters on llvmpipe: it caps every shader at 65,535 loop iterations in all
        // (loops end early beyond), and values written in a block need no loop masks.
        let jumps = jumps_out(body);
        for k in 0..count {
            if jumps {
                out.push_str(&format!(
                    "for (var once_{var} = 0u; once_{var} < 1u; once_{var}++) {{ const {var} = {k}u;{body}}}\n"
                ));
            } else {
                out.push_str(&format!("{{ const {var} = {k}u;{body}}}\n"));
            }
        }
        rest = &rest[end + 1..];
    }
    out.push_str(rest);
    out
}

/// Whether a loop body holds a `continue` or `break` of its own loop: one outside the loops
/// nested in it (`loop`, `for`, `while` statements, skipped with their bodies).
fn jumps_out(body: &str) -> bool {
    let code: Vec<&str> = body
        .lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect();
    let code = code.join("\n");
    let mut rest = code.as_str();
    loop {
        let nested = ["loop {", "for (", "while "]
            .iter()
            .filter_map(|k| rest.find(k))
            .min();
        let scan_to = nested.unwrap_or(rest.len());
        if rest[..scan_to].contains("continue") || rest[..scan_to].contains("break") {
            return true;
        }
        let Some(at) = nested else { return false };
        // Skip the nested statement: up to its opening brace, then past the matching one.
        let Some(open) = rest[at..].find('{') else {
            return false;
        };
        rest = match closing_brace(rest, at + open) {
            Some(close) => &rest[close + 1..],
            None => "",
        };
    }
}

/// The byte index of the `}` that closes the `{` at byte `open` of `src` (None when unbalanced).
fn closing_brace(src: &str, open: usize) -> Option<usize> {
    let mut depth = 0usize;
    for (i, ch) in src[open..].char_indices() {
        match ch {
            '{' => depth += 1,
            '}' => {
                depth -= 1;
                if depth == 0 {
                    return Some(open + i);
                }
            }
            _ => {}
        }
    }
    None
}

/// Grow-only named storage buffers, reused across calls.
#[derive(Default)]
struct Pool {
    buffers: HashMap<&'static str, wgpu::Buffer>,
}

const STORAGE: wgpu::BufferUsages = wgpu::BufferUsages::STORAGE
    .union(wgpu::BufferUsages::COPY_DST)
    .union(wgpu::BufferUsages::COPY_SRC);

impl Pool {
    /// A buffer of at least `bytes` bytes (and at least 16) under `name`.
    fn get(
        &mut self,
        dev: &wgpu::Device,
        name: &'static str,
        bytes: u64,
        usage: wgpu::BufferUsages,
    ) -> wgpu::Buffer {
        let bytes = bytes.max(16).next_multiple_of(16);
        if let Some(b) = self.buffers.get(name) {
            if b.size() >= bytes {
                return b.clone();
            }
        }
        let b = dev.create_buffer(&wgpu::BufferDescriptor {
            label: Some(name),
            size: bytes.next_power_of_two().max(bytes),
            usage,
            mapped_at_creation: false,
        });
        self.buffers.insert(name, b.clone());
        b
    }
}

/// What a forward rasterization leaves on the device for its backward (tile lists, depth
/// order, per-pixel last contributor and final transmittance, the splats and features), like
/// sync4d-raster's `RasterState`. Reuse one per concurrent render; buffers grow as needed.
#[derive(Default)]
pub struct GpuRasterState {
    pool: Pool,
    forward: Option<Forward>,
}

/// The last forward: its sizes, the device buffers the backward reads and how deep it composited.
struct Forward {
    shape: ForwardShape,
    buffers: ForwardBuffers,
    /// The deepest list position any pixel composited (what the backward walks).
    deepest: u32,
}

/// The device buffers both compositing kernels read.
struct ForwardBuffers {
    splats: wgpu::Buffer,
    ids: wgpu::Buffer,
    tile_offsets: wgpu::Buffer,
    features: wgpu::Buffer,
    pixel_state: wgpu::Buffer,
}

impl ForwardBuffers {
    /// Their bindings (blend.wgsl 1, 3-5 and 7).
    fn bindings(&self) -> [(u32, &wgpu::Buffer); 5] {
        [
            (1, &self.splats),
            (3, &self.ids),
            (4, &self.tile_offsets),
            (5, &self.features),
            (7, &self.pixel_state),
        ]
    }
}

/// One compositing run: the kernel (forward or backward), the frame's shape, the longest tile
/// list, the counters buffer (also among `bindings`), the bind group entries besides the
/// parameters, and the buffers (with byte counts) to zero before each attempt.
#[derive(Clone, Copy)]
struct CompositePass<'a> {
    pipe: &'a wgpu::ComputePipeline,
    shape: &'a ForwardShape,
    longest: u32,
    forward: bool,
    counters: &'a wgpu::Buffer,
    bindings: &'a [(u32, &'a wgpu::Buffer)],
    clear: &'a [(&'a wgpu::Buffer, u64)],
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct ForwardShape {
    n: usize,
    channels: usize,
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    alpha_max: f32,
    /// Tile intersections and visible splats (which kernels suit the scene: [`ColumnHalves`]).
    intersections: u64,
    visible: u64,
}

impl ForwardShape {
    /// The compositing kernels' parameters for window `w` of `windows` (blend.wgsl
    /// `BlendParams`): list positions [w * size, (w + 1) * size), the last one open-ended;
    /// `forward` walks them in increasing order, the backward in decreasing.
    fn blend_params(&self, w: u32, windows: u32, size: u32, forward: bool) -> BlendParams {
        let (first, last) = if forward {
            (w == 0, w + 1 == windows)
        } else {
            (w + 1 == windows, w == 0)
        };
        BlendParams {
            width: self.width,
            height: self.height,
            tiles_x: self.tiles_x,
            tiles_y: self.tiles_y,
            alpha_min: ALPHA_MIN,
            alpha_max: self.alpha_max,
            t_min: T_MIN,
            n: self.n as u32,
            canary: 2,
            win_lo: w * size,
            win_hi: if w + 1 == windows {
                u32::MAX
            } else {
                (w + 1) * size
            },
            window: (u32::from(first) * FIRST_WINDOW) | (u32::from(last) * LAST_WINDOW),
        }
    }
}

impl GpuRasterState {
    /// A fresh state with no buffers.
    pub fn new() -> Self {
        Self::default()
    }
}

/// The rasterizer on one wgpu device. Not `Sync`: use one per thread (or a lock).
pub struct GpuRasterizer {
    gpu: GpuDevice,
    kernels: Kernels,
    pool: Pool,
    /// Per-stage wall times when profiling is on (see [`GpuRasterizer::set_profiling`]).
    profile: Option<Profile>,
    layout: BlendLayout,
    /// On a CPU adapter, the threads its driver runs (lavapipe: one per CPU), which size the
    /// binning chunks; None on GPUs.
    cpu_threads: Option<u32>,
    /// Tile-list entries composited per dispatch (forward, backward); see
    /// [`GpuRasterizer::set_compositing_window`].
    windows: CompositingWindows,
}

/// How many tile-list entries one compositing dispatch walks: long lists are composited over
/// several dispatches, the per-pixel state kept on the device in between.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CompositingWindow {
    /// The default: one dispatch on GPUs; on CPU adapters (lavapipe, whose driver ends a
    /// shader's loops after 65,535 trips) a measured size, halved whenever the kernels' loop
    /// guard reports cut loops, until it passes or reaches 256 entries (then an error).
    Auto,
    /// Start at this many entries, halved like `Auto`.
    Start(u32),
    /// Exactly this many entries; cut loops are an error.
    Fixed(u32),
}

/// The compositing windows in use. lavapipe ends a shader's loops
/// after 65,535 trips in all (a guard in every kernel detects it), so long tile lists are
/// composited over several dispatches, the per-pixel state kept on the device in between.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct CompositingWindows {
    forward: u32,
    backward: u32,
    /// Halve a window and composite again when the guard reports cut loops (else an error).
    adaptive: bool,
}

impl CompositingWindows {
    /// The starting windows for `layout`: the row-block kernels of CPU adapters spend a few
    /// loop trips per entry (measured on lavapipe: forward ~1.2, backward ~5), others are
    /// walked in one dispatch; halved automatically when that proves too long. (A 70,000-entry
    /// list of one-pixel splats on lavapipe: forward passes at 35,000, backward at 17,500.)
    fn for_layout(layout: BlendLayout) -> Self {
        let (forward, backward) = if layout.block_rows > 0 {
            (32_768, 12_288)
        } else {
            (u32::MAX, u32::MAX)
        };
        CompositingWindows {
            forward,
            backward,
            adaptive: true,
        }
    }
}

/// Stage timings of the calls made while profiling: (stage name, seconds), in call order.
#[derive(Debug, Default)]
struct Profile {
    since: Option<std::time::Instant>,
    stages: Vec<(&'static str, f64)>,
}

/// Workgroup grid for `groups` workgroups of a 1D kernel (2D when beyond the per-dimension
/// limit; the kernels flatten the id).
fn grid(groups: u32) -> (u32, u32) {
    let x = groups.clamp(1, 65_535);
    (x, groups.div_ceil(x).max(1))
}

/// Tiles of `tiles` that [m - r, m + r] (pixels) reaches: ceil((m + r) / 16) - floor((m - r) /
/// 16), both clamped to [0, tiles], in f32 as bin.wgsl's tile_rect.
fn tile_span(m: f32, r: i32, tiles: u32) -> u32 {
    let (m, r, t) = (
        m / TILE_SIZE as f32,
        r as f32 / TILE_SIZE as f32,
        tiles as f32,
    );
    let lo = (m - r).floor().clamp(0.0, t);
    let hi = (m + r).ceil().clamp(0.0, t);
    // NaN means (rejected by validation) count as the whole grid.
    if hi >= lo {
        (hi - lo) as u32
    } else {
        tiles
    }
}

/// Entries per chunk of the chunk-serial kernels (radix sort, tile scatter) for `count`
/// entries, each costing up to `trips` loop trips of one invocation: up to MAX_CHUNKS chunks
/// on GPUs (`cpu_threads` None); on a CPU adapter running `cpu_threads` threads,
/// CPU_CHUNKS_PER_THREAD per thread (smaller count tables to scan) while a chunk stays within
/// CHUNK_TRIPS trips. At least MIN_CHUNK.
fn chunk_size(count: u32, trips: u32, cpu_threads: Option<u32>) -> u32 {
    let gpu_size = count.div_ceil(MAX_CHUNKS);
    let size = match cpu_threads {
        Some(threads) => {
            let cpu_size = count.div_ceil(CPU_CHUNKS_PER_THREAD.saturating_mul(threads).max(1));
            cpu_size.min(CHUNK_TRIPS / trips.max(1)).max(gpu_size)
        }
        None => gpu_size,
    };
    size.max(MIN_CHUNK)
}

/// An error when a kernel set its loop check flag (`counters[4]` compositing, `counters[7]`
/// the tile scatter; see loop_check.wgsl): the driver cut its loops short even
/// with the smallest compositing window tried, so the results are incomplete.
fn loops_completed(counters: &[u32], gpu: &GpuDevice) -> Result<()> {
    let what = if counters[7] != 0 {
        "the tile scatter's"
    } else if counters[4] != 0 {
        "the compositing kernels'"
    } else {
        return Ok(());
    };
    Err(GpuError::TooLarge(format!(
        "the adapter ({}) cut {what} loops short (lavapipe ends a shader's loops after 65,535 \
         trips), even composited in windows, so this scene is too large for it; render fewer \
         Gaussians or a smaller image, or use the CPU backend",
        gpu.adapter
    )))
}

fn check_binding(gpu: &GpuDevice, what: &str, bytes: u64) -> Result<()> {
    let max = gpu
        .limits
        .max_storage_buffer_binding_size
        .min(gpu.limits.max_buffer_size);
    if bytes > max {
        return Err(GpuError::TooLarge(format!(
            "{what} needs {bytes} bytes but the adapter ({}) binds at most {max}; render fewer \
             Gaussians or a smaller image, or use the CPU backend",
            gpu.adapter
        )));
    }
    Ok(())
}

/// A storage buffer of `bytes` from `pool`, after checking the device's limits.
fn storage_in(
    gpu: &GpuDevice,
    pool: &mut Pool,
    name: &'static str,
    bytes: u64,
) -> Result<wgpu::Buffer> {
    check_binding(gpu, name, bytes)?;
    Ok(pool.get(&gpu.device, name, bytes, STORAGE))
}

/// `data` in a storage buffer from `pool`.
fn upload_in<T: bytemuck::Pod>(
    gpu: &GpuDevice,
    pool: &mut Pool,
    name: &'static str,
    data: &[T],
) -> Result<wgpu::Buffer> {
    let bytes = std::mem::size_of_val(data) as u64;
    let buf = storage_in(gpu, pool, name, bytes)?;
    if bytes > 0 {
        gpu.queue.write_buffer(&buf, 0, bytemuck::cast_slice(data));
    }
    Ok(buf)
}

impl GpuRasterizer {
    /// Compile the kernels on `gpu`.
    pub fn new(gpu: GpuDevice) -> Self {
        let kernels = Kernels::new(&gpu.device);
        let layout = BlendLayout::for_device(&gpu);
        let cpu_threads = (gpu.adapter.kind == "cpu")
            .then(|| std::thread::available_parallelism().map_or(1, |t| t.get()) as u32);
        GpuRasterizer {
            gpu,
            kernels,
            pool: Pool::default(),
            profile: None,
            layout,
            cpu_threads,
            windows: CompositingWindows::for_layout(layout),
        }
    }

    /// How many tile-list entries one compositing dispatch walks (see [`CompositingWindow`]);
    /// results do not depend on it beyond float rounding.
    pub fn set_compositing_window(&mut self, window: CompositingWindow) -> Result<()> {
        let fixed = |entries: u32, adaptive: bool| {
            if entries == 0 {
                return Err(RasterError::invalid("window", "must be at least 1 entry"));
            }
            Ok(CompositingWindows {
                forward: entries,
                backward: entries,
                adaptive,
            })
        };
        self.windows = match window {
            CompositingWindow::Auto => CompositingWindows::for_layout(self.layout),
            CompositingWindow::Start(n) => fixed(n, true)?,
            CompositingWindow::Fixed(n) => fixed(n, false)?,
        };
        Ok(())
    }

    /// After a compositing attempt with the counters `cnt`: when the kernels' loops were cut
    /// and windows are automatic, halve the (forward or backward) window for lists of at most
    /// `longest` entries and return true (composite again); else false.
    fn shrink_window(&mut self, cnt: &[u32], longest: u32, forward: bool) -> bool {
        if cnt[4] == 0 || !self.windows.adaptive {
            return false;
        }
        let w = if forward {
            &mut self.windows.forward
        } else {
            &mut self.windows.backward
        };
        let current = (*w).min(longest);
        if current <= MIN_WINDOW {
            return false;
        }
        *w = (current / 2).max(MIN_WINDOW);
        true
    }

    /// Run `pass`'s compositing kernel (appended to `enc`) over every tile, in windows of the
    /// current size over lists of at most `pass.longest` entries (forward in increasing list
    /// order, backward decreasing); when the kernels' loop guard reports a cut and windows are
    /// automatic, zero the `clear` buffers and run again with a halved window. Returns the
    /// compositing counters.
    fn composite(
        &mut self,
        mut enc: wgpu::CommandEncoder,
        pass: &CompositePass<'_>,
    ) -> Result<Vec<u32>> {
        let CompositePass {
            pipe,
            shape,
            longest,
            forward,
            counters,
            bindings,
            clear,
        } = *pass;
        loop {
            for (buf, bytes) in clear {
                enc.clear_buffer(buf, 0, Some(*bytes));
            }
            let size = if forward {
                self.windows.forward
            } else {
                self.windows.backward
            };
            let windows = longest.div_ceil(size).max(1);
            for i in 0..windows {
                let w = if forward { i } else { windows - 1 - i };
                let params = self.uniform(&shape.blend_params(w, windows, size, forward));
                let mut all = vec![(0, &params)];
                all.extend_from_slice(bindings);
                let g = self.bind(pipe, &all);
                Self::dispatch(&mut enc, pipe, &g, (shape.tiles_x, shape.tiles_y));
            }
            self.mark(
                &mut enc,
                if forward {
                    "blend forward"
                } else {
                    "blend backward"
                },
            );
            self.gpu.queue.submit([enc.finish()]);
            let cnt: Vec<u32> = bytemuck::pod_collect_to_vec(&self.read(counters, COUNTERS_BYTES)?);
            if !self.shrink_window(&cnt, longest, forward) {
                return Ok(cnt);
            }
            enc = self.gpu.device.create_command_encoder(&Default::default());
        }
    }

    /// The compositing layout in use (chosen from the adapter kind).
    pub fn blend_layout(&self) -> BlendLayout {
        self.layout
    }

    /// Use another compositing layout (tests run both on any adapter); results agree to
    /// float rounding.
    pub fn set_blend_layout(&mut self, layout: BlendLayout) -> Result<()> {
        let p = layout.pixels_per_invocation;
        if !(p.is_power_of_two() && p <= 256) {
            return Err(RasterError::invalid(
                "pixels_per_invocation",
                "must be a power of two <= 256",
            )
            .into());
        }
        let r = layout.block_rows;
        if r != 0 && !(r.is_power_of_two() && r <= 16 && p * r >= 16) {
            return Err(RasterError::invalid(
                "block_rows",
                "must be 0 or a power of two <= 16 with pixels_per_invocation * block_rows >= 16",
            )
            .into());
        }
        if layout.column_halves != ColumnHalves::Never && !(r > 0 && p == 32) {
            return Err(RasterError::invalid(
                "column_halves",
                "needs block_rows > 0 and 32 pixels_per_invocation",
            )
            .into());
        }
        if layout.subgroup_sums && !layout.can_sum_by_subgroups(&self.gpu) {
            return Err(RasterError::invalid(
                "subgroup_sums",
                "needs block_rows > 0, partials, and a device whose subgroups hold 256 / \
                 pixels_per_invocation invocations",
            )
            .into());
        }
        if layout.float_atomics && !self.gpu.float_atomics {
            return Err(RasterError::invalid(
                "float_atomics",
                "needs a device with f32 atomic adds (wgpu's SHADER_FLOAT32_ATOMIC)",
            )
            .into());
        }
        if layout != self.layout {
            self.layout = layout;
            self.kernels.blend.clear();
            if self.windows.adaptive {
                self.windows = CompositingWindows::for_layout(layout);
            }
        }
        Ok(())
    }

    /// Time every stage of the following calls (projection, depth sort, binning, scatter,
    /// compositing, ...): each stage is submitted on its own and waited for, which costs some
    /// overlap, so use it to find where time goes, not to measure the total.
    pub fn set_profiling(&mut self, on: bool) {
        self.profile = on.then(Profile::default);
    }

    /// The (stage, seconds) timings recorded since the last call, in order; empty when
    /// profiling is off.
    pub fn take_profile(&mut self) -> Vec<(&'static str, f64)> {
        self.profile
            .as_mut()
            .map(|p| std::mem::take(&mut p.stages))
            .unwrap_or_default()
    }

    /// When profiling: submit `enc`, wait for the device and book the time since the previous
    /// mark to `stage`; `enc` continues as a fresh encoder.
    fn mark(&mut self, enc: &mut wgpu::CommandEncoder, stage: &'static str) {
        let Some(p) = self.profile.as_mut() else {
            return;
        };
        let done = std::mem::replace(
            enc,
            self.gpu.device.create_command_encoder(&Default::default()),
        );
        self.gpu.queue.submit([done.finish()]);
        let _ = self.gpu.device.poll(wgpu::PollType::wait_indefinitely());
        let now = std::time::Instant::now();
        if let Some(t0) = p.since {
            p.stages.push((stage, (now - t0).as_secs_f64()));
        }
        p.since = Some(now);
    }

    /// When profiling: book host-side work since the previous mark to `stage`.
    fn mark_host(&mut self, stage: &'static str) {
        if let Some(p) = self.profile.as_mut() {
            let now = std::time::Instant::now();
            if let Some(t0) = p.since {
                p.stages.push((stage, (now - t0).as_secs_f64()));
            }
            p.since = Some(now);
        }
    }

    /// The device this rasterizer runs on.
    pub fn device(&self) -> &GpuDevice {
        &self.gpu
    }

    fn upload<T: bytemuck::Pod>(&mut self, name: &'static str, data: &[T]) -> Result<wgpu::Buffer> {
        upload_in(&self.gpu, &mut self.pool, name, data)
    }

    fn storage(&mut self, name: &'static str, bytes: u64) -> Result<wgpu::Buffer> {
        storage_in(&self.gpu, &mut self.pool, name, bytes)
    }

    fn uniform<T: bytemuck::Pod>(&self, value: &T) -> wgpu::Buffer {
        self.gpu
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("params"),
                contents: bytemuck::bytes_of(value),
                usage: wgpu::BufferUsages::UNIFORM,
            })
    }

    fn bind(
        &self,
        pipe: &wgpu::ComputePipeline,
        buffers: &[(u32, &wgpu::Buffer)],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry> = buffers
            .iter()
            .map(|(b, buf)| wgpu::BindGroupEntry {
                binding: *b,
                resource: buf.as_entire_binding(),
            })
            .collect();
        self.gpu
            .device
            .create_bind_group(&wgpu::BindGroupDescriptor {
                label: None,
                layout: &pipe.get_bind_group_layout(0),
                entries: &entries,
            })
    }

    /// Copy the first `bytes` of `src` to the host.
    fn read(&mut self, src: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>> {
        if bytes == 0 {
            return Ok(Vec::new());
        }
        let staging = self.pool.get(
            &self.gpu.device,
            "staging",
            bytes,
            wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        );
        let mut enc = self.gpu.device.create_command_encoder(&Default::default());
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, bytes);
        self.gpu.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, ..bytes, move |r| {
            let _ = tx.send(r);
        });
        self.gpu
            .device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv()
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let data = staging
            .get_mapped_range(..bytes)
            .map_err(|e| GpuError::Readback(e.to_string()))?
            .to_vec();
        staging.unmap();
        Ok(data)
    }

    fn read_f32(&mut self, src: &wgpu::Buffer, count: usize) -> Result<Vec<f32>> {
        Ok(bytemuck::pod_collect_to_vec(
            &self.read(src, count as u64 * 4)?,
        ))
    }

    fn dispatch(
        enc: &mut wgpu::CommandEncoder,
        pipe: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
        groups: (u32, u32),
    ) {
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipe);
        pass.set_bind_group(0, group, &[]);
        pass.dispatch_workgroups(groups.0, groups.1, 1);
    }

    /// Upload the Gaussians and the projection parameters.
    fn gaussians_in(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
    ) -> Result<[wgpu::Buffer; 5]> {
        let n = gaussians.len();
        if n > (1 << 27) {
            return Err(
                RasterError::invalid("means", "too many Gaussians for the GPU path").into(),
            );
        }
        Ok([
            self.uniform(&project_params(camera, settings, n as u32)),
            self.upload("means", gaussians.means)?,
            self.upload("quats", gaussians.quats)?,
            self.upload("scales", gaussians.scales)?,
            self.upload("opacities", gaussians.opacities)?,
        ])
    }

    /// Project every Gaussian through `camera` (as [`sync4d_raster::project_forward`]);
    /// returns the number of visible Gaussians. Computed in f32 on the device, so outputs
    /// agree with the CPU path (f64 inside) to f32 rounding, and radii to +-1 pixel.
    pub fn project_forward(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
        out: ProjectionMut<'_, f32>,
    ) -> Result<usize> {
        gaussians.validate()?;
        camera.validate()?;
        settings.validate()?;
        let n = gaussians.len();
        out.check_len(n)?;
        if n == 0 {
            return Ok(0);
        }
        let [params, means, quats, scales, opac] =
            self.gaussians_in(gaussians, camera, settings)?;
        let splats = self.storage("projected", (n * SPLAT_FLOATS * 4) as u64)?;
        let radii = self.storage("projected_radii", (n * 8) as u64)?;
        let group = self.bind(
            &self.kernels.project,
            &[
                (0, &params),
                (1, &means),
                (2, &quats),
                (3, &scales),
                (4, &opac),
                (5, &splats),
                (6, &radii),
            ],
        );
        let mut enc = self.gpu.device.create_command_encoder(&Default::default());
        Self::dispatch(
            &mut enc,
            &self.kernels.project,
            &group,
            grid((n as u32).div_ceil(WG)),
        );
        self.gpu.queue.submit([enc.finish()]);
        let packed = self.read_f32(&splats, n * SPLAT_FLOATS)?;
        let rad: Vec<i32> = bytemuck::pod_collect_to_vec(&self.read(&radii, (n * 8) as u64)?);
        let mut visible = 0;
        for i in 0..n {
            let s = &packed[SPLAT_FLOATS * i..SPLAT_FLOATS * (i + 1)];
            out.means2d[2 * i] = s[0];
            out.means2d[2 * i + 1] = s[1];
            out.conics[3 * i..3 * i + 3].copy_from_slice(&s[2..5]);
            out.opacities[i] = s[5];
            out.depths[i] = s[6];
            out.radii[2 * i] = rad[2 * i];
            out.radii[2 * i + 1] = rad[2 * i + 1];
            visible += usize::from(rad[2 * i] > 0 && rad[2 * i + 1] > 0);
        }
        Ok(visible)
    }

    /// Backward of [`GpuRasterizer::project_forward`] (as [`sync4d_raster::project_backward`]):
    /// dL/d(means, quats, scales, opacities) from dL/d(projection outputs), in f32.
    pub fn project_backward(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
        v_out: &ProjectionGrads<'_, f32>,
        grads: GaussianGradsMut<'_, f32>,
    ) -> Result<()> {
        gaussians.validate()?;
        camera.validate()?;
        settings.validate()?;
        let n = gaussians.len();
        v_out.validate(n)?;
        grads.check_len(n)?;
        if n == 0 {
            return Ok(());
        }
        let [params, means, quats, scales, opac] =
            self.gaussians_in(gaussians, camera, settings)?;
        let mut v = vec![0.0f32; n * 8];
        for i in 0..n {
            v[8 * i] = v_out.means2d[2 * i];
            v[8 * i + 1] = v_out.means2d[2 * i + 1];
            v[8 * i + 2..8 * i + 5].copy_from_slice(&v_out.conics[3 * i..3 * i + 3]);
            v[8 * i + 5] = v_out.depths[i];
            v[8 * i + 6] = v_out.opacities[i];
        }
        let v_buf = self.upload("v_projected", &v)?;
        let out = self.storage("gaussian_grads", (n * 12 * 4) as u64)?;
        let group = self.bind(
            &self.kernels.project_backward,
            &[
                (0, &params),
                (1, &means),
                (2, &quats),
                (3, &scales),
                (4, &opac),
                (7, &v_buf),
                (8, &out),
            ],
        );
        let mut enc = self.gpu.device.create_command_encoder(&Default::default());
        Self::dispatch(
            &mut enc,
            &self.kernels.project_backward,
            &group,
            grid((n as u32).div_ceil(WG)),
        );
        self.gpu.queue.submit([enc.finish()]);
        let g = self.read_f32(&out, n * 12)?;
        for i in 0..n {
            let r = &g[12 * i..12 * i + 12];
            grads.means[3 * i..3 * i + 3].copy_from_slice(&r[0..3]);
            grads.quats[4 * i..4 * i + 4].copy_from_slice(&r[3..7]);
            grads.scales[3 * i..3 * i + 3].copy_from_slice(&r[7..10]);
            grads.opacities[i] = r[10];
        }
        Ok(())
    }

    /// Composite `splats` into a `width` x `height` image (as
    /// [`sync4d_raster::rasterize_forward`]): features plus `T_final * background`, alpha and
    /// accumulated depth; `state` keeps what the backward needs. Counters: `visible`,
    /// `intersections` and `blended` equal the CPU path's; `evaluated` counts the (live
    /// pixel, splat) pairs the kernel evaluated (the row-block kernels skip the splats whose
    /// support misses a block; the CPU path also skips row halves its support misses, so its
    /// count is lower).
    #[allow(clippy::too_many_arguments)]
    pub fn rasterize_forward(
        &mut self,
        splats: &Splats<'_, f32>,
        width: u32,
        height: u32,
        background: &[f32],
        settings: &BlendSettings,
        state: &mut GpuRasterState,
        out: ImageMut<'_, f32>,
    ) -> Result<Counters> {
        splats.validate(background)?;
        settings.validate()?;
        check_image_size(width, height)?;
        let ch = splats.channels;
        let n = splats.len();
        let npix = (width * height) as usize;
        out.check_len(npix, ch)?;
        if n > (1 << 27) {
            return Err(RasterError::invalid("means2d", "too many splats for the GPU path").into());
        }
        state.forward = None;
        if let Some(p) = self.profile.as_mut() {
            p.since = Some(std::time::Instant::now());
        }
        let dev = self.gpu.device.clone();
        let gpu = &self.gpu;
        let sp = &mut state.pool;

        // Inputs: packed splats, radii, features with the background appended.
        let mut packed = vec![0.0f32; n.max(1) * SPLAT_FLOATS];
        let mut visible = 0u32;
        // The widest and the largest tile rectangle (in tiles), bounding the tile scatter's
        // trips per splat.
        let (tiles_x, tiles_y) = (width.div_ceil(TILE_SIZE), height.div_ceil(TILE_SIZE));
        let (mut widest, mut largest) = (0u32, 0u32);
        for i in 0..n {
            let s = &mut packed[SPLAT_FLOATS * i..SPLAT_FLOATS * (i + 1)];
            s[0] = splats.means2d[2 * i];
            s[1] = splats.means2d[2 * i + 1];
            s[2..5].copy_from_slice(&splats.conics[3 * i..3 * i + 3]);
            s[5] = splats.opacities[i];
            s[6] = splats.depths[i];
            let (rx, ry) = (splats.radii[2 * i], splats.radii[2 * i + 1]);
            if rx > 0 && ry > 0 {
                visible += 1;
                let w = tile_span(s[0], rx, tiles_x);
                widest = widest.max(w);
                largest = largest.max(w * tile_span(s[1], ry, tiles_y));
            }
        }
        let cpu_threads = self.cpu_threads;
        let mut feats = Vec::with_capacity(n * ch + ch);
        feats.extend_from_slice(splats.features);
        feats.extend_from_slice(background);
        let splat_buf = upload_in(gpu, sp, "splats", &packed)?;
        let radii_buf = upload_in(gpu, sp, "radii", if n > 0 { splats.radii } else { &[0, 0] })?;
        let feat_buf = upload_in(gpu, sp, "features", &feats)?;
        let keys = storage_in(gpu, sp, "keys", n.max(1) as u64 * 8)?;
        let keys_tmp = storage_in(gpu, sp, "keys_tmp", n.max(1) as u64 * 8)?;
        let num_tiles = tiles_x * tiles_y;
        let tile_offsets = storage_in(gpu, sp, "tile_offsets", (u64::from(num_tiles) + 1) * 4)?;
        let pixel_state = storage_in(gpu, sp, "pixel_state", npix as u64 * 8)?;

        // 1. Depth order: radix sort of (depth key, index), 8 bits a pass, ping-ponging between
        // `keys_tmp` and `keys` (four passes: the result lands in `keys`).
        let mut enc = dev.create_command_encoder(&Default::default());
        self.mark(&mut enc, "upload");
        let sort_chunk = chunk_size(n as u32, 1, cpu_threads);
        let sort_chunks = (n as u32).div_ceil(sort_chunk).max(1);
        let digit_counts = self.storage("digit_counts", u64::from(256 * sort_chunks) * 4)?;
        let digit_cursors = self.storage("digit_cursors", u64::from(256 * sort_chunks + 1) * 4)?;
        let sort_params = |shift: u32| SortParams {
            n: n as u32,
            chunks: sort_chunks,
            chunk_size: sort_chunk,
            shift,
        };
        let prm = self.uniform(&sort_params(0));
        let g = self.bind(
            &self.kernels.depth_keys,
            &[(0, &prm), (2, &keys), (3, &splat_buf), (4, &radii_buf)],
        );
        Self::dispatch(
            &mut enc,
            &self.kernels.depth_keys,
            &g,
            grid((n as u32).div_ceil(WG)),
        );
        for pass in 0..4u32 {
            let (src, dst) = if pass % 2 == 0 {
                (&keys, &keys_tmp)
            } else {
                (&keys_tmp, &keys)
            };
            let prm = self.uniform(&sort_params(8 * pass));
            let count = &self.kernels.radix_count;
            let g = self.bind(count, &[(0, &prm), (1, src), (5, &digit_counts)]);
            Self::dispatch(&mut enc, count, &g, (sort_chunks.div_ceil(CHUNK_WG), 1));
            self.scan(&mut enc, &digit_counts, &digit_cursors, 256 * sort_chunks)?;
            let scatter = &self.kernels.radix_scatter;
            let g = self.bind(
                scatter,
                &[(0, &prm), (1, src), (2, dst), (6, &digit_cursors)],
            );
            Self::dispatch(&mut enc, scatter, &g, (sort_chunks.div_ceil(CHUNK_WG), 1));
        }
        self.mark(&mut enc, "depth sort");

        // 2. Tile binning: per (tile, chunk) counts, their scan, tile ranges.
        // The tile scatter's invocations take a trip per splat of their chunk plus, per splat,
        // the tiles of its row (`scatter`) or of its whole rectangle (`scatter_chunks`) and one
        // more (an inner loop's last, masked on llvmpipe). CPU adapters use scatter_chunks
        // unless the largest rectangle would make its chunks less than half the size the
        // count tables want, or overrun the trips with the smallest chunks (cpu_vs_wgpu
        // SYNC4D_SCALE=0.1: scatter 38 -> 10 ms).
        let by_chunks = cpu_threads.is_some()
            && MIN_CHUNK * (largest + 2) <= CHUNK_TRIPS
            && 2 * chunk_size(visible, largest + 2, cpu_threads)
                >= chunk_size(visible, 1, cpu_threads);
        let trips = if by_chunks { largest } else { widest } + 2;
        let chunk_size = chunk_size(visible, trips, cpu_threads);
        let chunks = visible.div_ceil(chunk_size).max(1);
        let table = u64::from(num_tiles) * u64::from(chunks);
        if table >= u64::from(u32::MAX) {
            return Err(GpuError::TooLarge(format!(
                "tile table of {table} entries; render a smaller image"
            )));
        }
        let counts = self.storage("counts", table * 4)?;
        let rects = self.storage("rects", u64::from(visible.max(1)) * 8)?;
        let cursors = self.storage("cursors", (table + 1) * 4)?;
        enc.clear_buffer(&counts, 0, Some(table * 4));
        let bin = BinParams {
            visible,
            chunks,
            chunk_size,
            tiles_x,
            tiles_y,
            num_tiles,
            axis: 0,
            canary: 2,
        };
        let bin_params = self.uniform(&bin);
        // Auto layouts hold only the bindings an entry point uses.
        let g = self.bind(
            &self.kernels.count_corners,
            &[
                (0, &bin_params),
                (1, &keys),
                (2, &splat_buf),
                (3, &radii_buf),
                (4, &counts),
                (9, &rects),
            ],
        );
        Self::dispatch(
            &mut enc,
            &self.kernels.count_corners,
            &g,
            grid(visible.div_ceil(WG)),
        );
        for (axis, lines) in [(0, tiles_y), (1, tiles_x)] {
            let prm = self.uniform(&BinParams { axis, ..bin });
            let g = self.bind(&self.kernels.sum_lines, &[(0, &prm), (4, &counts)]);
            let groups = grid((chunks * lines).div_ceil(WG));
            Self::dispatch(&mut enc, &self.kernels.sum_lines, &g, groups);
        }
        self.mark(&mut enc, "tile counts");
        self.scan(&mut enc, &counts, &cursors, table as u32)?;
        self.mark(&mut enc, "tile scan");
        let g = self.bind(
            &self.kernels.tile_ranges,
            &[(0, &bin_params), (5, &cursors), (7, &tile_offsets)],
        );
        Self::dispatch(
            &mut enc,
            &self.kernels.tile_ranges,
            &g,
            grid((num_tiles + 1).div_ceil(WG)),
        );
        self.mark(&mut enc, "tile ranges");
        self.gpu.queue.submit([enc.finish()]);
        let offsets: Vec<u32> = bytemuck::pod_collect_to_vec(
            &self.read(&tile_offsets, (u64::from(num_tiles) + 1) * 4)?,
        );
        let total = offsets[num_tiles as usize];
        let longest = offsets.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);

        self.mark_host("read total");

        // 3. Scatter splat indices into tile lists, then composite.
        let ids = storage_in(&self.gpu, &mut state.pool, "ids", u64::from(total) * 4)?;
        let mut enc = dev.create_command_encoder(&Default::default());
        let counters = self.storage("counters", COUNTERS_BYTES)?;
        enc.clear_buffer(&counters, 0, Some(COUNTERS_BYTES));
        let (scatter, invocations) = if by_chunks {
            (&self.kernels.scatter_chunks, chunks)
        } else {
            (&self.kernels.scatter, chunks * tiles_y)
        };
        let g = self.bind(
            scatter,
            &[
                (0, &bin_params),
                (1, &keys),
                (5, &cursors),
                (6, &ids),
                (8, &counters),
                (9, &rects),
            ],
        );
        Self::dispatch(&mut enc, scatter, &g, grid(invocations.div_ceil(CHUNK_WG)));
        let stage = if by_chunks {
            "scatter by chunks"
        } else {
            "scatter by rows"
        };
        self.mark(&mut enc, stage);
        let image_len = npix * (ch + 2);
        let image = self.storage("image", image_len as u64 * 4)?;
        let shape = ForwardShape {
            n,
            channels: ch,
            width,
            height,
            tiles_x,
            tiles_y,
            alpha_max: settings.alpha_max as f32,
            intersections: u64::from(total),
            visible: u64::from(visible),
        };
        let buffers = ForwardBuffers {
            splats: splat_buf,
            ids,
            tile_offsets,
            features: feat_buf,
            pixel_state,
        };
        let halves = self
            .layout
            .column_halves
            .applies(false, total.into(), visible.into());
        let pipe = self.kernels.blend(&dev, self.layout, ch, halves, true);
        let mut bindings = vec![(6, &image), (8, &counters)];
        bindings.extend(buffers.bindings());
        let clear = [(&counters, COMPOSITING_COUNTERS_BYTES)];
        let pass = CompositePass {
            pipe: &pipe,
            shape: &shape,
            longest,
            forward: true,
            counters: &counters,
            bindings: &bindings,
            clear: &clear,
        };
        let cnt = self.composite(enc, &pass)?;
        let img = self.read_f32(&image, image_len)?;
        self.mark_host("read image");
        loops_completed(&cnt, &self.gpu)?;
        out.features.copy_from_slice(&img[..npix * ch]);
        out.alpha.copy_from_slice(&img[npix * ch..npix * (ch + 1)]);
        out.depth
            .copy_from_slice(&img[npix * (ch + 1)..npix * (ch + 2)]);
        state.forward = Some(Forward {
            shape,
            buffers,
            deepest: cnt[5],
        });
        let wide = |lo: u32, hi: u32| u64::from(lo) | (u64::from(hi) << 32);
        Ok(Counters {
            visible: u64::from(visible),
            intersections: u64::from(total),
            evaluated: wide(cnt[0], cnt[1]),
            blended: wide(cnt[2], cnt[3]),
        })
    }

    /// Backward of [`GpuRasterizer::rasterize_forward`] (as
    /// [`sync4d_raster::rasterize_backward`]): dL/d(splats) from dL/d(image outputs).
    /// `splats`, `background`, `settings` and `state` must be the forward's.
    #[allow(clippy::too_many_arguments)]
    pub fn rasterize_backward(
        &mut self,
        splats: &Splats<'_, f32>,
        width: u32,
        height: u32,
        background: &[f32],
        settings: &BlendSettings,
        state: &mut GpuRasterState,
        v: &ImageGrads<'_, f32>,
        grads: SplatGradsMut<'_, f32>,
    ) -> Result<()> {
        splats.validate(background)?;
        settings.validate()?;
        let ch = splats.channels;
        let n = splats.len();
        let forward =
            match &state.forward {
                Some(f)
                    if f.shape.n == n
                        && f.shape.channels == ch
                        && f.shape.width == width
                        && f.shape.height == height
                        && f.shape.alpha_max == settings.alpha_max as f32 =>
                {
                    f
                }
                _ => return Err(RasterError::invalid(
                    "state",
                    "backward needs the state of a forward call with the same splats, image size \
                     and channels",
                )
                .into()),
            };
        let npix = (width * height) as usize;
        v.validate(npix, ch)?;
        grads.check_len(n, ch)?;
        if n == 0 {
            return Ok(());
        }
        let stride = ch + 7;
        if let Some(p) = self.profile.as_mut() {
            p.since = Some(std::time::Instant::now());
        }
        let dev = self.gpu.device.clone();
        let mut vimg = Vec::with_capacity(npix * (ch + 2));
        vimg.extend_from_slice(v.features);
        vimg.extend_from_slice(v.alpha);
        vimg.extend_from_slice(v.depth);
        let v_buf = self.upload("v_image", &vimg)?;
        let out = self.storage("splat_grads", (n * stride * 4) as u64)?;
        let mut enc = dev.create_command_encoder(&Default::default());
        self.mark(&mut enc, "upload v_image");
        let (isects, visible) = (forward.shape.intersections, forward.shape.visible);
        let halves = self.layout.column_halves.applies(true, isects, visible);
        let pipe = self.kernels.blend(&dev, self.layout, ch, halves, false);
        let counters = self.storage("counters", COUNTERS_BYTES)?;
        let walk_state = self.storage("walk_state", npix as u64 * 8)?;
        let mut bindings = vec![(8, &counters), (9, &v_buf), (10, &out), (11, &walk_state)];
        bindings.extend(forward.buffers.bindings());
        let grads_bytes = (n * stride * 4) as u64;
        let clear = [(&out, grads_bytes), (&counters, COMPOSITING_COUNTERS_BYTES)];
        let pass = CompositePass {
            pipe: &pipe,
            shape: &forward.shape,
            longest: forward.deepest,
            forward: false,
            counters: &counters,
            bindings: &bindings,
            clear: &clear,
        };
        let cnt = self.composite(enc, &pass)?;
        let r = self.read_f32(&out, n * stride)?;
        self.mark_host("read grads");
        loops_completed(&cnt, &self.gpu)?;
        for i in 0..n {
            let s = &r[stride * i..stride * (i + 1)];
            grads.means2d[2 * i..2 * i + 2].copy_from_slice(&s[0..2]);
            grads.conics[3 * i..3 * i + 3].copy_from_slice(&s[2..5]);
            grads.opacities[i] = s[5];
            grads.features[ch * i..ch * (i + 1)].copy_from_slice(&s[6..6 + ch]);
            grads.depths[i] = s[6 + ch];
        }
        Ok(())
    }

    /// Exclusive scan of `len` u32 values of `values` into `out` (`len + 1` entries; the last
    /// is the total).
    fn scan(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        values: &wgpu::Buffer,
        out: &wgpu::Buffer,
        len: u32,
    ) -> Result<()> {
        let blocks = len.div_ceil(SCAN_BLOCK);
        let sums = self.storage("scan_sums", u64::from(blocks.max(1)) * 4)?;
        let prm = self.uniform(&ScanParams {
            len,
            blocks,
            pad: [0; 2],
        });
        let k = &self.kernels;
        let g = self.bind(
            &k.scan_blocks,
            &[(0, &prm), (1, values), (2, out), (3, &sums)],
        );
        Self::dispatch(enc, &k.scan_blocks, &g, grid(blocks.max(1)));
        let g = self.bind(&k.scan_sums, &[(0, &prm), (2, out), (3, &sums)]);
        Self::dispatch(enc, &k.scan_sums, &g, (1, 1));
        let g = self.bind(&k.scan_add, &[(0, &prm), (2, out), (3, &sums)]);
        Self::dispatch(enc, &k.scan_add, &g, grid(blocks.max(1)));
        Ok(())
    }
}

/// Camera and settings in the layout of project.wgsl's `Params`.
fn project_params(cam: &Camera, s: &ProjectSettings, n: u32) -> ProjectParams {
    let m = &cam.world_to_camera;
    let (w, h) = (cam.width as f64, cam.height as f64);
    let tan_fovx = 0.5 * w / cam.fx;
    let tan_fovy = 0.5 * h / cam.fy;
    let row = |r: usize| {
        [
            m[r][0] as f32,
            m[r][1] as f32,
            m[r][2] as f32,
            m[r][3] as f32,
        ]
    };
    ProjectParams {
        rot: [row(0), row(1), row(2)],
        intr: [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32],
        size: [
            w as f32,
            h as f32,
            s.eps2d as f32,
            f32::from(u8::from(s.antialiased)),
        ],
        lims: [
            ((w - cam.cx) / cam.fx + 0.3 * tan_fovx) as f32,
            (cam.cx / cam.fx + 0.3 * tan_fovx) as f32,
            ((h - cam.cy) / cam.fy + 0.3 * tan_fovy) as f32,
            (cam.cy / cam.fy + 0.3 * tan_fovy) as f32,
        ],
        clip: [s.near as f32, s.far.min(f32::MAX as f64) as f32, 0.0, 0.0],
        count: [n, 0, 0, 0],
    }
}

#[cfg(test)]
mod tests {
    use super::{chunk_size, jumps_out, ColumnHalves, CHUNK_TRIPS, MIN_CHUNK};

    #[test]
    fn chunks_fit_the_loop_trips_of_cpu_adapters() {
        // GPUs: up to MAX_CHUNKS chunks of at least MIN_CHUNK entries.
        assert_eq!(chunk_size(100_000, 50, None), 256);
        assert_eq!(chunk_size(10_000_000, 1, None), 9766);
        // CPU adapters: fewer, larger chunks, each within CHUNK_TRIPS trips.
        let threads = std::thread::available_parallelism().map_or(1, |t| t.get()) as u32;
        let small = chunk_size(100_000, 5, Some(threads));
        assert_eq!(small, 100_000u32.div_ceil(16 * threads).clamp(256, 12_000));
        for trips in [1, 5, 52, 1000] {
            for count in [0, 1000, 100_000, 3_000_000, 100_000_000] {
                let size = chunk_size(count, trips, Some(threads));
                assert!(size >= MIN_CHUNK);
                assert!(
                    size * trips <= CHUNK_TRIPS
                        || size == MIN_CHUNK
                        || size == chunk_size(count, trips, None)
                );
            }
        }
    }

    #[test]
    fn column_halves_follow_the_splat_size() {
        let small = ColumnHalves::BackwardBelowTilesPerSplat(7);
        assert!(small.applies(true, 400_000, 100_000));
        assert!(!small.applies(false, 400_000, 100_000));
        assert!(!small.applies(true, 700_000, 100_000));
        assert!(!small.applies(true, 0, 0));
        assert!(ColumnHalves::Always.applies(false, 0, 0));
        assert!(!ColumnHalves::Never.applies(true, 1, 1_000));
    }

    #[test]
    fn jumps_out_sees_only_the_bodys_own_jumps() {
        assert!(jumps_out("if a { continue; }"));
        assert!(jumps_out("x = 1; break;"));
        assert!(!jumps_out("loop { if a { break; } }"));
        assert!(!jumps_out(
            "for (var i = 0u; i < 3u; i++) { continue; } y = 2;"
        ));
        assert!(jumps_out("loop { break; } if b { continue; }"));
        // Comments are not code.
        assert!(!jumps_out("// break while we can\nx = 1;"));
        assert!(jumps_out("// loop { over\nbreak;"));
    }
}
