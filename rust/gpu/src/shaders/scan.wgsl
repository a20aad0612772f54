// Exclusive prefix sum of a u32 array: per-block scans, a scan of the block sums, then the
// block offsets added back. `out` has one more entry than `values`: the total.

struct ScanParams {
    // Number of values L and of blocks.
    len: u32,
    blocks: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> Q: ScanParams;
@group(0) @binding(1) var<storage, read> values: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<u32>;
@group(0) @binding(3) var<storage, read_write> sums: array<u32>;

const WG: u32 = 256u;
const PER: u32 = 4u;
const BLOCK: u32 = 1024u; // WG * PER

var<workgroup> shared_sums: array<u32, 256>;

// Exclusive scan of one value per invocation across the workgroup; returns the invocation's
// exclusive prefix and leaves the workgroup total in shared_sums[WG - 1] + own value.
fn workgroup_exclusive(lid: u32, v: u32) -> u32 {
    shared_sums[lid] = v;
    workgroupBarrier();
    for (var off = 1u; off < WG; off = off * 2u) {
        var add = 0u;
        if lid >= off {
            add = shared_sums[lid - off];
        }
        workgroupBarrier();
        shared_sums[lid] = shared_sums[lid] + add;
        workgroupBarrier();
    }
    return shared_sums[lid] - v;
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(local_invocation_index) lid: u32,
               @builtin(workgroup_id) wid: vec3<u32>,
               @builtin(num_workgroups) nwg: vec3<u32>) {
    let block = wid.x + wid.y * nwg.x;
    let base = block * BLOCK + lid * PER;
    var local: array<u32, 4>;
    var total = 0u;
    for (var k = 0u; k < PER; k++) {
        var v = 0u;
        if base + k < Q.len {
            v = values[base + k];
        }
        local[k] = total;
        total += v;
    }
    let prefix = workgroup_exclusive(lid, total);
    for (var k = 0u; k < PER; k++) {
        if base + k < Q.len {
            out[base + k] = prefix + local[k];
        }
    }
    if lid == WG - 1u && block < Q.blocks {
        sums[block] = prefix + total;
    }
}

// One workgroup: exclusive scan of the block sums in place, in chunks of WG with a carry;
// writes the grand total to out[len].
@compute @workgroup_size(256)
fn scan_sums(@builtin(local_invocation_index) lid: u32) {
    var carry = 0u;
    for (var start = 0u; start < Q.blocks; start += WG) {
        let i = start + lid;
        var v = 0u;
        if i < Q.blocks {
            v = sums[i];
        }
        let prefix = workgroup_exclusive(lid, v);
        let chunk_total = shared_sums[WG - 1u];
        if i < Q.blocks {
            sums[i] = carry + prefix;
        }
        carry += chunk_total;
        workgroupBarrier();
    }
    if lid == 0u {
        out[Q.len] = carry;
    }
}

@compute @workgroup_size(256)
fn scan_add(@builtin(local_invocation_index) lid: u32,
            @builtin(workgroup_id) wid: vec3<u32>,
            @builtin(num_workgroups) nwg: vec3<u32>) {
    let block = wid.x + wid.y * nwg.x;
    let base = block * BLOCK + lid * PER;
    if block >= Q.blocks {
        return;
    }
    let add = sums[block];
    for (var k = 0u; k < PER; k++) {
        if base + k < Q.len {
            out[base + k] += add;
        }
    }
}
