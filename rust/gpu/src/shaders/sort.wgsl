// Depth order of the visible splats: 64-bit keys (order-preserving depth bits, splat index)
// sorted by a bitonic network over a power-of-two padded array. Keys are unique, so the
// result is the (depth, index) order of sync4d-raster, whatever the hardware.

struct SortParams {
    // Bitonic stage size k and compare distance j.
    k: u32,
    j: u32,
    // Splats N and padded length P (a power of two >= N).
    n: u32,
    p: u32,
}

@group(0) @binding(0) var<uniform> S: SortParams;
// (depth key, splat index) per slot; invisible splats and padding are (MAX, MAX).
@group(0) @binding(1) var<storage, read_write> keys: array<vec2<u32>>;
@group(0) @binding(2) var<storage, read> splats: array<f32>;
@group(0) @binding(3) var<storage, read> radii: array<i32>;

const NONE: u32 = 0xffffffffu;

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
    if i >= S.p {
        return;
    }
    if i < S.n && radii[2u * i] > 0 && radii[2u * i + 1u] > 0 {
        keys[i] = vec2<u32>(depth_key(splats[8u * i + 6u]), i);
    } else {
        keys[i] = vec2<u32>(NONE, NONE);
    }
}

fn less(a: vec2<u32>, b: vec2<u32>) -> bool {
    return a.x < b.x || (a.x == b.x && a.y < b.y);
}

@compute @workgroup_size(256)
fn bitonic_step(@builtin(global_invocation_id) gid: vec3<u32>,
                @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = flat_id(gid, nwg);
    let l = i ^ S.j;
    if i >= S.p || l <= i {
        return;
    }
    let a = keys[i];
    let b = keys[l];
    let ascending = (i & S.k) == 0u;
    if (ascending && less(b, a)) || (!ascending && less(a, b)) {
        keys[i] = b;
        keys[l] = a;
    }
}
