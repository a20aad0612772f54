// Depth order of the visible splats: (order-preserving depth bits, splat index) pairs sorted
// by a least-significant-digit radix sort, four passes of 8 bits. Each pass is a stable
// counting sort cut into chunks of the array: `radix_count` counts each chunk's digits, an
// exclusive scan of the digit-major counts gives every (digit, chunk) a write cursor, and
// `radix_scatter` walks each chunk in order. The input is in index order and every pass is
// stable, so the result is the (depth, index) order of sync4d-raster on any hardware;
// invisible splats (key MAX) come last.

struct SortParams {
    // Splats N, chunks and their size, and this pass's digit shift.
    n: u32,
    chunks: u32,
    chunk_size: u32,
    shift: u32,
}

@group(0) @binding(0) var<uniform> S: SortParams;
@group(0) @binding(1) var<storage, read> keys_in: array<vec2<u32>>;
// (depth key, splat index) per slot; invisible splats are (MAX, index).
@group(0) @binding(2) var<storage, read_write> keys_out: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> splats: array<f32>;
@group(0) @binding(4) var<storage, read> radii: array<i32>;
// Per (digit, chunk), digit-major: counts; then, scanned, write cursors.
@group(0) @binding(5) var<storage, read_write> counts: array<u32>;
@group(0) @binding(6) var<storage, read_write> cursors: array<u32>;

const NONE: u32 = 0xffffffffu;
const DIGITS: u32 = 256u;

// Order-preserving map of an f32 to a u32 (as `depth_key` in sync4d-raster's bins.rs).
fn depth_key(d: f32) -> u32 {
    let b = bitcast<u32>(d);
    if (b & 0x80000000u) != 0u {
        return ~b;
    }
    return b | 0x80000000u;
}

fn flat_id(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 256u;
}

@compute @workgroup_size(256)
fn depth_keys(@builtin(global_invocation_id) gid: vec3<u32>,
              @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = flat_id(gid, nwg);
    if i >= S.n {
        return;
    }
    if radii[2u * i] > 0 && radii[2u * i + 1u] > 0 {
        keys_out[i] = vec2<u32>(depth_key(splats[8u * i + 6u]), i);
    } else {
        keys_out[i] = vec2<u32>(NONE, i);
    }
}

// The pass's digit of `key` (`shift` is S.shift, read once per invocation: llvmpipe turns a
// uniform read inside a loop into a bounds-checked per-lane gather).
fn digit(key: u32, shift: u32) -> u32 {
    return (key >> shift) & (DIGITS - 1u);
}

// One invocation per chunk: its digit counts.
@compute @workgroup_size(16)
fn radix_count(@builtin(global_invocation_id) gid: vec3<u32>) {
    let chunk = gid.x;
    let chunks = S.chunks;
    let shift = S.shift;
    if chunk >= chunks {
        return;
    }
    for (var d = 0u; d < DIGITS; d++) {
        counts[d * chunks + chunk] = 0u;
    }
    let end = min((chunk + 1u) * S.chunk_size, S.n);
    for (var i = chunk * S.chunk_size; i < end; i++) {
        let at = digit(keys_in[i].x, shift) * chunks + chunk;
        counts[at] += 1u;
    }
}

// One invocation per chunk: its keys, in order, to their digit's cursor.
@compute @workgroup_size(16)
fn radix_scatter(@builtin(global_invocation_id) gid: vec3<u32>) {
    let chunk = gid.x;
    let chunks = S.chunks;
    let shift = S.shift;
    if chunk >= chunks {
        return;
    }
    let end = min((chunk + 1u) * S.chunk_size, S.n);
    for (var i = chunk * S.chunk_size; i < end; i++) {
        let k = keys_in[i];
        let at = digit(k.x, shift) * chunks + chunk;
        let to = cursors[at];
        cursors[at] = to + 1u;
        keys_out[to] = k;
    }
}
