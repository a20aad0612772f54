// Front-to-back compositing of 16x16 tiles, one workgroup per tile and one invocation per
// pixel; splats are staged through workgroup memory in batches. Same rules and arithmetic as
// sync4d-raster's f32 path: alpha = min(opacity exp(-sigma), alpha_max) with the same
// polynomial exp, skipped below 1/255 or when sigma < 0, and a pixel stops (excluding the
// current splat) when its transmittance would fall below t_min. CHANNELS is substituted by
// the host (one pipeline per channel count).

const C: u32 = {{CHANNELS}}u;

struct BlendParams {
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    alpha_min: f32,
    alpha_max: f32,
    t_min: f32,
    // Number of splats N (features are N*C, then the C background values).
    n: u32,
}

@group(0) @binding(0) var<uniform> F: BlendParams;
// Per splat: mean x, mean y, conic a, b, c, opacity, depth, 0.
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read> keys: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> ids: array<u32>;
@group(0) @binding(4) var<storage, read> tile_offsets: array<u32>;
// N*C features, then C background values.
@group(0) @binding(5) var<storage, read> features: array<f32>;
// H*W*C features, then H*W alpha, then H*W depth.
@group(0) @binding(6) var<storage, read_write> image: array<f32>;
// Per pixel: 1 + list index of the last composited splat (0 if none), final transmittance bits.
@group(0) @binding(7) var<storage, read_write> pixel_state: array<u32>;
// evaluated lo/hi, blended lo/hi.
@group(0) @binding(8) var<storage, read_write> counters: array<atomic<u32>>;

const WG: u32 = 256u;

var<workgroup> sh_pos: array<vec4<f32>, 256>;   // mean x, mean y, opacity, depth
var<workgroup> sh_conic: array<vec4<f32>, 256>; // a, b, c, -
var<workgroup> sh_index: array<u32, 256>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> stop_flag: u32;
var<workgroup> range_start: u32;
var<workgroup> range_end: u32;
var<workgroup> wg_evaluated: atomic<u32>;
var<workgroup> wg_blended: atomic<u32>;

// exp(x) in f32: the Cephes polynomial of sync4d-raster's `fast_exp`, constant for constant.
fn fast_exp(x_in: f32) -> f32 {
    let x = min(max(x_in, -87.0), 87.0);
    let n = floor(x * 1.4426950408889634 + 0.5);
    let r = x - n * 0.693359375 - n * -2.12194440e-4;
    var p = 1.9875691e-4;
    p = p * r + 1.3981999e-3;
    p = p * r + 8.3334519e-3;
    p = p * r + 4.1665796e-2;
    p = p * r + 1.6666665e-1;
    p = p * r + 0.5;
    let poly = p * r * r + r + 1.0;
    return poly * bitcast<f32>(u32(i32(n) + 127) << 23u);
}

fn add_wide(lo: u32, v: u32) {
    if v == 0u {
        return;
    }
    let old = atomicAdd(&counters[lo], v);
    if old + v < old {
        atomicAdd(&counters[lo + 1u], 1u);
    }
}

@compute @workgroup_size(16, 16)
fn blend_forward(@builtin(local_invocation_id) lid3: vec3<u32>,
                 @builtin(local_invocation_index) lid: u32,
                 @builtin(workgroup_id) wid: vec3<u32>) {
    let tile = wid.y * F.tiles_x + wid.x;
    let px = wid.x * 16u + lid3.x;
    let py = wid.y * 16u + lid3.y;
    let inside = px < F.width && py < F.height;
    if lid == 0u {
        atomicStore(&done_count, 0u);
        atomicStore(&wg_evaluated, 0u);
        atomicStore(&wg_blended, 0u);
        range_start = tile_offsets[tile];
        range_end = tile_offsets[tile + 1u];
    }
    let start = workgroupUniformLoad(&range_start);
    let end = workgroupUniformLoad(&range_end);
    var t = 1.0;
    var acc: array<f32, C>;
    var depth = 0.0;
    var last = 0u;
    var done = !inside;
    var evaluated = 0u;
    var blended = 0u;
    if done {
        atomicAdd(&done_count, 1u);
    }
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;
    for (var batch = start; batch < end; batch += WG) {
        workgroupBarrier();
        if lid == 0u {
            stop_flag = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&stop_flag) == WG {
            break;
        }
        let at = batch + lid;
        if at < end {
            let g = keys[ids[at]].y;
            sh_pos[lid] = vec4<f32>(splats[8u * g], splats[8u * g + 1u], splats[8u * g + 5u],
                                    splats[8u * g + 6u]);
            sh_conic[lid] = vec4<f32>(splats[8u * g + 2u], splats[8u * g + 3u],
                                      splats[8u * g + 4u], 0.0);
            sh_index[lid] = g;
        }
        workgroupBarrier();
        let count = min(WG, end - batch);
        for (var k = 0u; k < count && !done; k++) {
            let pos = sh_pos[k];
            let con = sh_conic[k];
            let dx = fx - pos.x;
            let dy = fy - pos.y;
            let sigma = 0.5 * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
            let alpha = min(pos.z * fast_exp(-sigma), F.alpha_max);
            evaluated += 1u;
            if !(sigma >= 0.0) || !(alpha >= F.alpha_min) {
                continue;
            }
            let next_t = t * (1.0 - alpha);
            if next_t < F.t_min {
                done = true;
                atomicAdd(&done_count, 1u);
                break;
            }
            let w = alpha * t;
            let g = sh_index[k];
            for (var c = 0u; c < C; c++) {
                acc[c] += features[g * C + c] * w;
            }
            depth += pos.w * w;
            t = next_t;
            last = batch - start + k + 1u;
            blended += 1u;
        }
    }
    atomicAdd(&wg_evaluated, evaluated);
    atomicAdd(&wg_blended, blended);
    if inside {
        let pix = py * F.width + px;
        let npix = F.width * F.height;
        for (var c = 0u; c < C; c++) {
            image[pix * C + c] = acc[c] + t * features[F.n * C + c];
        }
        image[npix * C + pix] = 1.0 - t;
        image[npix * (C + 1u) + pix] = depth;
        pixel_state[2u * pix] = last;
        pixel_state[2u * pix + 1u] = bitcast<u32>(t);
    }
    workgroupBarrier();
    if lid == 0u {
        add_wide(0u, atomicLoad(&wg_evaluated));
        add_wide(2u, atomicLoad(&wg_blended));
    }
}

// ---------------------------------------------------------------------------------------------
// Backward: each tile walks its list back to front from the furthest last contributor; every
// pixel recovers its transmittance by division (T_i = T_{i+1} / (1 - alpha_i)) and keeps the
// running sum of what lies behind, exactly as sync4d-raster's f32 backward. A batch of splats'
// gradients is summed over the tile's pixels in workgroup memory, then added to the global
// per-splat gradients (float adds by compare-and-swap, so the summation order, and the last
// bits, depend on scheduling).

// Per splat: mean x, mean y, conic a, b, c, opacity, C features, depth.
const STRIDE: u32 = 7u + C;
// Splats per backward batch (the workgroup accumulators hold BATCH * STRIDE floats).
const BATCH: u32 = {{BATCH}}u;

// dL/d image: H*W*C features, then H*W alpha, then H*W depth.
@group(0) @binding(9) var<storage, read> v_image: array<f32>;
// Per splat STRIDE gradient sums (f32 bits, added by compare-and-swap).
@group(0) @binding(10) var<storage, read_write> grads: array<atomic<u32>>;

var<workgroup> acc_grad: array<atomic<u32>, {{ACC}}>;
var<workgroup> sh_b_pos: array<vec4<f32>, BATCH>;   // mean x, mean y, opacity, depth
var<workgroup> sh_b_conic: array<vec4<f32>, BATCH>; // a, b, c, -
var<workgroup> sh_b_index: array<u32, BATCH>;
var<workgroup> max_last: atomic<u32>;
var<workgroup> max_last_u: u32;

fn shared_add(i: u32, v: f32) {
    var old = atomicLoad(&acc_grad[i]);
    loop {
        let r = atomicCompareExchangeWeak(&acc_grad[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}

fn global_add(i: u32, v: f32) {
    var old = atomicLoad(&grads[i]);
    loop {
        let r = atomicCompareExchangeWeak(&grads[i], old, bitcast<u32>(bitcast<f32>(old) + v));
        if r.exchanged {
            break;
        }
        old = r.old_value;
    }
}

@compute @workgroup_size(16, 16)
fn blend_backward(@builtin(local_invocation_id) lid3: vec3<u32>,
                  @builtin(local_invocation_index) lid: u32,
                  @builtin(workgroup_id) wid: vec3<u32>) {
    let tile = wid.y * F.tiles_x + wid.x;
    let px = wid.x * 16u + lid3.x;
    let py = wid.y * 16u + lid3.y;
    let inside = px < F.width && py < F.height;
    let npix = F.width * F.height;
    let pix = py * F.width + px;
    if lid == 0u {
        atomicStore(&max_last, 0u);
        range_start = tile_offsets[tile];
    }
    for (var i = lid; i < BATCH * STRIDE; i += WG) {
        atomicStore(&acc_grad[i], 0u);
    }
    workgroupBarrier();
    var t = 1.0;
    var last = 0u;
    var vc: array<f32, C>;
    var v_depth = 0.0;
    var tail = 0.0;
    var vr = 0.0;
    if inside {
        last = pixel_state[2u * pix];
        t = bitcast<f32>(pixel_state[2u * pix + 1u]);
        var vbg = 0.0;
        for (var c = 0u; c < C; c++) {
            vc[c] = v_image[pix * C + c];
            vbg += vc[c] * features[F.n * C + c];
        }
        v_depth = v_image[npix * (C + 1u) + pix];
        tail = t * (vbg - v_image[npix * C + pix]);
        atomicMax(&max_last, last);
    }
    workgroupBarrier();
    if lid == 0u {
        max_last_u = atomicLoad(&max_last);
    }
    let start_list = workgroupUniformLoad(&range_start);
    var end = workgroupUniformLoad(&max_last_u);
    let fx = f32(px) + 0.5;
    let fy = f32(py) + 0.5;
    while end > 0u {
        let start = select(end - BATCH, 0u, end < BATCH);
        let count = end - start;
        if lid < count {
            let g = keys[ids[start_list + start + lid]].y;
            sh_b_pos[lid] = vec4<f32>(splats[8u * g], splats[8u * g + 1u], splats[8u * g + 5u],
                                      splats[8u * g + 6u]);
            sh_b_conic[lid] = vec4<f32>(splats[8u * g + 2u], splats[8u * g + 3u],
                                        splats[8u * g + 4u], 0.0);
            sh_b_index[lid] = g;
        }
        workgroupBarrier();
        if inside {
            for (var j = i32(count) - 1; j >= 0; j--) {
                let k = start + u32(j);
                if k >= last {
                    continue;
                }
                let pos = sh_b_pos[j];
                let con = sh_b_conic[j];
                let g = sh_b_index[j];
                var vf = v_depth * pos.w;
                for (var c = 0u; c < C; c++) {
                    vf += vc[c] * features[g * C + c];
                }
                let dx = fx - pos.x;
                let dy = fy - pos.y;
                let sigma = 0.5 * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
                let vis = fast_exp(-sigma);
                let raw = pos.z * vis;
                let alpha = min(raw, F.alpha_max);
                if !(sigma >= 0.0) || !(alpha >= F.alpha_min) {
                    continue;
                }
                let one_m = 1.0 - alpha;
                let ti = t / one_m;
                let w = alpha * ti;
                let v_alpha = ti * vf - (vr + tail) / one_m;
                vr += w * vf;
                t = ti;
                let base = u32(j) * STRIDE;
                for (var c = 0u; c < C; c++) {
                    shared_add(base + 6u + c, w * vc[c]);
                }
                shared_add(base + 6u + C, w * v_depth);
                if raw > F.alpha_max {
                    continue;
                }
                let v_sigma = -v_alpha * alpha;
                shared_add(base + 5u, v_alpha * vis);
                shared_add(base + 2u, 0.5 * v_sigma * dx * dx);
                shared_add(base + 3u, v_sigma * dx * dy);
                shared_add(base + 4u, 0.5 * v_sigma * dy * dy);
                shared_add(base, -v_sigma * (con.x * dx + con.y * dy));
                shared_add(base + 1u, -v_sigma * (con.z * dy + con.y * dx));
            }
        }
        workgroupBarrier();
        for (var i = lid; i < count * STRIDE; i += WG) {
            let v = bitcast<f32>(atomicLoad(&acc_grad[i]));
            if v != 0.0 {
                global_add(sh_b_index[i / STRIDE] * STRIDE + i % STRIDE, v);
            }
            atomicStore(&acc_grad[i], 0u);
        }
        workgroupBarrier();
        end = start;
    }
}
