// Tile binning: which splats touch which 16x16 tile, front to back within a tile. The depth
// ordered list (ranks) is cut into chunks; `count_chunks` counts each chunk's splats per tile
// (tile-major counts), an exclusive scan turns the counts into write cursors, and `scatter`
// walks each chunk in order and writes ranks: a stable counting sort by tile of the depth
// order, as sync4d-raster's TileBins builds it, deterministic on any hardware.

struct BinParams {
    visible: u32,
    chunks: u32,
    chunk_size: u32,
    tiles_x: u32,
    tiles_y: u32,
    num_tiles: u32,
    pad0: u32,
    pad1: u32,
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
// Depth ranks, grouped by tile.
@group(0) @binding(6) var<storage, read_write> ids: array<u32>;
// tile_offsets[t]..tile_offsets[t + 1] indexes `ids` for tile t.
@group(0) @binding(7) var<storage, read_write> tile_offsets: array<u32>;

const TILE: f32 = 16.0;

fn flat_id(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 256u;
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

@compute @workgroup_size(256)
fn count_chunks(@builtin(global_invocation_id) gid: vec3<u32>,
                @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = flat_id(gid, nwg);
    if r >= B.visible {
        return;
    }
    let rect = tile_rect(keys[r].y);
    let chunk = r / B.chunk_size;
    for (var y = rect.y; y < rect.w; y++) {
        for (var x = rect.x; x < rect.z; x++) {
            atomicAdd(&counts[(y * B.tiles_x + x) * B.chunks + chunk], 1u);
        }
    }
}

@compute @workgroup_size(256)
fn tile_ranges(@builtin(global_invocation_id) gid: vec3<u32>,
               @builtin(num_workgroups) nwg: vec3<u32>) {
    let t = flat_id(gid, nwg);
    if t > B.num_tiles {
        return;
    }
    tile_offsets[t] = cursors[t * B.chunks];
}

@compute @workgroup_size(64)
fn scatter(@builtin(global_invocation_id) gid: vec3<u32>) {
    let chunk = gid.x;
    if chunk >= B.chunks {
        return;
    }
    let end = min((chunk + 1u) * B.chunk_size, B.visible);
    for (var r = chunk * B.chunk_size; r < end; r++) {
        let rect = tile_rect(keys[r].y);
        for (var y = rect.y; y < rect.w; y++) {
            for (var x = rect.x; x < rect.z; x++) {
                let slot = (y * B.tiles_x + x) * B.chunks + chunk;
                let at = cursors[slot];
                ids[at] = r;
                cursors[slot] = at + 1u;
            }
        }
    }
}
