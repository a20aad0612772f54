//! The rasterizer: [`GpuRasterizer`] (the device, compiled kernels, compositing layout and
//! windows in use) and [`GpuRasterState`] (what a forward leaves for its backward), the
//! rasterization forward (depth sort, tile binning, scatter, compositing) and backward, and the
//! chunking of the chunk-serial kernels. The layout policy, kernels, buffers, windows and
//! profiling it drives live in the sibling files.

use sync4d_raster::blend::check_image_size;
use sync4d_raster::{
    BlendSettings, Counters, ImageGrads, ImageMut, RasterError, SplatGradsMut, Splats, TILE_SIZE,
};

use super::buffers::{storage_in, upload_in, ForwardBuffers, Pool};
use super::kernels::{grid, Kernels};
use super::layout::{BlendLayout, ColumnHalves};
use super::params::{
    BinParams, BlendParams, ScanParams, SortParams, CHUNK_WG, COMPOSITING_COUNTERS_BYTES,
    COUNTERS_BYTES, FIRST_WINDOW, LAST_WINDOW, SCAN_BLOCK, SPLAT_FLOATS, WG,
};
use super::profile::Profile;
use super::window::{CompositePass, CompositingWindows};
use crate::device::GpuDevice;
use crate::error::{GpuError, Result};

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

/// Compositing thresholds: sync4d-raster's, in f32 (the CPU kernels round them the same way).
const ALPHA_MIN: f32 = sync4d_raster::ALPHA_MIN as f32;
const T_MIN: f32 = sync4d_raster::T_MIN as f32;

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

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct ForwardShape {
    n: usize,
    channels: usize,
    width: u32,
    height: u32,
    pub(super) tiles_x: u32,
    pub(super) tiles_y: u32,
    alpha_max: f32,
    /// Tile intersections and visible splats (which kernels suit the scene: [`ColumnHalves`]).
    intersections: u64,
    visible: u64,
}

impl ForwardShape {
    /// The compositing kernels' parameters for window `w` of `windows` (blend.wgsl
    /// `BlendParams`): list positions [w * size, (w + 1) * size), the last one open-ended;
    /// `forward` walks them in increasing order, the backward in decreasing.
    pub(super) fn blend_params(
        &self,
        w: u32,
        windows: u32,
        size: u32,
        forward: bool,
    ) -> BlendParams {
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
    pub(super) gpu: GpuDevice,
    pub(super) kernels: Kernels,
    pub(super) pool: Pool,
    /// Per-stage wall times when profiling is on (see [`GpuRasterizer::set_profiling`]).
    pub(super) profile: Option<Profile>,
    pub(super) layout: BlendLayout,
    /// On a CPU adapter, the threads its driver runs (lavapipe: one per CPU), which size the
    /// binning chunks; None on GPUs.
    cpu_threads: Option<u32>,
    /// Tile-list entries composited per dispatch (forward, backward); see
    /// [`GpuRasterizer::set_compositing_window`].
    pub(super) windows: CompositingWindows,
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

/// The splats packed for the device ([`SPLAT_FLOATS`] floats each: mean, conic, opacity,
/// depth, padding) and what the binning needs to know of them.
struct PackedSplats {
    packed: Vec<f32>,
    /// Splats with both radii positive.
    visible: u32,
    /// The widest and the largest tile rectangle of a visible splat (in tiles), bounding the
    /// tile scatter's trips per splat.
    widest: u32,
    largest: u32,
    tiles_x: u32,
    tiles_y: u32,
}

/// Forward stage 0, on the host: pack `splats` for the device and measure their tile
/// rectangles on a `tiles_x` x `tiles_y` grid.
fn pack_splats(splats: &Splats<'_, f32>, tiles_x: u32, tiles_y: u32) -> PackedSplats {
    let n = splats.len();
    let mut packed = vec![0.0f32; n.max(1) * SPLAT_FLOATS];
    let mut visible = 0u32;
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
    PackedSplats {
        packed,
        visible,
        widest,
        largest,
        tiles_x,
        tiles_y,
    }
}

/// A forward's device inputs and the state buffers it fills for the backward.
struct ForwardInputs {
    splats: wgpu::Buffer,
    radii: wgpu::Buffer,
    /// Features with the background appended.
    features: wgpu::Buffer,
    /// (depth key, index) pairs, depth-sorted by [`GpuRasterizer::depth_sort`].
    keys: wgpu::Buffer,
    keys_tmp: wgpu::Buffer,
    /// Each tile's range of the tile lists (tiles + 1 entries).
    tile_offsets: wgpu::Buffer,
    pixel_state: wgpu::Buffer,
}

/// What tile binning leaves for the scatter: its choice of kernel and chunks, its
/// parameters, the scanned (tile, chunk) counts and the visible splats' tile rectangles, and
/// the tile lists' total length and longest list.
struct TileBinning {
    by_chunks: bool,
    chunks: u32,
    tiles_y: u32,
    params: wgpu::Buffer,
    cursors: wgpu::Buffer,
    rects: wgpu::Buffer,
    total: u32,
    longest: u32,
}

impl GpuRasterizer {
    /// Compile the kernels on `gpu`.
    pub fn new(gpu: GpuDevice) -> Self {
        let kernels = Kernels::new(&gpu.device);
        let layout = BlendLayout::for_device(&gpu);
        let cpu_threads = (gpu.adapter.kind == "cpu")
            .then(|| std::thread::available_parallelism().map_or(1, std::num::NonZero::get) as u32);
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

    /// The device this rasterizer runs on.
    pub fn device(&self) -> &GpuDevice {
        &self.gpu
    }

    /// Composite `splats` into a `width` x `height` image (as
    /// [`sync4d_raster::rasterize_forward`]): features plus `T_final * background`, alpha and
    /// accumulated depth; `state` keeps what the backward needs. Counters: `visible`,
    /// `intersections` and `blended` equal the CPU path's; `evaluated` counts the (live
    /// pixel, splat) pairs the kernel evaluated (the row-block kernels skip the splats whose
    /// support misses a block; the CPU path also skips row halves its support misses, so its
    /// count is lower).
    ///
    /// Stages, each its own function: [`pack_splats`] (host), [`Self::upload_inputs`],
    /// [`Self::depth_sort`], [`Self::bin_tiles`] (which reads the tile ranges back),
    /// [`Self::scatter_ids`] and [`Self::composite_forward`] (which reads the image back).
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
        let (tiles_x, tiles_y) = (width.div_ceil(TILE_SIZE), height.div_ceil(TILE_SIZE));
        let packed = pack_splats(splats, tiles_x, tiles_y);
        let inputs = self.upload_inputs(&mut state.pool, splats, background, &packed, npix)?;

        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        self.mark(&mut enc, "upload");
        self.depth_sort(&mut enc, n as u32, &inputs)?;
        let bins = self.bin_tiles(enc, &inputs, &packed, tiles_x, tiles_y)?;
        let (enc, ids, counters) = self.scatter_ids(&mut state.pool, &inputs, &bins)?;

        let shape = ForwardShape {
            n,
            channels: ch,
            width,
            height,
            tiles_x,
            tiles_y,
            alpha_max: settings.alpha_max as f32,
            intersections: u64::from(bins.total),
            visible: u64::from(packed.visible),
        };
        let buffers = ForwardBuffers {
            splats: inputs.splats,
            ids,
            tile_offsets: inputs.tile_offsets,
            features: inputs.features,
            pixel_state: inputs.pixel_state,
        };
        let (img, cnt) = self.composite_forward(enc, &shape, &buffers, &counters, bins.longest)?;
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
            visible: u64::from(packed.visible),
            intersections: u64::from(bins.total),
            evaluated: wide(cnt[0], cnt[1]),
            blended: wide(cnt[2], cnt[3]),
        })
    }

    /// Forward stage: the device buffers of the inputs (packed splats, radii, features with
    /// the background appended) and of the per-forward state the backward reads (depth keys,
    /// tile offsets, per-pixel state), all from `pool` (the [`GpuRasterState`]'s).
    fn upload_inputs(
        &self,
        pool: &mut Pool,
        splats: &Splats<'_, f32>,
        background: &[f32],
        packed: &PackedSplats,
        npix: usize,
    ) -> Result<ForwardInputs> {
        let (gpu, n, ch) = (&self.gpu, splats.len(), splats.channels);
        let mut feats = Vec::with_capacity(n * ch + ch);
        feats.extend_from_slice(splats.features);
        feats.extend_from_slice(background);
        let splats_buf = upload_in(gpu, pool, "splats", &packed.packed)?;
        let radii = upload_in(
            gpu,
            pool,
            "radii",
            if n > 0 { splats.radii } else { &[0, 0] },
        )?;
        let features = upload_in(gpu, pool, "features", &feats)?;
        let keys = storage_in(gpu, pool, "keys", n.max(1) as u64 * 8)?;
        let keys_tmp = storage_in(gpu, pool, "keys_tmp", n.max(1) as u64 * 8)?;
        let num_tiles = u64::from(packed.tiles_x * packed.tiles_y);
        let tile_offsets = storage_in(gpu, pool, "tile_offsets", (num_tiles + 1) * 4)?;
        let pixel_state = storage_in(gpu, pool, "pixel_state", npix as u64 * 8)?;
        Ok(ForwardInputs {
            splats: splats_buf,
            radii,
            features,
            keys,
            keys_tmp,
            tile_offsets,
            pixel_state,
        })
    }

    /// Forward stage 1, depth order: radix sort of the `n` splats' (depth key, index) pairs,
    /// 8 bits a pass, ping-ponging between `keys_tmp` and `keys` (four passes: the result
    /// lands in `inputs.keys`). Appended to `enc`.
    fn depth_sort(
        &mut self,
        enc: &mut wgpu::CommandEncoder,
        n: u32,
        inputs: &ForwardInputs,
    ) -> Result<()> {
        let (keys, keys_tmp) = (&inputs.keys, &inputs.keys_tmp);
        let sort_chunk = chunk_size(n, 1, self.cpu_threads);
        let sort_chunks = n.div_ceil(sort_chunk).max(1);
        let digit_counts = self.storage("digit_counts", u64::from(256 * sort_chunks) * 4)?;
        let digit_cursors = self.storage("digit_cursors", u64::from(256 * sort_chunks + 1) * 4)?;
        let sort_params = |shift: u32| SortParams {
            n,
            chunks: sort_chunks,
            chunk_size: sort_chunk,
            shift,
        };
        let prm = self.uniform(&sort_params(0));
        let g = self.bind(
            &self.kernels.depth_keys,
            &[
                (0, &prm),
                (2, keys),
                (3, &inputs.splats),
                (4, &inputs.radii),
            ],
        );
        Self::dispatch(enc, &self.kernels.depth_keys, &g, grid(n.div_ceil(WG)));
        for pass in 0..4u32 {
            let (src, dst) = if pass % 2 == 0 {
                (keys, keys_tmp)
            } else {
                (keys_tmp, keys)
            };
            let prm = self.uniform(&sort_params(8 * pass));
            let count = &self.kernels.radix_count;
            let g = self.bind(count, &[(0, &prm), (1, src), (5, &digit_counts)]);
            Self::dispatch(enc, count, &g, (sort_chunks.div_ceil(CHUNK_WG), 1));
            self.scan(enc, &digit_counts, &digit_cursors, 256 * sort_chunks)?;
            let scatter = &self.kernels.radix_scatter;
            let g = self.bind(
                scatter,
                &[(0, &prm), (1, src), (2, dst), (6, &digit_cursors)],
            );
            Self::dispatch(enc, scatter, &g, (sort_chunks.div_ceil(CHUNK_WG), 1));
        }
        self.mark(enc, "depth sort");
        Ok(())
    }

    /// Forward stage 2, tile binning: per (tile, chunk) counts of the depth-sorted visible
    /// splats, their scan, and each tile's range of the tile lists (`inputs.tile_offsets`).
    /// Submits `enc` and reads the ranges back for the list total and the longest list.
    fn bin_tiles(
        &mut self,
        mut enc: wgpu::CommandEncoder,
        inputs: &ForwardInputs,
        packed: &PackedSplats,
        tiles_x: u32,
        tiles_y: u32,
    ) -> Result<TileBinning> {
        let (cpu_threads, visible, largest) = (self.cpu_threads, packed.visible, packed.largest);
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
        let trips = if by_chunks { largest } else { packed.widest } + 2;
        let chunk_size = chunk_size(visible, trips, cpu_threads);
        let chunks = visible.div_ceil(chunk_size).max(1);
        let num_tiles = tiles_x * tiles_y;
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
        let params = self.uniform(&bin);
        // Auto layouts hold only the bindings an entry point uses.
        let g = self.bind(
            &self.kernels.count_corners,
            &[
                (0, &params),
                (1, &inputs.keys),
                (2, &inputs.splats),
                (3, &inputs.radii),
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
        let tile_offsets = &inputs.tile_offsets;
        let g = self.bind(
            &self.kernels.tile_ranges,
            &[(0, &params), (5, &cursors), (7, tile_offsets)],
        );
        Self::dispatch(
            &mut enc,
            &self.kernels.tile_ranges,
            &g,
            grid((num_tiles + 1).div_ceil(WG)),
        );
        self.mark(&mut enc, "tile ranges");
        self.gpu.queue.submit([enc.finish()]);
        let offsets: Vec<u32> =
            bytemuck::pod_collect_to_vec(&self.read(tile_offsets, (u64::from(num_tiles) + 1) * 4)?);
        let total = offsets[num_tiles as usize];
        let longest = offsets.windows(2).map(|w| w[1] - w[0]).max().unwrap_or(0);
        self.mark_host("read total");
        Ok(TileBinning {
            by_chunks,
            chunks,
            tiles_y,
            params,
            cursors,
            rects,
            total,
            longest,
        })
    }

    /// Forward stage 3, tile lists: scatter the splat indices into each tile's list (`ids`,
    /// from `pool`), by chunks or by rows of tiles as [`Self::bin_tiles`] chose. Returns a
    /// fresh encoder holding the scatter, the tile lists and the cleared counters buffer.
    fn scatter_ids(
        &mut self,
        pool: &mut Pool,
        inputs: &ForwardInputs,
        bins: &TileBinning,
    ) -> Result<(wgpu::CommandEncoder, wgpu::Buffer, wgpu::Buffer)> {
        let ids = storage_in(&self.gpu, pool, "ids", u64::from(bins.total) * 4)?;
        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        let counters = self.storage("counters", COUNTERS_BYTES)?;
        enc.clear_buffer(&counters, 0, Some(COUNTERS_BYTES));
        let (scatter, invocations) = if bins.by_chunks {
            (&self.kernels.scatter_chunks, bins.chunks)
        } else {
            (&self.kernels.scatter, bins.chunks * bins.tiles_y)
        };
        let g = self.bind(
            scatter,
            &[
                (0, &bins.params),
                (1, &inputs.keys),
                (5, &bins.cursors),
                (6, &ids),
                (8, &counters),
                (9, &bins.rects),
            ],
        );
        Self::dispatch(&mut enc, scatter, &g, grid(invocations.div_ceil(CHUNK_WG)));
        let stage = if bins.by_chunks {
            "scatter by chunks"
        } else {
            "scatter by rows"
        };
        self.mark(&mut enc, stage);
        Ok((enc, ids, counters))
    }

    /// Forward stage 4, compositing: every tile's list front to back (appended to `enc`, in
    /// windows of at most `longest` entries), then the image read back: features, alpha and
    /// accumulated depth planes, one after the other. Returns the image and the counters;
    /// errors when the adapter cut a kernel's loops short.
    fn composite_forward(
        &mut self,
        enc: wgpu::CommandEncoder,
        shape: &ForwardShape,
        buffers: &ForwardBuffers,
        counters: &wgpu::Buffer,
        longest: u32,
    ) -> Result<(Vec<f32>, Vec<u32>)> {
        let (ch, npix) = (shape.channels, (shape.width * shape.height) as usize);
        let image_len = npix * (ch + 2);
        let image = self.storage("image", image_len as u64 * 4)?;
        let halves = self
            .layout
            .column_halves
            .applies(false, shape.intersections, shape.visible);
        let dev = self.gpu.device.clone();
        let pipe = self.kernels.blend(&dev, self.layout, ch, halves, true);
        let mut bindings = vec![(6, &image), (8, counters)];
        bindings.extend(buffers.bindings());
        let clear = [(counters, COMPOSITING_COUNTERS_BYTES)];
        let pass = CompositePass {
            pipe: &pipe,
            shape,
            longest,
            forward: true,
            counters,
            bindings: &bindings,
            clear: &clear,
        };
        let cnt = self.composite(enc, &pass)?;
        let img = self.read_f32(&image, image_len)?;
        self.mark_host("read image");
        loops_completed(&cnt, &self.gpu)?;
        Ok((img, cnt))
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
        let mut enc = dev.create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
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

#[cfg(test)]
mod tests {
    use super::{chunk_size, CHUNK_TRIPS, MIN_CHUNK};

    #[test]
    fn chunks_fit_the_loop_trips_of_cpu_adapters() {
        // GPUs: up to MAX_CHUNKS chunks of at least MIN_CHUNK entries.
        assert_eq!(chunk_size(100_000, 50, None), 256);
        assert_eq!(chunk_size(10_000_000, 1, None), 9766);
        // CPU adapters: fewer, larger chunks, each within CHUNK_TRIPS trips.
        let threads = std::thread::available_parallelism().map_or(1, std::num::NonZero::get) as u32;
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
}
