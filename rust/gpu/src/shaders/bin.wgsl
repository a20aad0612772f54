// Tile binning: which splats touch which 16x16 tile, front to back within a tile. The depth
// ordered list (ranks) is cut into chunks; `count_corners` and `sum_lines` count
// each chunk's splats per tile (tile-major counts), an exclusive scan turns the counts into write cursors, and `scatter`
// walks each chunk in order and writes the splats' indices: a stable counting sort by tile of
// the depth order, as sync4d-raster's TileBins builds it, deterministic on any hardware.

struct BinParams {
    visible: u32,
    chunks: u32,
    chunk_size: u32,
    tiles_x: u32,
    tiles_y: u32,
    num_tiles: u32,
    // sum_lines: 0 along x, 1 along y.
    axis: u32,
    // Trips of the loop check in `scatter` (2, see loop_check.wgsl).
    canary: u32,
}

@group(0) @binding(0) var<uniform> B: BinParams;
// Sorted (depth key, splat index); the first `visible` entries are the visible splats.
@group(0) @binding(1) var<storage, read> keys: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> splats: array<f32>;
@group(0) @binding(3) var<storage, read> radii: array<i32>;
// Per (tile, chunk), tile-major: intersection counts.
@group(0) @binding(4) var<storage, read_write> counts: array<atomic<u32>>;
// Exclusive scan of `counts` (plus the total): write cursors, advanced by `scatter`.
@group(0) @binding(5) var<storage, read_write> cursors: array<u32>;
// Splat indices, grouped by tile, front to back within a tile.
@group(0) @binding(6) var<storage, read_write> ids: array<u32>;
// tile_offsets[t]..tile_offsets[t + 1] indexes `ids` for tile t.
@group(0) @binding(7) var<storage, read_write> tile_offsets: array<u32>;
// The compositing counters; entry 7 is set when `scatter`'s loops were cut short (llvmpipe's
// cap on loop trips, see loop_check.wgsl).
@group(0) @binding(8) var<storage, read_write> counters: array<atomic<u32>>;
// Per depth rank: its tile rectangle packed as (x0 | x1 << 16, y0 | y1 << 16), written by
// `count_corners` for `scatter` (an empty rectangle where x0 == x1 or y0 == y1).
@group(0) @binding(9) var<storage, read_write> rects: array<vec2<u32>>;

const TILE: f32 = 16.0;

// The flat invocation index of a 2D grid of workgroups of `size` invocations (see `grid` in
// raster/kernels.rs: beyond 65,535 workgroups the grid wraps into y).
fn flat_id(gid: vec3<u32>, nwg: vec3<u32>, size: u32) -> u32 {
    return gid.x + gid.y * nwg.x * size;
}

// Tile rectangle [x0, y0, x1, y1) of splat g: floor((m - r) / 16) .. ceil((m + r) / 16).
fn tile_rect(g: u32) -> vec4<u32> {
    let mx = splats[8u * g] / TILE;
    let my = splats[8u * g + 1u] / TILE;
    let rx = f32(radii[2u * g]) / TILE;
    let ry = f32(radii[2u * g + 1u]) / TILE;
    let tx = f32(B.tiles_x);
    let ty = f32(B.tiles_y);
    return vec4<u32>(
        u32(clamp(floor(mx - rx), 0.0, tx)),
        u32(clamp(floor(my - ry), 0.0, ty)),
        u32(clamp(ceil(mx + rx), 0.0, tx)),
        u32(clamp(ceil(my + ry), 0.0, ty)),
    );
}

// Per-chunk tile counts as 2D difference tables: each splat adds +1 at its tile rectangle's
// top-left corner and -1 / -1 / +1 at the corners past its right, bottom and bottom-right
// edges (those inside the grid; u32 arithmetic wraps, the sums are exact). `sum_lines` along x,
// then along y, turns the table into counts: 4 atomics per splat instead of one per tile.
fn add_corner(x: u32, y: u32, chunk: u32, v: u32) {
    if x < B.tiles_x && y < B.tiles_y {
        atomicAdd(&counts[(y * B.tiles_x + x) * B.chunks + chunk], v);
    }
}

@compute @workgroup_size(256)
fn count_corners(@builtin(global_invocation_id) gid: vec3<u32>,
                 @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = flat_id(gid, nwg, 256u);
    if r >= B.visible {
        return;
    }
    let rect = tile_rect(keys[r].y);
    rects[r] = vec2<u32>(rect.x | (rect.z << 16u), rect.y | (rect.w << 16u));
    if rect.x >= rect.z || rect.y >= rect.w {
        return;
    }
    let chunk = r / B.chunk_size;
    add_corner(rect.x, rect.y, chunk, 1u);
    add_corner(rect.z, rect.y, chunk, 0xffffffffu);
    add_corner(rect.x, rect.w, chunk, 0xffffffffu);
    add_corner(rect.z, rect.w, chunk, 1u);
}

// Running sums of the difference table along x (`B.axis` 0: every (chunk, tile row)), then
// along y (1: every (chunk, tile column)); after both, the per-(tile, chunk) counts.
@compute @workgroup_size(256)
fn sum_lines(@builtin(global_invocation_id) gid: vec3<u32>,
             @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = flat_id(gid, nwg, 256u);
    let rows = B.axis == 0u;
    let lines = select(B.tiles_x, B.tiles_y, rows);
    if i >= B.chunks * lines {
        return;
    }
    let line = i / B.chunks;
    let first = select(line, line * B.tiles_x, rows) * B.chunks + i % B.chunks;
    let step = select(B.tiles_x * B.chunks, B.chunks, rows);
    let length = select(B.tiles_y, B.tiles_x, rows);
    var run = 0u;
    for (var k = 0u; k < length; k++) {
        let at = first + k * step;
        run += atomicLoad(&counts[at]);
        atomicStore(&counts[at], run);
    }
}

@compute @workgroup_size(256)
fn tile_ranges(@builtin(global_invocation_id) gid: vec3<u32>,
               @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = flat_id(gid, nwg, 256u);
    if t > B.num_tiles {
        return;
    }
    tile_offsets[t] = cursors[t * B.chunks];
}

// One invocation per (chunk, tile row) walks the chunk in order and writes the indices of the
// splats that reach its row: a few hundred loop trips each (llvmpipe ends a shader's loops
// after 65,535 trips in all, which one invocation per chunk reached on large scenes).
// Neighbouring invocations take neighbouring rows of one chunk, so SIMD lanes read the same
// rectangles and mostly agree on the row loop's trip count.
@compute @workgroup_size(16)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>,
           @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = flat_id(gid, nwg, 16u);
    if i >= B.chunks * B.tiles_y {
        return;
    }
    let chunk = i / B.tiles_y;
    let y = i % B.tiles_y;
    // Uniforms read once, out of the loops: llvmpipe turns a uniform read inside a loop into a
    // bounds-checked per-lane gather.
    let chunks = B.chunks;
    let row_slots = y * B.tiles_x * chunks + chunk;
    let end = min((chunk + 1u) * B.chunk_size, B.visible);
    for (var r = chunk * B.chunk_size; r < end; r++) {
        let rect = rects[r];
        let x1 = select(0u, rect.x >> 16u, y >= (rect.y & 0xffffu) && y < (rect.y >> 16u));
        // The splat index is read per written entry, not per (splat, row): most rows of a
        // chunk's splats miss this invocation's row, and on llvmpipe every read costs a
        // per-lane loop even where all lanes skip it.
        for (var x = rect.x & 0xffffu; x < x1; x++) {
            let slot = row_slots + x * chunks;
            let at = cursors[slot];
            ids[at] = keys[r].y;
            cursors[slot] = at + 1u;
        }
    }
    if !loops_completed(B.canary) {
        atomicStore(&counters[7], 1u);
    }
}

// The same writes with one invocation per chunk, for CPU adapters: it walks its chunk's splats
// once, in order, and each splat's whole tile rectangle (SIMD lanes take different chunks, so
// a rectangle read serves one lane instead of being repeated for every tile row; the host
// picks this kernel only when every chunk stays within the driver's loop trips).
@compute @workgroup_size(16)
fn scatter_chunks(@builtin(global_invocation_id) gid: vec3<u32>,
                  @builtin(num_workgroups) nwg: vec3<u32>) {
    let chunk = flat_id(gid, nwg, 16u);
    if chunk >= B.chunks {
        return;
    }
    let chunks = B.chunks;
    let tiles_x = B.tiles_x;
    let end = min((chunk + 1u) * B.chunk_size, B.visible);
    for (var r = chunk * B.chunk_size; r < end; r++) {
        let rect = rects[r];
        let g = keys[r].y;
        let x0 = rect.x & 0xffffu;
        let y0 = rect.y & 0xffffu;
        let width = (rect.x >> 16u) - min(x0, rect.x >> 16u);
        let cells = select(0u, width * ((rect.y >> 16u) - y0), (rect.y >> 16u) > y0);
        // One flat loop over the rectangle, row by row.
        var x = x0;
        var slot = (y0 * tiles_x + x0) * chunks + chunk;
        for (var c = 0u; c < cells; c++) {
            let at = cursors[slot];
            ids[at] = g;
            cursors[slot] = at + 1u;
            x += 1u;
            slot += chunks;
            if x == x0 + width {
                x = x0;
                slot += (tiles_x - width) * chunks;
            }
        }
    }
    if !loops_completed(B.canary) {
        atomicStore(&counters[7], 1u);
    }
}

