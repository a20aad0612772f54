//! The compositing layout policy: how the compositing kernels map a 16x16 tile onto
//! invocations ([`BlendLayout`]), when row blocks split into column halves ([`ColumnHalves`]),
//! and which layout each adapter kind gets, with the measurements behind the choice. Kept apart
//! from the kernels it configures (`kernels` turns a layout into WGSL) so that the policy and its
//! numbers read on their own.

use crate::device::GpuDevice;

/// Tile intersections per visible splat below which lavapipe's backward compositing splits
/// rows into column halves. cpu_vs_wgpu, 100k splats 800x800, medians of interleaved runs,
/// backward compositing time over the CPU path's forward time: with halves 5.1 / 4.1 / 3.0
/// against 6.5 / 5.0 / 2.8 at 4.0 / 4.9 / 7.8 intersections per splat (SYNC4D_SCALE 0.08 /
/// 0.1 / 0.15); 1.67 against 1.33 at 163 (an earlier build). The forward was slower with
/// halves at all four (2.9 / 2.5 / 2.3 against 2.5 / 2.3 / 1.8 at the small ones).
const SMALL_SPLAT_TILES: u32 = 7;

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
    /// One pixel per invocation with atomic gradient sums: the layout of discrete and
    /// integrated GPUs (no partials, row blocks, subgroup sums or column halves).
    pub const ONE_PIXEL: BlendLayout = BlendLayout {
        pixels_per_invocation: 1,
        partials: false,
        block_rows: 0,
        subgroup_sums: false,
        column_halves: ColumnHalves::Never,
        float_atomics: false,
    };

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
            BlendLayout::ONE_PIXEL
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
}

#[cfg(test)]
mod tests {
    use super::ColumnHalves;

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
}
