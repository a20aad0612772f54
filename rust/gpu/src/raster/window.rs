//! Compositing in windows: lavapipe's driver ends a shader's loops after 65,535 trips, so long
//! tile lists are composited over several dispatches, the per-pixel state kept on the device in
//! between. The window choice ([`CompositingWindow`]), the windows in use, and the dispatch loop
//! that halves a window when the kernels' loop guard reports a cut. Apart from the stages, which
//! hand it one compositing pass each.

use sync4d_raster::RasterError;

use super::layout::BlendLayout;
use super::params::COUNTERS_BYTES;
use super::rasterizer::{ForwardShape, GpuRasterizer};
use crate::error::Result;

/// The smallest compositing window the automatic choice halves down to before giving up.
const MIN_WINDOW: u32 = 256;

/// One compositing run: the kernel (forward or backward), the frame's shape, the longest tile
/// list, the counters buffer (also among `bindings`), the bind group entries besides the
/// parameters, and the buffers (with byte counts) to zero before each attempt.
#[derive(Clone, Copy)]
pub(super) struct CompositePass<'a> {
    pub(super) pipe: &'a wgpu::ComputePipeline,
    pub(super) shape: &'a ForwardShape,
    pub(super) longest: u32,
    pub(super) forward: bool,
    pub(super) counters: &'a wgpu::Buffer,
    pub(super) bindings: &'a [(u32, &'a wgpu::Buffer)],
    pub(super) clear: &'a [(&'a wgpu::Buffer, u64)],
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
pub(super) struct CompositingWindows {
    forward: u32,
    backward: u32,
    /// Halve a window and composite again when the guard reports cut loops (else an error).
    pub(super) adaptive: bool,
}

impl CompositingWindows {
    /// The starting windows for `layout`: the row-block kernels of CPU adapters spend a few
    /// loop trips per entry (measured on lavapipe: forward ~1.2, backward ~5), others are
    /// walked in one dispatch; halved automatically when that proves too long. (A 70,000-entry
    /// list of one-pixel splats on lavapipe: forward passes at 35,000, backward at 17,500.)
    pub(super) fn for_layout(layout: BlendLayout) -> Self {
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

impl GpuRasterizer {
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
    pub(super) fn composite(
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
            enc = self
                .gpu
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        }
    }
}
