//! Tile binning: which splats touch which 16x16 tile, in front-to-back order.
//!
//! Parallel design. Visible splats are first sorted by `(depth, index)` (one parallel sort of
//! packed u64 keys; depth > near > 0 so its f32 bits sort like the value). The depth-ordered list
//! is cut into a fixed number of chunks (a function of N only, never of the thread count): each
//! chunk counts its splats per tile in parallel, an exclusive prefix sum over (tile, chunk) gives
//! every chunk a private write cursor per tile, and a second parallel pass scatters depth ranks.
//! The result equals a stable counting sort by tile of the depth-ordered list, so it is the same
//! for any thread count. Alongside, each splat's intersection positions are recorded (CSR), so the
//! backward can reduce per-intersection gradients per splat without atomics.

use crate::error::{RasterError, Result};
use crate::TILE_SIZE;
use rayon::prelude::*;

/// Per-tile lists of splat ids plus the per-splat inverse map. Buffers are reused across calls.
#[derive(Debug, Default, Clone)]
pub struct TileBins {
    /// Tiles along x.
    pub tiles_x: u32,
    /// Tiles along y.
    pub tiles_y: u32,
    /// `tile_offsets[t]..tile_offsets[t + 1]` indexes `ids` for tile `t` (row-major tiles).
    pub tile_offsets: Vec<u32>,
    /// Depth rank (index into [`TileBins::splat_of_rank`]) of every intersection, grouped by
    /// tile, front to back within a tile.
    pub ids: Vec<u32>,
    /// `splat_offsets[g]..splat_offsets[g + 1]` indexes `splat_isects` for splat `g`.
    pub splat_offsets: Vec<u32>,
    /// Positions in `ids` of each splat's intersections.
    pub splat_isects: Vec<u32>,
    /// Scratch: depth-sort keys.
    order: Vec<u64>,
    /// Scratch: per-(chunk, tile) counts, then write cursors.
    chunk_cursors: Vec<u32>,
    /// Scratch: per-splat tile rectangles `[x0, y0, x1, y1]` (half-open).
    rects: Vec<[u32; 4]>,
}

/// Raw pointer that may be shared across rayon tasks which write disjoint indices.
#[derive(Clone, Copy)]
pub(crate) struct SharedMut<T> {
    ptr: *mut T,
    len: usize,
}

// SAFETY: every user writes disjoint indices from different tasks (documented at each use).
unsafe impl<T: Send> Send for SharedMut<T> {}
unsafe impl<T: Send> Sync for SharedMut<T> {}

impl<T> SharedMut<T> {
    /// Wrap a slice whose elements the caller will write from several tasks, disjointly.
    pub(crate) fn new(s: &mut [T]) -> Self {
        SharedMut {
            ptr: s.as_mut_ptr(),
            len: s.len(),
        }
    }

    /// Write `v` at `i`.
    ///
    /// # Safety
    /// No other task may access index `i` concurrently, and the slice must outlive the call.
    #[inline(always)]
    pub(crate) unsafe fn write(&self, i: usize, v: T) {
        debug_assert!(i < self.len);
        // SAFETY: `i` is in bounds (the callers index their own tile's or splat's range) and
        // no other task touches it (this function's contract).
        unsafe {
            *self.ptr.add(i) = v;
        }
    }
}

/// Tile rectangle `[x0, y0, x1, y1)` of a splat, gsplat's rule:
/// `floor((m - r) / 16) .. ceil((m + r) / 16)`, clamped to the grid.
#[inline]
pub fn tile_rect(mean: [f64; 2], radius: [i32; 2], tiles_x: u32, tiles_y: u32) -> [u32; 4] {
    let ts = TILE_SIZE as f64;
    let clampi = |v: f64, hi: u32| v.max(0.0).min(hi as f64) as u32;
    let (mx, my) = (mean[0] / ts, mean[1] / ts);
    let (rx, ry) = (radius[0] as f64 / ts, radius[1] as f64 / ts);
    [
        clampi((mx - rx).floor(), tiles_x),
        clampi((my - ry).floor(), tiles_y),
        clampi((mx + rx).ceil(), tiles_x),
        clampi((my + ry).ceil(), tiles_y),
    ]
}

/// Order-preserving map of an f32 to a u32 (negative values included).
#[inline(always)]
fn depth_key(d: f32) -> u32 {
    let b = d.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b | 0x8000_0000
    }
}

impl TileBins {
    /// Bin splats (`means2d` N*2, `radii` N*2, `depths` N) into the tiles of a
    /// `width` x `height` image. Splats with a zero radius are skipped.
    pub fn build(
        &mut self,
        means2d: &[f32],
        radii: &[i32],
        depths: &[f32],
        width: u32,
        height: u32,
    ) -> Result<()> {
        self.build_generic(
            |g| [means2d[2 * g] as f64, means2d[2 * g + 1] as f64],
            radii,
            depths,
            width,
            height,
        )
    }

    // The counting sort's passes (count, scan, scatter, per-splat index) share their buffers.
    #[allow(clippy::too_many_lines)]
    fn build_generic(
        &mut self,
        mean_of: impl Fn(usize) -> [f64; 2] + Sync,
        radii: &[i32],
        depths: &[f32],
        width: u32,
        height: u32,
    ) -> Result<()> {
        let n = depths.len();
        let tiles_x = width.div_ceil(TILE_SIZE);
        let tiles_y = height.div_ceil(TILE_SIZE);
        let num_tiles = (tiles_x * tiles_y) as usize;
        self.tiles_x = tiles_x;
        self.tiles_y = tiles_y;

        // Tile rectangles and per-splat counts.
        self.rects.resize(n, [0; 4]);
        self.rects.par_iter_mut().enumerate().for_each(|(g, r)| {
            let rad = [radii[2 * g], radii[2 * g + 1]];
            *r = if rad[0] > 0 && rad[1] > 0 {
                tile_rect(mean_of(g), rad, tiles_x, tiles_y)
            } else {
                [0; 4]
            };
        });
        self.splat_offsets.resize(n + 1, 0);
        self.splat_offsets[0] = 0;
        let mut total: u64 = 0;
        for (g, r) in self.rects.iter().enumerate() {
            total += ((r[2] - r[0]) as u64) * ((r[3] - r[1]) as u64);
            if total > u32::MAX as u64 {
                return Err(RasterError::invalid(
                    "radii",
                    "more than 2^32 tile intersections; reduce the image size or Gaussian count",
                ));
            }
            self.splat_offsets[g + 1] = total as u32;
        }
        let m = total as usize;

        // Depth order of the splats that touch at least one tile.
        self.order.clear();
        self.order.extend((0..n).filter_map(|g| {
            let r = self.rects[g];
            (r[2] > r[0] && r[3] > r[1]).then(|| ((depth_key(depths[g]) as u64) << 32) | g as u64)
        }));
        self.order.par_sort_unstable();

        // Chunked counting sort by tile.
        let nv = self.order.len();
        let chunks = (nv / 8192).clamp(1, 64);
        let chunk_len = nv.div_ceil(chunks).max(1);
        self.chunk_cursors.clear();
        self.chunk_cursors.resize(chunks * num_tiles, 0);
        let rects = &self.rects;
        let order = &self.order;
        self.chunk_cursors
            .par_chunks_mut(num_tiles)
            .enumerate()
            .for_each(|(ci, counts)| {
                let lo = (ci * chunk_len).min(nv);
                let hi = ((ci + 1) * chunk_len).min(nv);
                for key in &order[lo..hi] {
                    let r = rects[(key & 0xffff_ffff) as usize];
                    for ty in r[1]..r[3] {
                        let row = (ty * tiles_x) as usize;
                        for tx in r[0]..r[2] {
                            counts[row + tx as usize] += 1;
                        }
                    }
                }
            });
        self.tile_offsets.resize(num_tiles + 1, 0);
        let mut run: u32 = 0;
        for t in 0..num_tiles {
            self.tile_offsets[t] = run;
            for ci in 0..chunks {
                let cnt = self.chunk_cursors[ci * num_tiles + t];
                self.chunk_cursors[ci * num_tiles + t] = run;
                run += cnt;
            }
        }
        self.tile_offsets[num_tiles] = run;
        debug_assert_eq!(run as usize, m);

        self.ids.resize(m, 0);
        self.splat_isects.resize(m, 0);
        let ids = SharedMut::new(&mut self.ids);
        let isects = SharedMut::new(&mut self.splat_isects);
        let splat_offsets = &self.splat_offsets;
        self.chunk_cursors
            .par_chunks_mut(num_tiles)
            .enumerate()
            .for_each(|(ci, cursors)| {
                let lo = (ci * chunk_len).min(nv);
                let hi = ((ci + 1) * chunk_len).min(nv);
                for (i, key) in order[lo..hi].iter().enumerate() {
                    let rank = (lo + i) as u32;
                    let g = (key & 0xffff_ffff) as usize;
                    let r = rects[g];
                    let mut slot = splat_offsets[g] as usize;
                    for ty in r[1]..r[3] {
                        let row = (ty * tiles_x) as usize;
                        for tx in r[0]..r[2] {
                            let pos = cursors[row + tx as usize];
                            cursors[row + tx as usize] += 1;
                            // SAFETY: `pos` comes from this chunk's private cursor range for the
                            // tile, and `slot` from this splat's private CSR range: no two tasks
                            // write the same index, and both vectors outlive the scope.
                            unsafe {
                                ids.write(pos as usize, rank);
                                isects.write(slot, pos);
                            }
                            slot += 1;
                        }
                    }
                }
            });
        Ok(())
    }

    /// Number of splats that touch at least one tile (the depth ranks run over `0..visible()`).
    pub fn visible(&self) -> usize {
        self.order.len()
    }

    /// Splat index of depth rank `rank`.
    #[inline(always)]
    pub fn splat_of_rank(&self, rank: usize) -> usize {
        (self.order[rank] & 0xffff_ffff) as usize
    }

    /// Number of tile intersections.
    pub fn len(&self) -> usize {
        self.ids.len()
    }

    /// Whether no splat touches any tile.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }

    /// Range of `ids` for tile `t`.
    #[inline(always)]
    pub fn tile_range(&self, t: usize) -> std::ops::Range<usize> {
        self.tile_offsets[t] as usize..self.tile_offsets[t + 1] as usize
    }
}
