// Projection of 3D Gaussians to screen-space splats (EWA), one invocation per Gaussian.
// The arithmetic follows sync4d-raster's `project_one` step for step, in f32 instead of f64.

struct Params {
    // Rows of the world-to-camera rotation; .w holds the translation entry of that row.
    rot0: vec4<f32>,
    rot1: vec4<f32>,
    rot2: vec4<f32>,
    // fx, fy, cx, cy (pixels).
    intr: vec4<f32>,
    // width, height, eps2d, antialiased (0 or 1).
    size: vec4<f32>,
    // Frustum limits of x/z and y/z: +x, -x, +y, -y.
    lims: vec4<f32>,
    // near, far.
    clip: vec4<f32>,
    // Number of Gaussians.
    count: vec4<u32>,
}

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read> means: array<f32>;
@group(0) @binding(2) var<storage, read> quats: array<f32>;
@group(0) @binding(3) var<storage, read> scales: array<f32>;
@group(0) @binding(4) var<storage, read> opacities: array<f32>;
// Per Gaussian: mean x, mean y, conic a, b, c, opacity, depth, 0.
@group(0) @binding(5) var<storage, read_write> splats: array<f32>;
// Per Gaussian: radius x, radius y (0 = culled).
@group(0) @binding(6) var<storage, read_write> radii: array<i32>;

const RADIUS_SIGMAS: f32 = 3.33;
const QUAT_EPS: f32 = 1e-12;
const DET_EPS: f32 = 1e-10;
const MAX_RADIUS: f32 = 1.0e7;
const COND_MAX: f32 = 1.0e10;
const F32_MAX: f32 = 3.4028235e38;

fn finite(v: f32) -> bool {
    // NaN fails both comparisons; +-inf fails the bound.
    return abs(v) <= F32_MAX;
}

fn quat_to_rotmat(q: vec4<f32>) -> mat3x3<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    // Columns of the row-major matrix of sync4d-raster's `quat_to_rotmat`.
    return mat3x3<f32>(
        vec3<f32>(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y + w * z), 2.0 * (x * z - w * y)),
        vec3<f32>(2.0 * (x * y - w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z + w * x)),
        vec3<f32>(2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)),
    );
}

fn cull(i: u32) {
    for (var k = 0u; k < 8u; k++) {
        splats[8u * i + k] = 0.0;
    }
    radii[2u * i] = 0;
    radii[2u * i + 1u] = 0;
}

// One Gaussian's projection and the intermediates its backward needs.
struct Core {
    // False when the Gaussian has no projection (behind the near plane, not finite, or a
    // blurred 2D covariance too ill-conditioned to invert); the other fields are then unset.
    ok: bool,
    mean_cam: vec3<f32>,
    quat_norm: f32,
    quat_unit: vec4<f32>,
    rot: mat3x3<f32>,
    scale: vec3<f32>,
    // R diag(scale), the world-to-camera rotation, the camera-space covariance.
    m: mat3x3<f32>,
    w: mat3x3<f32>,
    cov_cam: mat3x3<f32>,
    clamped_x: bool,
    clamped_y: bool,
    tx: f32,
    ty: f32,
    // Rows of the perspective Jacobian.
    j0: vec3<f32>,
    j1: vec3<f32>,
    // Un-blurred 2D covariance (xx, xy, yy), its blurred diagonal a, d and determinant.
    cov2d: vec3<f32>,
    a: f32,
    d: f32,
    det: f32,
    compensation: f32,
    conic: vec3<f32>,
    mean2d: vec2<f32>,
}

fn project_core(i: u32) -> Core {
    var c: Core;
    c.ok = false;
    let mean = vec3<f32>(means[3u * i], means[3u * i + 1u], means[3u * i + 2u]);
    let x = dot(P.rot0.xyz, mean) + P.rot0.w;
    let y = dot(P.rot1.xyz, mean) + P.rot1.w;
    let z = dot(P.rot2.xyz, mean) + P.rot2.w;
    c.mean_cam = vec3<f32>(x, y, z);
    if !(z > P.clip.x) || !(finite(x) && finite(y) && finite(z)) {
        return c;
    }
    let q = vec4<f32>(quats[4u * i], quats[4u * i + 1u], quats[4u * i + 2u], quats[4u * i + 3u]);
    c.quat_norm = max(sqrt(dot(q, q)), QUAT_EPS);
    c.quat_unit = q / c.quat_norm;
    c.rot = quat_to_rotmat(c.quat_unit);
    c.scale = vec3<f32>(scales[3u * i], scales[3u * i + 1u], scales[3u * i + 2u]);
    c.m = mat3x3<f32>(c.rot[0] * c.scale.x, c.rot[1] * c.scale.y, c.rot[2] * c.scale.z);
    c.w = transpose(mat3x3<f32>(P.rot0.xyz, P.rot1.xyz, P.rot2.xyz));
    c.cov_cam = c.w * (c.m * transpose(c.m)) * transpose(c.w);
    let ux = x / z;
    let uy = y / z;
    c.clamped_x = ux < -P.lims.y || ux > P.lims.x;
    c.clamped_y = uy < -P.lims.w || uy > P.lims.z;
    c.tx = z * clamp(ux, -P.lims.y, P.lims.x);
    c.ty = z * clamp(uy, -P.lims.w, P.lims.z);
    let rz = 1.0 / z;
    c.j0 = vec3<f32>(P.intr.x * rz, 0.0, -P.intr.x * c.tx * rz * rz);
    c.j1 = vec3<f32>(0.0, P.intr.y * rz, -P.intr.y * c.ty * rz * rz);
    c.cov2d = vec3<f32>(dot(c.j0, c.cov_cam * c.j0), dot(c.j0, c.cov_cam * c.j1),
                        dot(c.j1, c.cov_cam * c.j1));
    c.a = c.cov2d.x + P.size.z;
    c.d = c.cov2d.z + P.size.z;
    let b = c.cov2d.y;
    c.det = max(c.a * c.d - b * b, DET_EPS);
    if (c.a + c.d) * (c.a + c.d) > COND_MAX * c.det {
        return c;
    }
    c.compensation = 1.0;
    if P.size.w > 0.5 {
        let det_orig = c.cov2d.x * c.cov2d.z - b * b;
        c.compensation = sqrt(max(det_orig / c.det, 0.0));
    }
    c.conic = vec3<f32>(c.d / c.det, -b / c.det, c.a / c.det);
    c.mean2d = vec2<f32>(P.intr.x * x / z + P.intr.z, P.intr.y * y / z + P.intr.w);
    c.ok = finite(c.mean2d.x) && finite(c.mean2d.y) && finite(c.conic.x) && finite(c.conic.y)
        && finite(c.conic.z) && finite(c.a) && finite(c.d);
    return c;
}

@compute @workgroup_size(256)
fn project_forward(@builtin(global_invocation_id) gid: vec3<u32>,
                   @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= P.count.x {
        return;
    }
    let c = project_core(i);
    if !c.ok {
        cull(i);
        return;
    }
    let rx = min(ceil(RADIUS_SIGMAS * sqrt(c.a)), MAX_RADIUS);
    let ry = min(ceil(RADIUS_SIGMAS * sqrt(c.d)), MAX_RADIUS);
    let inside = c.mean2d.x + rx > 0.0 && c.mean2d.x - rx < P.size.x && c.mean2d.y + ry > 0.0
        && c.mean2d.y - ry < P.size.y;
    splats[8u * i] = c.mean2d.x;
    splats[8u * i + 1u] = c.mean2d.y;
    splats[8u * i + 2u] = c.conic.x;
    splats[8u * i + 3u] = c.conic.y;
    splats[8u * i + 4u] = c.conic.z;
    splats[8u * i + 5u] = opacities[i] * c.compensation;
    splats[8u * i + 6u] = c.mean_cam.z;
    splats[8u * i + 7u] = 0.0;
    if c.mean_cam.z < P.clip.y && inside {
        radii[2u * i] = i32(rx);
        radii[2u * i + 1u] = i32(ry);
    } else {
        radii[2u * i] = 0;
        radii[2u * i + 1u] = 0;
    }
}

// ---------------------------------------------------------------------------------------------
// Backward: per Gaussian, recompute the forward and apply the chain rule of sync4d-raster's
// `project_one_vjp` (f32). Culled Gaussians get zero gradients.

// Per Gaussian: dL/d mean2d x, y, conic a, b, c, depth, opacity (effective), 0.
@group(0) @binding(7) var<storage, read> v_splats: array<f32>;
// Per Gaussian: dL/d mean (3), quat (4), scale (3), opacity (1), 0.
@group(0) @binding(8) var<storage, read_write> grads: array<f32>;

// Element (r, c) of a row-major matrix stored as WGSL columns.
fn el(m: mat3x3<f32>, r: u32, c: u32) -> f32 {
    return m[c][r];
}

fn outer(a: vec3<f32>, b: vec3<f32>) -> mat3x3<f32> {
    return mat3x3<f32>(a * b.x, a * b.y, a * b.z);
}

// Gradient w.r.t. the unit quaternion (w, x, y, z) given dL/dR (row-major entries).
fn quat_to_rotmat_vjp(q: vec4<f32>, v: mat3x3<f32>) -> vec4<f32> {
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let v00 = el(v, 0u, 0u);
    let v01 = el(v, 0u, 1u);
    let v02 = el(v, 0u, 2u);
    let v10 = el(v, 1u, 0u);
    let v11 = el(v, 1u, 1u);
    let v12 = el(v, 1u, 2u);
    let v20 = el(v, 2u, 0u);
    let v21 = el(v, 2u, 1u);
    let v22 = el(v, 2u, 2u);
    let gw = -z * v01 + y * v02 + z * v10 - x * v12 - y * v20 + x * v21;
    let gx = y * v01 + z * v02 + y * v10 - 2.0 * x * v11 - w * v12 + z * v20 + w * v21
        - 2.0 * x * v22;
    let gy = -2.0 * y * v00 + x * v01 + w * v02 + x * v10 + z * v12 - w * v20 + z * v21
        - 2.0 * y * v22;
    let gz = -2.0 * z * v00 - w * v01 + x * v02 + w * v10 - 2.0 * z * v11 + y * v12 + x * v20
        + y * v21;
    return 2.0 * vec4<f32>(gw, gx, gy, gz);
}

fn zero_grads(i: u32) {
    for (var k = 0u; k < 12u; k++) {
        grads[12u * i + k] = 0.0;
    }
}

@compute @workgroup_size(256)
fn project_backward(@builtin(global_invocation_id) gid: vec3<u32>,
                    @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= P.count.x {
        return;
    }
    let c = project_core(i);
    if !c.ok {
        zero_grads(i);
        return;
    }
    let x = c.mean_cam.x;
    let y = c.mean_cam.y;
    let z = c.mean_cam.z;
    let fx = P.intr.x;
    let fy = P.intr.y;
    let rz = 1.0 / z;
    let tx = c.tx;
    let ty = c.ty;
    let r0 = c.j0;
    let r1 = c.j1;
    let cov_cam = c.cov_cam;
    let conic = c.conic;
    let compensation = c.compensation;
    let a = c.a;
    let b = c.cov2d.y;
    let d = c.d;
    let det = c.det;
    let c00 = c.cov2d.x;
    let c11 = c.cov2d.z;
    let det_orig = c00 * c11 - b * b;
    let opacity = opacities[i];
    let v_m2 = vec2<f32>(v_splats[8u * i], v_splats[8u * i + 1u]);
    let v_conic = vec3<f32>(v_splats[8u * i + 2u], v_splats[8u * i + 3u], v_splats[8u * i + 4u]);
    let v_depth = v_splats[8u * i + 5u];
    let v_op_eff = v_splats[8u * i + 6u];

    // Opacity and antialiasing compensation.
    let v_opacity = v_op_eff * compensation;
    var v_cov2d = vec3<f32>(0.0);
    if P.size.w > 0.5 && compensation > 1e-12 {
        let v_ratio = v_op_eff * opacity * 0.5 / compensation;
        let rr = det_orig / (det * det);
        v_cov2d += v_ratio * vec3<f32>(c11 / det - rr * d, -2.0 * b / det + rr * 2.0 * b,
                                        c00 / det - rr * a);
    }
    // Conic = inverse(blurred cov): G = -Q V Q with V = [[va, vb/2], [vb/2, vc]].
    let va = v_conic.x;
    let vb = 0.5 * v_conic.y;
    let vcc = v_conic.z;
    let qv00 = conic.x * va + conic.y * vb;
    let qv01 = conic.x * vb + conic.y * vcc;
    let qv10 = conic.y * va + conic.z * vb;
    let qv11 = conic.y * vb + conic.z * vcc;
    v_cov2d += vec3<f32>(-(qv00 * conic.x + qv01 * conic.y),
                         2.0 * -(qv00 * conic.y + qv01 * conic.z),
                         -(qv10 * conic.y + qv11 * conic.z));
    let g00 = v_cov2d.x;
    let g01 = 0.5 * v_cov2d.y;
    let g11 = v_cov2d.z;
    // v_cov_cam = J^T G J; v_J = 2 G J Sigma_cam.
    let v_cov_cam = outer(r0, r0) * g00 + (outer(r0, r1) + outer(r1, r0)) * g01
        + outer(r1, r1) * g11;
    let gj0 = g00 * r0 + g01 * r1;
    let gj1 = g01 * r0 + g11 * r1;
    let vj0 = 2.0 * (gj0 * cov_cam);
    let vj1 = 2.0 * (gj1 * cov_cam);
    let rz2 = rz * rz;
    let rz3 = rz2 * rz;
    let v_tx = vj0.z * (-fx * rz2);
    let v_ty = vj1.z * (-fy * rz2);
    var v_mc = vec3<f32>(0.0);
    v_mc.z += -fx * rz2 * vj0.x + 2.0 * fx * tx * rz3 * vj0.z - fy * rz2 * vj1.y
        + 2.0 * fy * ty * rz3 * vj1.z;
    if c.clamped_x {
        v_mc.z += v_tx * tx * rz;
    } else {
        v_mc.x += v_tx;
    }
    if c.clamped_y {
        v_mc.z += v_ty * ty * rz;
    } else {
        v_mc.y += v_ty;
    }
    v_mc.x += v_m2.x * fx * rz;
    v_mc.y += v_m2.y * fy * rz;
    v_mc.z -= (v_m2.x * fx * x + v_m2.y * fy * y) * rz2;
    v_mc.z += v_depth;
    let v_mean = transpose(c.w) * v_mc;
    let v_cov = transpose(c.w) * v_cov_cam * c.w;
    let v_cov_sym = v_cov + transpose(v_cov);
    let v_m = v_cov_sym * c.m;
    let s = c.scale;
    let v_rot = mat3x3<f32>(v_m[0] * s.x, v_m[1] * s.y, v_m[2] * s.z);
    let v_scale = vec3<f32>(dot(v_m[0], c.rot[0]), dot(v_m[1], c.rot[1]), dot(v_m[2], c.rot[2]));
    let qu = c.quat_unit;
    let v_qu = quat_to_rotmat_vjp(qu, v_rot);
    let v_quat = (v_qu - qu * dot(qu, v_qu)) / c.quat_norm;
    grads[12u * i] = v_mean.x;
    grads[12u * i + 1u] = v_mean.y;
    grads[12u * i + 2u] = v_mean.z;
    grads[12u * i + 3u] = v_quat.x;
    grads[12u * i + 4u] = v_quat.y;
    grads[12u * i + 5u] = v_quat.z;
    grads[12u * i + 6u] = v_quat.w;
    grads[12u * i + 7u] = v_scale.x;
    grads[12u * i + 8u] = v_scale.y;
    grads[12u * i + 9u] = v_scale.z;
    grads[12u * i + 10u] = v_opacity;
    grads[12u * i + 11u] = 0.0;
}
