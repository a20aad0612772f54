// Front-to-back compositing of 16x16 tiles, one workgroup per tile; each invocation composites
// PIXELS pixels of the tile (1 on GPUs; more on CPU adapters such as lavapipe, where every
// read from workgroup or storage memory costs a per-lane loop and is better amortised), and
// splats are staged through workgroup memory in batches of 256. Same rules and arithmetic as
// sync4d-raster's f32 path: alpha = min(opacity exp(-sigma), alpha_max) with the same
// polynomial exp, skipped below 1/255 or when sigma < 0, and a pixel stops (excluding the
// current splat) when its transmittance would fall below t_min. CHANNELS is substituted by
// the host (one pipeline per channel count).

const C: u32 = {{CHANNELS}}u;
// Pixels per invocation (a divisor of 256) and invocations per tile.
const P: u32 = {{PIXELS}}u;
const WG: u32 = 256u / P;
// Splats per forward batch.
const FB: u32 = 256u;

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
    // Trips of the loop check (loop_check.wgsl) (2; a uniform, so that no compiler unrolls it).
    canary: u32,
    // This dispatch's window of each tile's list, in list positions [win_lo, win_hi): long
    // lists are composited over several dispatches (llvmpipe caps a shader's loop trips), with
    // the per-pixel running state kept in the outputs between them.
    win_lo: u32,
    win_hi: u32,
    // Bit 0: the first window walked (fresh state, else resumed); bit 1: the last (final
    // outputs, else running state for the next window).
    window: u32,
}

@group(0) @binding(0) var<uniform> F: BlendParams;
// Per splat: mean x, mean y, conic a, b, c, opacity, depth, 0.
@group(0) @binding(1) var<storage, read> splats: array<f32>;
// Splat indices grouped by tile, front to back (bin.wgsl's scatter).
@group(0) @binding(3) var<storage, read> ids: array<u32>;
@group(0) @binding(4) var<storage, read> tile_offsets: array<u32>;
// N*C features, then C background values.
@group(0) @binding(5) var<storage, read> features: array<f32>;
// H*W*C features, then H*W alpha, then H*W depth.
@group(0) @binding(6) var<storage, read_write> image: array<f32>;
// Per pixel: 1 + list index of the last composited splat (0 if none), final transmittance bits.
@group(0) @binding(7) var<storage, read_write> pixel_state: array<u32>;
// evaluated lo/hi, blended lo/hi, then 1 when a kernel's loops were cut short (see
// loop_check.wgsl), then the largest list position + 1 of a pixel's last contributor.
@group(0) @binding(8) var<storage, read_write> counters: array<atomic<u32>>;

// Flag cut loops (loop_check.wgsl) in the counters.
fn check_loops() {
    if !loops_completed(F.canary) {
        atomicStore(&counters[4], 1u);
    }
}

var<workgroup> sh_pos: array<vec4<f32>, FB>;   // mean x, mean y, opacity, depth
var<workgroup> sh_conic: array<vec4<f32>, FB>; // a, b, c, -
var<workgroup> sh_box: array<vec4<f32>, FB>;   // support_box
var<workgroup> sh_index: array<u32, FB>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> stop_flag: u32;
var<workgroup> range_base: u32;
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

// Splat g's mean x, mean y, opacity, depth.
fn splat_pos(g: u32) -> vec4<f32> {
    return vec4<f32>(splats[8u * g], splats[8u * g + 1u], splats[8u * g + 5u], splats[8u * g + 6u]);
}

// Splat g's conic a, b, c (and 0).
fn splat_conic(g: u32) -> vec4<f32> {
    return vec4<f32>(splats[8u * g + 2u], splats[8u * g + 3u], splats[8u * g + 4u], 0.0);
}

// The pixel-centre box [x_lo, x_hi] x [y_lo, y_hi] outside which the splat's alpha is below
// 1/255 (where sigma > ln(255 opacity)), padded so that f32 rounding never culls a pixel the
// alpha test would keep; no culling when the conic is not safely positive definite.
fn support_box(pos: vec4<f32>, con: vec4<f32>) -> vec4<f32> {
    let op = pos.z;
    if !(op * 255.0 >= 1.0) {
        return vec4<f32>(1.0, -1.0, 1.0, -1.0); // alpha < 1/255 everywhere: empty
    }
    let a = con.x;
    let c = con.z;
    let det_lo = a * c - con.y * con.y - 4.8e-7 * (abs(a * c) + con.y * con.y);
    if !(a > 0.0 && c > 0.0 && det_lo > 0.0) {
        return vec4<f32>(-3e38, 3e38, -3e38, 3e38);
    }
    let smax = log(255.0 * op) * 1.01 + 0.01;
    let ex = sqrt(2.0 * smax * c / det_lo) + 0.05;
    let ey = sqrt(2.0 * smax * a / det_lo) + 0.05;
    return vec4<f32>(pos.x - ex, pos.x + ex, pos.y - ey, pos.y + ey);
}

// The compositing thresholds of `F`, read once per invocation and passed to the pixel bodies:
// llvmpipe turns every uniform-buffer read inside a loop into a bounds-checked per-lane gather.
struct Limits {
    alpha_min: f32,
    alpha_max: f32,
    t_min: f32,
}

fn limits() -> Limits {
    return Limits(F.alpha_min, F.alpha_max, F.t_min);
}

// Splat (pos, conic)'s alpha at pixel centre (x, y): min(opacity exp(-sigma), alpha_max), or 0
// where it is not composited (sigma < 0 or alpha < alpha_min).
fn splat_alpha(pos: vec4<f32>, con: vec4<f32>, x: f32, y: f32, lim: Limits) -> f32 {
    let dx = x - pos.x;
    let dy = y - pos.y;
    let sigma = 0.5 * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
    let alpha = min(pos.z * fast_exp(-sigma), lim.alpha_max);
    return select(0.0, alpha, sigma >= 0.0 && alpha >= lim.alpha_min);
}

fn in_box(b: vec4<f32>, x: f32, y: f32) -> bool {
    return x >= b.x && x <= b.y && y >= b.z && y <= b.w;
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

// Pixel j of invocation `lid`: tile-local (x, y).
fn tile_pixel(lid: u32, j: u32) -> vec2<u32> {
    let i = lid + j * WG;
    return vec2<u32>(i % 16u, i / 16u);
}

const FIRST_WINDOW: u32 = 1u;
const LAST_WINDOW: u32 = 2u;

// A pixel's forward compositing state: accumulated features and depth, transmittance (negated
// once the pixel stopped; t > 0 while it composites), and the list position + 1 of the last
// composited splat (0 if none).
struct PixelForward {
    acc: array<f32, C>,
    t: f32,
    depth: f32,
    last: u32,
}

// Pixel q's state at the start of this window: fresh in the first (stopped, t = -1, outside
// the image), else as the previous window stored it.
fn load_pixel(q: vec2<u32>) -> PixelForward {
    var r: PixelForward;
    let outside = q.x >= F.width || q.y >= F.height;
    r.t = select(1.0, -1.0, outside);
    if outside || (F.window & FIRST_WINDOW) != 0u {
        return r;
    }
    let npix = F.width * F.height;
    let pix = q.y * F.width + q.x;
    for (var c = 0u; c < C; c++) { // unroll: channels
        r.acc[c] = image[pix * C + c];
    }
    r.depth = image[npix * (C + 1u) + pix];
    r.last = pixel_state[2u * pix];
    r.t = bitcast<f32>(pixel_state[2u * pix + 1u]);
    return r;
}

// The forward state of invocation `lid`'s P pixels of tile `wid` (`PixelForward` each, as
// arrays indexed by pixel), their centres, and how many are not done.
struct PixelsForward {
    t: array<f32, P>,
    acc: array<f32, P * C>,
    depth: array<f32, P>,
    last: array<u32, P>,
    fx: array<f32, P>,
    fy: array<f32, P>,
    live: u32,
}

fn load_pixels(lid: u32, wid: vec3<u32>) -> PixelsForward {
    var s: PixelsForward;
    for (var j = 0u; j < P; j++) { // unroll: pixels
        let q = vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j);
        let r = load_pixel(q);
        s.t[j] = r.t;
        for (var c = 0u; c < C; c++) { // unroll: channels
            s.acc[j * C + c] = r.acc[c];
        }
        s.depth[j] = r.depth;
        s.last[j] = r.last;
        s.live += select(0u, 1u, r.t > 0.0);
        s.fx[j] = f32(q.x) + 0.5;
        s.fy[j] = f32(q.y) + 0.5;
    }
    return s;
}

// Composite splat (pos, conic, features f; list position + 1 `rank`) over pixel j of `px` where
// `inside` (the pixel still composites there): alpha as splat_alpha, the pixel stopping (the
// splat excluded) when its transmittance would fall below t_min. Returns (blended, stopped).
fn blend_pixel(px: ptr<function, PixelsForward>, j: u32, pos: vec4<f32>, con: vec4<f32>,
               f: array<f32, C>, rank: u32, lim: Limits, inside: bool) -> vec2<bool> {
    let t = (*px).t[j];
    let alpha = splat_alpha(pos, con, (*px).fx[j], (*px).fy[j], lim);
    let ok = inside && alpha > 0.0;
    let next_t = t * (1.0 - alpha);
    let stop = ok && next_t < lim.t_min;
    let take = ok && !stop;
    let w = select(0.0, alpha * t, take);
    for (var c = 0u; c < C; c++) { // unroll: channels
        (*px).acc[j * C + c] += f[c] * w;
    }
    (*px).depth[j] += pos.w * w;
    (*px).t[j] = select(select(t, next_t, take), -t, stop);
    (*px).last[j] = select((*px).last[j], rank, take);
    return vec2<bool>(take, stop);
}

// Write pixel q's state (`t` signed as in `PixelForward`): in the last window the composited
// features (accumulated `a` plus the background through the final transmittance |t|), alpha,
// depth and the backward's state (last contributor, |t|); before, the running sums and t.
fn store_pixel(q: vec2<u32>, a: array<f32, C>, t_signed: f32, depth: f32, last: u32) {
    if q.x >= F.width || q.y >= F.height {
        return;
    }
    let npix = F.width * F.height;
    let pix = q.y * F.width + q.x;
    let final_window = (F.window & LAST_WINDOW) != 0u;
    let t = abs(t_signed);
    for (var c = 0u; c < C; c++) { // unroll: channels
        image[pix * C + c] = a[c] + select(0.0, t * features[F.n * C + c], final_window);
    }
    if final_window {
        image[npix * C + pix] = 1.0 - t;
    }
    image[npix * (C + 1u) + pix] = depth;
    pixel_state[2u * pix] = last;
    pixel_state[2u * pix + 1u] = bitcast<u32>(select(t_signed, t, final_window));
}

// Store invocation `lid`'s pixels of tile `wid` and record their deepest last contributor.
// In a middle window, pixels that had all stopped before it are not stored again: `px.live`
// counts the pixels that were compositing when they were loaded, and nothing changed since.
fn store_pixels(lid: u32, wid: vec3<u32>, px: PixelsForward) {
    let unchanged = px.live == 0u && (F.window & LAST_WINDOW) == 0u;
    var deepest = 0u;
    for (var j = 0u; j < P; j++) { // unroll: pixels
        if !unchanged {
            var a: array<f32, C>;
            for (var c = 0u; c < C; c++) { // unroll: channels
                a[c] = px.acc[j * C + c];
            }
            let q = vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j);
            store_pixel(q, a, px.t[j], px.depth[j], px.last[j]);
        }
        deepest = max(deepest, px.last[j]);
    }
    atomicMax(&counters[5], deepest);
}

// This tile's list start and this window's [start, end) in `ids`, shared with the workgroup.
fn window_range(tile: u32) {
    let base = tile_offsets[tile];
    let len = tile_offsets[tile + 1u] - base;
    range_base = base;
    range_start = base + min(F.win_lo, len);
    range_end = base + min(F.win_hi, len);
}

@compute @workgroup_size(WG)
fn blend_forward(@builtin(local_invocation_index) lid: u32,
                 @builtin(workgroup_id) wid: vec3<u32>) {
    let lim = limits();
    let tile = wid.y * F.tiles_x + wid.x;
    if lid == 0u {
        atomicStore(&done_count, 0u);
        atomicStore(&wg_evaluated, 0u);
        atomicStore(&wg_blended, 0u);
        window_range(tile);
    }
    let start = workgroupUniformLoad(&range_start);
    let end = workgroupUniformLoad(&range_end);
    let base = workgroupUniformLoad(&range_base);
    // Nothing of this tile's list in a middle window: its state stays where it is.
    if start == end && (F.window & (FIRST_WINDOW | LAST_WINDOW)) == 0u {
        return;
    }
    var px = load_pixels(lid, wid);
    var live = px.live;
    var evaluated = 0u;
    var blended = 0u;
    if live == 0u {
        atomicAdd(&done_count, 1u);
    }
    var f: array<f32, C>;
    for (var batch = start; batch < end; batch += FB) {
        workgroupBarrier();
        if lid == 0u {
            stop_flag = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&stop_flag) == WG {
            break;
        }
        for (var i = lid; i < FB && batch + i < end; i += WG) {
            let g = ids[batch + i];
            sh_pos[i] = splat_pos(g);
            sh_conic[i] = splat_conic(g);
            sh_index[i] = g;
            sh_box[i] = support_box(sh_pos[i], sh_conic[i]);
        }
        workgroupBarrier();
        let count = min(FB, end - batch);
        for (var k = 0u; k < count && live > 0u; k++) {
            let pos = sh_pos[k];
            let con = sh_conic[k];
            let bx = sh_box[k];
            let g = sh_index[k];
            for (var c = 0u; c < C; c++) { // unroll: channels
                f[c] = features[g * C + c];
            }
            let rank = batch - base + k + 1u;
            // Per pixel: skip it when done or outside the splat's support box (neighbouring
            // pixels mostly agree, so SIMD lanes skip together); the rest is branch-free.
            for (var j = 0u; j < P; j++) { // unroll: pixels
                if px.t[j] < 0.0 || !in_box(bx, px.fx[j], px.fy[j]) {
                    continue;
                }
                let r = blend_pixel(&px, j, pos, con, f, rank, lim, true);
                evaluated += 1u;
                blended += select(0u, 1u, r.x);
                live -= select(0u, 1u, r.y);
            }
            if live == 0u {
                atomicAdd(&done_count, 1u);
            }
        }
    }
    atomicAdd(&wg_evaluated, evaluated);
    atomicAdd(&wg_blended, blended);
    store_pixels(lid, wid, px);
    check_loops();
    workgroupBarrier();
    if lid == 0u {
        add_wide(0u, atomicLoad(&wg_evaluated));
        add_wide(2u, atomicLoad(&wg_blended));
    }
}

// <rows>
// Forward for CPU adapters (llvmpipe runs every branch of a divergent `if` under a lane mask, so
// skipping a pixel outside a splat's support saves nothing there; only loop trip counts skip
// work). The invocation's P pixels form NB blocks of RB tile rows (or of one half of them);
// each batch of 32 splats is staged with one bit per (block, splat) set where the splat's
// alpha-support ellipse reaches the block (support_meets), and the batch is walked (see NW
// below) block by block or by the whole tile, each walk visiting only its set bits, in order,
// each lane until all of its pixels there are done. lavapipe's default is one block (RB = 16):
// many of a tile's list entries (binned by their 3-sigma extent) have an alpha support that
// misses the tile's pixel centres altogether, and every visit reloads the splat, per lane.
const RB: u32 = {{ROWS}}u;
// Column groups per block row: 1 (blocks span the tile's width) or 2 (a block is RB rows of
// one half of the tile, the pixels of one SIMD lane group; needs P = 32).
const HALVES: u32 = {{HALVES}}u;
const NB: u32 = HALVES * (16u / RB);
const JB: u32 = P / NB;
var<workgroup> hit: array<array<atomic<u32>, NB>, 2>;
// A batch of 32 splats staged for the row-block kernels: mean x, mean y, opacity, depth; conic
// a, b, c and the splat index (bits); the C features in CV vectors of 4 (read with one
// per-lane loop each on llvmpipe, where every feature read from storage took one).
const CV: u32 = (C + 3u) / 4u;
var<workgroup> rows_pos: array<vec4<f32>, 32>;
var<workgroup> rows_conic: array<vec4<f32>, 32>;
var<workgroup> rows_features: array<vec4<f32>, 32 * CV>;

// Stage splat g in slot i of the row-block batch; returns its (pos, conic) (see splat_pos,
// splat_conic).
fn stage_rows_splat(i: u32, g: u32) -> array<vec4<f32>, 2> {
    let pos = splat_pos(g);
    let con = splat_conic(g);
    rows_pos[i] = pos;
    rows_conic[i] = vec4<f32>(con.xyz, bitcast<f32>(g));
    var fs: array<f32, 4 * CV>;
    for (var c = 0u; c < C; c++) { // unroll: channels
        fs[c] = features[g * C + c];
    }
    for (var v = 0u; v < CV; v++) { // unroll: feature vectors
        rows_features[i * CV + v] = vec4<f32>(fs[4u * v], fs[4u * v + 1u], fs[4u * v + 2u],
                                              fs[4u * v + 3u]);
    }
    return array<vec4<f32>, 2>(pos, con);
}

// The features of the splat staged in slot k.
fn staged_features(k: u32) -> array<f32, C> {
    var fv: array<vec4<f32>, CV>;
    for (var v = 0u; v < CV; v++) { // unroll: feature vectors
        fv[v] = rows_features[k * CV + v];
    }
    var f: array<f32, C>;
    for (var c = 0u; c < C; c++) { // unroll: channels
        f[c] = fv[c / 4u][c % 4u];
    }
    return f;
}

// The block holding pixel j of the invocation's P pixels (see tile_pixel).
fn block_of(j: u32) -> u32 {
    if HALVES == 1u {
        return j / JB;
    }
    return ((j / 2u) / RB) * 2u + j % 2u;
}

// A batch is composited by walks: with several blocks, either each block walks the splats that
// reach it, or the whole tile walks the splats that reach any block (one pixel-body per
// pixel group per visit either way, but each visit also reloads the splat), whichever the
// cost estimate favours for that batch. Walk w < NB is block w's, walk NB the whole tile's.
const NW: u32 = {{WALKS}}u;
// A visit's cost besides its pixel bodies (staged splat reads, loop bookkeeping), in pixel
// bodies (one pixel of every invocation: a SIMD group of pixels on llvmpipe).
const VISIT_COST: u32 = 2u;

// Whether walk w composites pixel j.
fn walk_has(w: u32, j: u32) -> bool {
    return w == NB || block_of(j) == w;
}

// How a batch with per-block masks `masks` is walked: the masks, their union (the whole
// tile's), and whether the blocks walk their own splats (else the whole tile walks them all),
// by the estimated cost (each loop taking at least one trip, with JB or P pixels a visit).
struct Walks {
    masks: array<u32, NB>,
    all: u32,
    by_blocks: bool,
}

fn plan_walks(masks: array<u32, NB>) -> Walks {
    var all = 0u;
    var block_trips = 0u;
    for (var b = 0u; b < NB; b++) { // unroll: blocks
        all |= masks[b];
        block_trips += max(countOneBits(masks[b]), 1u);
    }
    let tile_trips = max(countOneBits(all), 1u);
    let by_blocks = NB > 1u && block_trips * (VISIT_COST + JB) < tile_trips * (VISIT_COST + P);
    return Walks(masks, all, by_blocks);
}

// The bits walk w of plan `p` visits.
fn walk_bits(w: u32, p: Walks) -> u32 {
    if NB == 1u {
        return p.all;
    }
    if w == NB {
        return select(p.all, 0u, p.by_blocks);
    }
    return select(0u, p.masks[min(w, NB - 1u)], p.by_blocks);
}

// sigma of splat conic (a, b, c) at offset (dx, dy), less a bound on its f32 rounding error.
fn sigma_low(a: f32, b: f32, c: f32, dx: f32, dy: f32) -> f32 {
    let qa = 0.5 * a * dx * dx;
    let qb = b * dx * dy;
    let qc = 0.5 * c * dy * dy;
    return qa + qb + qc - 1e-5 * (qa + abs(qb) + qc);
}

// Whether splat (pos, conic)'s alpha support, the ellipse sigma <= ln(255 opacity) outside
// which alpha < 1/255, may reach a point of the rectangle [xl, xh] x [yl, yh]: the least
// sigma over the rectangle (on its edges when the centre lies outside it) against a bound
// padded like support_box's (by 1 % and 0.02), with the rounding of sigma allowed for. False
// when the opacity is below 1/255, true when the conic is not safely positive definite.
fn support_meets(pos: vec4<f32>, con: vec4<f32>, xl: f32, xh: f32, yl: f32, yh: f32) -> bool {
    let op = pos.z;
    let a = con.x;
    let b = con.y;
    let c = con.z;
    let det_lo = a * c - b * b - 4.8e-7 * (abs(a * c) + b * b);
    let definite = a > 0.0 && c > 0.0 && det_lo > 0.0;
    let smax = log(255.0 * op) * 1.01 + 0.02;
    let dxl = xl - pos.x;
    let dxh = xh - pos.x;
    let dyl = yl - pos.y;
    let dyh = yh - pos.y;
    let inside = dxl <= 0.0 && dxh >= 0.0 && dyl <= 0.0 && dyh >= 0.0;
    // On a vertical edge (dx fixed) sigma is least at dy = -b dx / c, clamped to the edge;
    // on a horizontal edge at dx = -b dy / a.
    let ic = 1.0 / c;
    let ia = 1.0 / a;
    let s1 = sigma_low(a, b, c, dxl, clamp(-b * dxl * ic, dyl, dyh));
    let s2 = sigma_low(a, b, c, dxh, clamp(-b * dxh * ic, dyl, dyh));
    let s3 = sigma_low(a, b, c, clamp(-b * dyl * ia, dxl, dxh), dyl);
    let s4 = sigma_low(a, b, c, clamp(-b * dyh * ia, dxl, dxh), dyh);
    let near = inside || min(min(s1, s2), min(s3, s4)) <= smax;
    return op * 255.0 >= 1.0 && (!definite || near);
}

// 1 << bit in each block of the tile whose top-left pixel corner is (x0, y0) that splat
// (pos, conic)'s alpha support may reach (support_meets on the block's pixel centres,
// widened by 0.01 px); 0 elsewhere.
fn block_bits(pos: vec4<f32>, con: vec4<f32>, x0: f32, y0: f32, bit: u32) -> array<u32, NB> {
    var m: array<u32, NB>;
    for (var b = 0u; b < NB; b++) { // unroll: blocks
        let width = 16.0 / f32(HALVES);
        let xl = x0 + f32(b % HALVES) * width + 0.49;
        let yl = y0 + f32(b / HALVES) * f32(RB) + 0.49;
        if support_meets(pos, con, xl, xl + width - 0.98, yl, yl + f32(RB) - 0.98) {
            m[b] = 1u << bit;
        }
    }
    return m;
}

@compute @workgroup_size(WG)
fn blend_forward_rows(@builtin(local_invocation_index) lid: u32,
                      @builtin(workgroup_id) wid: vec3<u32>) {
    let lim = limits();
    let tile = wid.y * F.tiles_x + wid.x;
    if lid == 0u {
        atomicStore(&done_count, 0u);
        atomicStore(&wg_evaluated, 0u);
        atomicStore(&wg_blended, 0u);
        window_range(tile);
        for (var b = 0u; b < NB; b++) {
            atomicStore(&hit[0][b], 0u);
            atomicStore(&hit[1][b], 0u);
        }
    }
    let start = workgroupUniformLoad(&range_start);
    let end = workgroupUniformLoad(&range_end);
    let base = workgroupUniformLoad(&range_base);
    // Nothing of this tile's list in a middle window: its state stays where it is.
    if start == end && (F.window & (FIRST_WINDOW | LAST_WINDOW)) == 0u {
        return;
    }
    let x0 = f32(wid.x * 16u);
    let y0 = f32(wid.y * 16u);
    var px = load_pixels(lid, wid);
    var live = px.live;
    var evaluated = 0u;
    var blended = 0u;
    var counted = live == 0u;
    if counted {
        atomicAdd(&done_count, 1u);
    }
    var parity = 0u;
    for (var batch = start; batch < end; batch += 32u) {
        workgroupBarrier();
        if lid == 0u {
            stop_flag = atomicLoad(&done_count);
        }
        if workgroupUniformLoad(&stop_flag) == WG {
            break;
        }
        var mine: array<u32, NB>;
        for (var i = lid; i < 32u && batch + i < end; i += WG) {
            let sp = stage_rows_splat(i, ids[batch + i]);
            let m = block_bits(sp[0], sp[1], x0, y0, i);
            for (var b = 0u; b < NB; b++) { // unroll: blocks
                mine[b] |= m[b];
            }
        }
        for (var b = 0u; b < NB; b++) { // unroll: blocks
            if mine[b] != 0u {
                atomicOr(&hit[parity][b], mine[b]);
            }
        }
        workgroupBarrier();
        var masks: array<u32, NB>;
        for (var b = 0u; b < NB; b++) { // unroll: blocks
            masks[b] = atomicLoad(&hit[parity][b]);
            // Reset the other parity's masks for the next batch (read before this batch's barrier).
            atomicStore(&hit[1u - parity][b], 0u);
        }
        let plan = plan_walks(masks);
        for (var w = 0u; w < NW; w++) { // unroll: walks
            var bits = walk_bits(w, plan);
            var wdone = true;
            for (var j = 0u; j < P; j++) { // unroll: pixels
                if walk_has(w, j) {
                    wdone = wdone && px.t[j] < 0.0;
                }
            }
            if wdone {
                bits = 0u;
            }
            // llvmpipe tests a loop's exit at its end only: the last trip runs masked (an exit
            // test at the end instead measured ~20 % slower).
            loop {
                if bits == 0u {
                    break;
                }
                let k = firstTrailingBit(bits);
                bits &= bits - 1u;
                let pos = rows_pos[k];
                let con = rows_conic[k];
                let f = staged_features(k);
                let rank = batch - base + k + 1u;
                var all_done = true;
                for (var j = 0u; j < P; j++) { // unroll: pixels
                    if walk_has(w, j) {
                        // Outside the support ellipse alpha is below 1/255: no per-pixel test.
                        let inside = px.t[j] > 0.0;
                        let r = blend_pixel(&px, j, pos, con, f, rank, lim, inside);
                        evaluated += select(0u, 1u, inside);
                        blended += select(0u, 1u, r.x);
                        live -= select(0u, 1u, r.y);
                        all_done = all_done && px.t[j] < 0.0;
                    }
                }
                if all_done {
                    bits = 0u;
                }
            }
        }
        if live == 0u && !counted {
            atomicAdd(&done_count, 1u);
            counted = true;
        }
        parity = 1u - parity;
    }
    atomicAdd(&wg_evaluated, evaluated);
    atomicAdd(&wg_blended, blended);
    store_pixels(lid, wid, px);
    check_loops();
    workgroupBarrier();
    if lid == 0u {
        add_wide(0u, atomicLoad(&wg_evaluated));
        add_wide(2u, atomicLoad(&wg_blended));
    }
}
// </rows>

// ---------------------------------------------------------------------------------------------
// Backward: each tile walks its list back to front from the furthest last contributor; every
// pixel recovers its transmittance by division (T_i = T_{i+1} / (1 - alpha_i)) and keeps the
// running sum of what lies behind, exactly as sync4d-raster's f32 backward. A batch of splats'
// gradients is summed over the tile's pixels in workgroup memory, then added to the global
// per-splat gradients (float atomic adds, or compare-and-swap, so the summation order, and the
// last bits, depend on scheduling).

// Per splat: mean x, mean y, conic a, b, c, opacity, C features, depth.
const STRIDE: u32 = 7u + C;
// Splats per backward batch (the workgroup accumulators hold BATCH * STRIDE floats).
const BATCH: u32 = {{BATCH}}u;

// dL/d image: H*W*C features, then H*W alpha, then H*W depth.
@group(0) @binding(9) var<storage, read> v_image: array<f32>;
// Per splat STRIDE gradient sums (f32; u32 bits without float atomics, see global_add).
@group(0) @binding(10) var<storage, read_write> grads: array<atomic<{{GRAD_ATOMIC}}>>;
// Per pixel between backward windows: the transmittance and running sum (`PixelGrad` t, vr).
@group(0) @binding(11) var<storage, read_write> walk_state: array<f32>;

// Backward reduction: per-invocation partial sums in workgroup memory, summed in a fixed order
// (CPU adapters: few invocations, many pixels each), or compare-and-swap float adds into
// per-splat accumulators (GPUs: one pixel per invocation).
const PARTIALS: bool = {{PARTIALS}};
var<workgroup> acc_grad: array<atomic<u32>, {{ACC}}>;
var<workgroup> partial: array<f32, {{PARTIAL_LEN}}>;
var<workgroup> q_last: array<u32, WG>;
var<workgroup> sh_b_pos: array<vec4<f32>, BATCH>;   // mean x, mean y, opacity, depth
var<workgroup> sh_b_conic: array<vec4<f32>, BATCH>; // a, b, c, -
var<workgroup> sh_b_box: array<vec4<f32>, BATCH>;   // support_box
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

// Add v to gradient sum i: a float atomic add where the device has them (BlendLayout's
// float_atomics), else a compare-and-swap loop on the bits.
// <float-atomics>
fn global_add(i: u32, v: f32) {
    atomicAdd(&grads[i], v);
}
// </float-atomics>
// <no-float-atomics>
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
// </no-float-atomics>

// What the backward needs of pixel q: its last contributor from the forward, dL/d features
// (`vc`) and dL/d depth, `tail` = T_final (dL/dfeatures . background - dL/dalpha), the gradient
// of what lies behind every splat, and the walk's state: transmittance `t` (T_final in the first
// window) and running sum `vr` of what lies behind (0 in the first window). Outside the image:
// t = 1, rest 0.
struct PixelGrad {
    last: u32,
    t: f32,
    vr: f32,
    v_depth: f32,
    tail: f32,
    vc: array<f32, C>,
}

fn load_pixel_grad(q: vec2<u32>) -> PixelGrad {
    var r: PixelGrad;
    r.t = 1.0;
    if q.x >= F.width || q.y >= F.height {
        return r;
    }
    let npix = F.width * F.height;
    let pix = q.y * F.width + q.x;
    r.last = pixel_state[2u * pix];
    r.t = bitcast<f32>(pixel_state[2u * pix + 1u]);
    var vbg = 0.0;
    for (var c = 0u; c < C; c++) { // unroll: channels
        r.vc[c] = v_image[pix * C + c];
        vbg += r.vc[c] * features[F.n * C + c];
    }
    r.v_depth = v_image[npix * (C + 1u) + pix];
    r.tail = r.t * (vbg - v_image[npix * C + pix]);
    if (F.window & FIRST_WINDOW) == 0u {
        r.t = walk_state[2u * pix];
        r.vr = walk_state[2u * pix + 1u];
    }
    return r;
}

// Keep pixel q's walk state (transmittance, running sum) for the next window, if any.
fn save_walk(q: vec2<u32>, t: f32, vr: f32) {
    if q.x >= F.width || q.y >= F.height || (F.window & LAST_WINDOW) != 0u {
        return;
    }
    let pix = q.y * F.width + q.x;
    walk_state[2u * pix] = t;
    walk_state[2u * pix + 1u] = vr;
}

// The backward walk's next batch below list position `end` (at most `batch` entries, not below
// the window's start).
fn batch_start(end: u32, batch: u32) -> u32 {
    return select(end - batch, F.win_lo, end < F.win_lo + batch);
}

// One pixel's step of the backward walk for splat (pos, conic, features f): given the
// transmittance t in front of the splat's successor, the running sum vr of what lies behind,
// `tail`, dL/d features v and dL/d depth, the transmittance in front of this splat, the new
// running sum and whether it was composited (and `visible`); adds the pixel's share of the
// splat's STRIDE gradients to `gs`. Clamped alphas pass no gradient to the opacity or conic.
struct PixelBackward {
    t: f32,
    vr: f32,
    ok: bool,
}

fn pixel_backward(pos: vec4<f32>, con: vec4<f32>, f: array<f32, C>, x: f32, y: f32, t: f32,
                  vr: f32, tail: f32, v: array<f32, C>, v_depth: f32, visible: bool,
                  lim: Limits, gs: ptr<function, array<f32, STRIDE>>) -> PixelBackward {
    var r: PixelBackward;
    var vf = v_depth * pos.w;
    for (var c = 0u; c < C; c++) { // unroll: channels
        vf += v[c] * f[c];
    }
    let dx = x - pos.x;
    let dy = y - pos.y;
    let sigma = 0.5 * (con.x * dx * dx + con.z * dy * dy) + con.y * dx * dy;
    let vis = fast_exp(-sigma);
    let raw = pos.z * vis;
    let alpha = min(raw, lim.alpha_max);
    let ok = visible && sigma >= 0.0 && alpha >= lim.alpha_min;
    let one_m = 1.0 - alpha;
    let ti = t / one_m;
    let w = alpha * ti;
    let v_alpha = ti * vf - (vr + tail) / one_m;
    r.ok = ok;
    r.vr = select(vr, vr + w * vf, ok);
    r.t = select(t, ti, ok);
    for (var c = 0u; c < C; c++) { // unroll: channels
        (*gs)[6u + c] += select(0.0, w * v[c], ok);
    }
    (*gs)[6u + C] += select(0.0, w * v_depth, ok);
    let live_grad = ok && raw <= lim.alpha_max;
    let v_sigma = -v_alpha * alpha;
    (*gs)[5] += select(0.0, v_alpha * vis, live_grad);
    (*gs)[2] += select(0.0, 0.5 * v_sigma * dx * dx, live_grad);
    (*gs)[3] += select(0.0, v_sigma * dx * dy, live_grad);
    (*gs)[4] += select(0.0, 0.5 * v_sigma * dy * dy, live_grad);
    (*gs)[0] += select(0.0, -v_sigma * (con.x * dx + con.y * dy), live_grad);
    (*gs)[1] += select(0.0, -v_sigma * (con.z * dy + con.y * dx), live_grad);
    return r;
}

@compute @workgroup_size(WG)
fn blend_backward(@builtin(local_invocation_index) lid: u32,
                  @builtin(workgroup_id) wid: vec3<u32>) {
    let lim = limits();
    let tile = wid.y * F.tiles_x + wid.x;
    if lid == 0u {
        atomicStore(&max_last, 0u);
        range_start = tile_offsets[tile];
    }
    for (var i = lid; i < BATCH * STRIDE; i += WG) {
        atomicStore(&acc_grad[i], 0u);
    }
    workgroupBarrier();
    var t: array<f32, P>;
    var last: array<u32, P>;
    var vc: array<f32, P * C>;
    var v_depth: array<f32, P>;
    var tail: array<f32, P>;
    var vr: array<f32, P>;
    var fx: array<f32, P>;
    var fy: array<f32, P>;
    var my_last = 0u;
    for (var j = 0u; j < P; j++) { // unroll: pixels
        let q = vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j);
        fx[j] = f32(q.x) + 0.5;
        fy[j] = f32(q.y) + 0.5;
        let r = load_pixel_grad(q);
        last[j] = r.last;
        t[j] = r.t;
        v_depth[j] = r.v_depth;
        tail[j] = r.tail;
        vr[j] = r.vr;
        for (var c = 0u; c < C; c++) { // unroll: channels
            vc[j * C + c] = r.vc[c];
        }
        my_last = max(my_last, r.last);
    }
    atomicMax(&max_last, my_last);
    q_last[lid] = my_last;
    workgroupBarrier();
    if lid == 0u {
        max_last_u = atomicLoad(&max_last);
    }
    let start_list = workgroupUniformLoad(&range_start);
    var end = min(workgroupUniformLoad(&max_last_u), F.win_hi);
    var f: array<f32, C>;
    // Per-splat gradient sums over this invocation's pixels: mean x, mean y, conic a, b, c,
    // opacity, C features, depth (the STRIDE layout).
    var gs: array<f32, STRIDE>;
    while end > F.win_lo {
        let start = batch_start(end, BATCH);
        let count = end - start;
        for (var i = lid; i < count; i += WG) {
            let g = ids[start_list + start + i];
            sh_b_pos[i] = splat_pos(g);
            sh_b_conic[i] = splat_conic(g);
            sh_b_index[i] = g;
            sh_b_box[i] = support_box(sh_b_pos[i], sh_b_conic[i]);
        }
        workgroupBarrier();
        for (var jj = i32(count) - 1; jj >= 0; jj--) {
            let k = start + u32(jj);
            if k >= my_last {
                continue;
            }
            let pos = sh_b_pos[jj];
            let con = sh_b_conic[jj];
            let bx = sh_b_box[jj];
            let g = sh_b_index[jj];
            for (var c = 0u; c < C; c++) { // unroll: channels
                f[c] = features[g * C + c];
            }
            for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                gs[s] = 0.0;
            }
            var touched = false;
            for (var j = 0u; j < P; j++) { // unroll: pixels
                if k >= last[j] || !in_box(bx, fx[j], fy[j]) {
                    continue;
                }
                var v: array<f32, C>;
                for (var c = 0u; c < C; c++) { // unroll: channels
                    v[c] = vc[j * C + c];
                }
                let r = pixel_backward(pos, con, f, fx[j], fy[j], t[j], vr[j], tail[j], v,
                                       v_depth[j], true, lim, &gs);
                t[j] = r.t;
                vr[j] = r.vr;
                touched = touched || r.ok;
            }
            if PARTIALS {
                let base = (u32(jj) * WG + lid) * STRIDE;
                for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                    partial[base + s] = gs[s];
                }
            } else if touched {
                let base = u32(jj) * STRIDE;
                for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                    if gs[s] != 0.0 {
                        shared_add(base + s, gs[s]);
                    }
                }
            }
        }
        workgroupBarrier();
        for (var i = lid; i < count * STRIDE; i += WG) {
            var v = 0.0;
            if PARTIALS {
                let jj = i / STRIDE;
                let s = i % STRIDE;
                // Skipped splats (beyond an invocation's last contributor) left no partials.
                for (var q = 0u; q < WG; q++) {
                    v += select(0.0, partial[(jj * WG + q) * STRIDE + s], start + jj < q_last[q]);
                }
            } else {
                v = bitcast<f32>(atomicLoad(&acc_grad[i]));
                atomicStore(&acc_grad[i], 0u);
            }
            if v != 0.0 {
                global_add(sh_b_index[i / STRIDE] * STRIDE + i % STRIDE, v);
            }
        }
        workgroupBarrier();
        end = start;
    }
    for (var j = 0u; j < P; j++) { // unroll: pixels
        save_walk(vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j), t[j], vr[j]);
    }
    check_loops();
}

// <rows>
// Backward for CPU adapters with row blocks (partial sums only): each batch of BATCH splats
// (at most 32) is staged with the same per-block hit bits as the forward; each block walks its
// set bits back to front, skipping splats at or behind the last contributor of all of the
// invocation's pixels in the block, and sums each visited splat's gradients over the blocks in
// the invocation's partial slot. The sums over invocations run in a fixed order over exactly
// the visited slots.
var<workgroup> b_hit: array<array<atomic<u32>, NB>, 2>;
// Per invocation: bit i set when it visited splat i of the batch in any block.
var<workgroup> q_visited: array<u32, WG>;
// Sum each visited splat's gradients over the workgroup with subgroup additions (the
// workgroup is one subgroup) instead of partials in workgroup memory.
const SUBGROUP_SUMS: bool = {{SUBGROUP_SUMS}};
// Spans of WG gradients in a splat's STRIDE (ceil(STRIDE / WG)).
const SPANS: u32 = {{SPANS}}u;
// <subgroups>
// Sum and maximum over the workgroup's invocations (one subgroup, all of it active: the walks
// are uniform). The sum adds the lanes in order through broadcasts from constant lanes, which
// llvmpipe compiles to register extracts, where subgroupAdd is a per-lane loop (backward
// compositing ~7 % faster with small splats); llvmpipe's subgroupAdd adds in the same order.
fn lanes_sum(v: f32) -> f32 {
    var s = 0.0;
    for (var l = 0u; l < WG; l++) { // unroll: lanes
        s += subgroupBroadcast(v, l);
    }
    return s;
}
fn lanes_max(v: u32) -> u32 {
    return subgroupMax(v);
}
// </subgroups>
// <no-subgroups>
// Without subgroup sums (never called then): the invocation's own value.
fn lanes_sum(v: f32) -> f32 {
    return v;
}
fn lanes_max(v: u32) -> u32 {
    return v;
}
// </no-subgroups>

@compute @workgroup_size(WG)
fn blend_backward_rows(@builtin(local_invocation_index) lid: u32,
                       @builtin(workgroup_id) wid: vec3<u32>) {
    let lim = limits();
    let tile = wid.y * F.tiles_x + wid.x;
    if lid == 0u {
        atomicStore(&max_last, 0u);
        range_start = tile_offsets[tile];
        for (var b = 0u; b < NB; b++) {
            atomicStore(&b_hit[0][b], 0u);
            atomicStore(&b_hit[1][b], 0u);
        }
    }
    workgroupBarrier();
    let x0 = f32(wid.x * 16u);
    let y0 = f32(wid.y * 16u);
    var t: array<f32, P>;
    var last: array<u32, P>;
    var vc: array<f32, P * C>;
    var v_depth: array<f32, P>;
    var tail: array<f32, P>;
    var vr: array<f32, P>;
    var fx: array<f32, P>;
    var fy: array<f32, P>;
    var my_last = 0u;
    for (var j = 0u; j < P; j++) { // unroll: pixels
        let q = vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j);
        fx[j] = f32(q.x) + 0.5;
        fy[j] = f32(q.y) + 0.5;
        let r = load_pixel_grad(q);
        last[j] = r.last;
        t[j] = r.t;
        v_depth[j] = r.v_depth;
        tail[j] = r.tail;
        vr[j] = r.vr;
        for (var c = 0u; c < C; c++) { // unroll: channels
            vc[j * C + c] = r.vc[c];
        }
        my_last = max(my_last, r.last);
    }
    // The last contributor over this invocation's pixels of each block.
    var block_last: array<u32, NB>;
    for (var j = 0u; j < P; j++) { // unroll: pixels
        block_last[block_of(j)] = max(block_last[block_of(j)], last[j]);
    }
    atomicMax(&max_last, my_last);
    workgroupBarrier();
    if lid == 0u {
        max_last_u = atomicLoad(&max_last);
    }
    let start_list = workgroupUniformLoad(&range_start);
    var end = min(workgroupUniformLoad(&max_last_u), F.win_hi);
    var gs: array<f32, STRIDE>;
    var parity = 0u;
    while end > F.win_lo {
        let start = batch_start(end, BATCH);
        let count = end - start;
        var mine: array<u32, NB>;
        var visited = 0u;
        for (var i = lid; i < count; i += WG) {
            let sp = stage_rows_splat(i, ids[start_list + start + i]);
            let m = block_bits(sp[0], sp[1], x0, y0, i);
            for (var b = 0u; b < NB; b++) { // unroll: blocks
                mine[b] |= m[b];
            }
        }
        for (var b = 0u; b < NB; b++) { // unroll: blocks
            if mine[b] != 0u {
                atomicOr(&b_hit[parity][b], mine[b]);
            }
        }
        workgroupBarrier();
        var masks: array<u32, NB>;
        for (var b = 0u; b < NB; b++) { // unroll: blocks
            // Only splats before this block's last contributor (list index < block_last); with
            // subgroup sums, every invocation walks the same splats (the workgroup's furthest).
            let bl = lanes_max(block_last[b]);
            let keep = select(0u, bl - start, bl > start);
            masks[b] = atomicLoad(&b_hit[parity][b]) &
                select(0xffffffffu, (1u << keep) - 1u, keep < 32u);
        }
        // Walks as in blend_forward_rows: every pixel still sees the splats back to front.
        let plan = plan_walks(masks);
        for (var w = 0u; w < NW; w++) { // unroll: walks
            var bits = walk_bits(w, plan);
            loop {
                if bits == 0u {
                    break;
                }
                let jj = firstLeadingBit(bits);
                bits &= ~(1u << jj);
                let k = start + jj;
                let pos = rows_pos[jj];
                let con = rows_conic[jj];
                let g = bitcast<u32>(con.w);
                let f = staged_features(jj);
                for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                    gs[s] = 0.0;
                }
                for (var j = 0u; j < P; j++) { // unroll: pixels
                    if walk_has(w, j) {
                        var v: array<f32, C>;
                        for (var c = 0u; c < C; c++) { // unroll: channels
                            v[c] = vc[j * C + c];
                        }
                        // Outside the support ellipse alpha is below 1/255: no per-pixel test.
                        let visible = k < last[j];
                        let r = pixel_backward(pos, con, f, fx[j], fy[j], t[j], vr[j], tail[j],
                                               v, v_depth[j], visible, lim, &gs);
                        t[j] = r.t;
                        vr[j] = r.vr;
                    }
                }
                if SUBGROUP_SUMS {
                    // The workgroup's sums; invocation i adds gradients i, i + WG, ...
                    var sums: array<f32, STRIDE>;
                    for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                        sums[s] = lanes_sum(gs[s]);
                    }
                    for (var h = 0u; h < SPANS; h++) { // unroll: spans
                        let s0 = h * WG;
                        var v = 0.0;
                        for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                            v = select(v, sums[s], s == s0 + lid);
                        }
                        if v != 0.0 {
                            global_add(g * STRIDE + s0 + lid, v);
                        }
                    }
                } else {
                    // Sum over this invocation's blocks in its partial slot: stored on the
                    // first visit of the splat, added on later ones.
                    let base = (jj * WG + lid) * STRIDE;
                    let again = (visited & (1u << jj)) != 0u;
                    visited |= 1u << jj;
                    for (var s = 0u; s < STRIDE; s++) { // unroll: stride
                        partial[base + s] = gs[s] + select(0.0, partial[base + s], again);
                    }
                }
            }
        }
        q_visited[lid] = visited;
        workgroupBarrier();
        for (var i = lid; i < count * STRIDE && !SUBGROUP_SUMS; i += WG) {
            let jj = i / STRIDE;
            let s = i % STRIDE;
            var v = 0.0;
            for (var q = 0u; q < WG; q++) {
                let seen = (q_visited[q] & (1u << jj)) != 0u;
                v += select(0.0, partial[(jj * WG + q) * STRIDE + s], seen);
            }
            if v != 0.0 {
                global_add(bitcast<u32>(rows_conic[jj].w) * STRIDE + s, v);
            }
        }
        for (var b = 0u; b < NB; b++) { // unroll: blocks
            atomicStore(&b_hit[1u - parity][b], 0u);
        }
        workgroupBarrier();
        parity = 1u - parity;
        end = start;
    }
    for (var j = 0u; j < P; j++) { // unroll: pixels
        save_walk(vec2<u32>(wid.x * 16u, wid.y * 16u) + tile_pixel(lid, j), t[j], vr[j]);
    }
    check_loops();
}
// </rows>
