//! Projection of 3D Gaussians to screen-space splats (EWA), and its exact backward.
//!
//! Parallel design: one independent task per Gaussian, chunked over rayon. Per-Gaussian math is
//! carried out in f64 for both element types; the forward and the backward share
//! [`project_one`], so the backward always differentiates exactly what the forward computed.
//!
//! Conventions (those of gsplat's pinhole path): covariance `R S S^T R^T` with `R` from the
//! normalised quaternion `(w, x, y, z)`; camera-space `x/z`, `y/z` clamped to the frustum widened
//! by 30 % before forming the Jacobian; `eps2d` added to the 2D covariance diagonal; in
//! antialiased mode the opacity is multiplied by `sqrt(det(cov2d) / det(cov2d + eps2d I))`;
//! per-axis radius `ceil(3.33 sigma)`, which bounds every pixel where an opacity-1 splat has
//! alpha >= 1/255.

use crate::camera::Camera;
use crate::error::{check_finite, check_len, RasterError, Result};
use crate::linalg::{mul33, mul3tv, mul3v, transpose, Mat3};
use rayon::prelude::*;
use sync4d_scalar::quat::{quat_to_rotmat, quat_to_rotmat_vjp};
use sync4d_scalar::{fits, Real};

/// Extent factor of the screen radius, in standard deviations: `sqrt(2 ln 255)`, rounded up.
pub const RADIUS_SIGMAS: f64 = 3.33;
/// Quaternions shorter than this are treated like `F.normalize` does (divided by this instead).
pub const QUAT_EPS: f64 = 1e-12;
/// Lower bound on the blurred 2D covariance determinant.
pub const DET_EPS: f64 = 1e-10;
/// Largest screen radius stored, pixels (keeps tile arithmetic in range).
pub const MAX_RADIUS: f64 = 1.0e7;
/// Largest condition number of the blurred 2D covariance that is projected, measured as
/// `(a + d)^2 / det` (between 1 and 4 times `lambda_max / lambda_min`). Rounding in the
/// covariance products leaves an error of ~1e-16 `lambda_max` on the small eigenvalue, so this
/// keeps the conic to ~1e-5 relative.
pub const COND_MAX: f64 = 1.0e10;

/// Settings of the projection stage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectSettings {
    /// Gaussians with camera depth `z <= near` are culled (and get no outputs).
    pub near: f64,
    /// Gaussians with `z >= far` are culled from rasterization.
    pub far: f64,
    /// Low-pass dilation added to the 2D covariance diagonal, pixels^2 (0.3 in 3DGS).
    pub eps2d: f64,
    /// gsplat's `rasterize_mode="antialiased"`: compensate opacity for the dilation.
    pub antialiased: bool,
}

impl Default for ProjectSettings {
    fn default() -> Self {
        ProjectSettings {
            near: 0.01,
            far: 1e10,
            eps2d: 0.3,
            antialiased: false,
        }
    }
}

impl ProjectSettings {
    /// Check the settings (finite, `0 < near < far`, `eps2d >= 0`).
    pub fn validate(&self) -> Result<()> {
        if !(self.near.is_finite() && self.near > 0.0) {
            return Err(RasterError::invalid(
                "near",
                format!("must be finite and > 0, got {}", self.near),
            ));
        }
        if self.far.is_nan() || self.far <= self.near {
            return Err(RasterError::invalid(
                "far",
                format!("must be > near ({}), got {}", self.near, self.far),
            ));
        }
        if !(self.eps2d.is_finite() && self.eps2d >= 0.0) {
            return Err(RasterError::invalid(
                "eps2d",
                format!("must be finite and >= 0, got {}", self.eps2d),
            ));
        }
        Ok(())
    }
}

/// Borrowed 3D Gaussians. Flat row-major arrays: `means` N*3, `quats` N*4 (w, x, y, z, need not be
/// normalised), `scales` N*3 (standard deviations, world units), `opacities` N in [0, 1].
#[derive(Debug, Clone, Copy)]
pub struct Gaussians<'a, F> {
    /// Centres, N*3 world units.
    pub means: &'a [F],
    /// Rotations, N*4 (w, x, y, z).
    pub quats: &'a [F],
    /// Standard deviations along the local axes, N*3.
    pub scales: &'a [F],
    /// Opacities, N, in [0, 1].
    pub opacities: &'a [F],
}

impl<F: Real> Gaussians<'_, F> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// Check lengths and finiteness; scales must be >= 0 and opacities in [0, 1].
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        check_len("means", self.means, n * 3)?;
        check_len("quats", self.quats, n * 4)?;
        check_len("scales", self.scales, n * 3)?;
        check_finite("means", self.means)?;
        check_finite("quats", self.quats)?;
        check_finite("scales", self.scales)?;
        check_finite("opacities", self.opacities)?;
        if let Some(i) = self.scales.iter().position(|s| *s < F::zero()) {
            return Err(RasterError::invalid(
                "scales",
                format!(
                    "must be >= 0 (standard deviations, not log-scales); negative at flat index {i}"
                ),
            ));
        }
        if let Some(i) = self
            .opacities
            .iter()
            .position(|o| *o < F::zero() || *o > F::one())
        {
            return Err(RasterError::invalid(
                "opacities",
                format!("must lie in [0, 1] (apply a sigmoid to logits); bad value at index {i}"),
            ));
        }
        Ok(())
    }
}

/// Mutable outputs of the projection, flat row-major: `means2d` N*2 pixels, `conics` N*3 (the
/// xx, xy, yy entries of the inverse blurred 2D covariance), `depths` N (camera z),
/// `opacities` N (after antialiasing compensation), `radii` N*2 (pixels, 0 = culled).
#[derive(Debug)]
pub struct ProjectionMut<'a, F> {
    /// Projected centres, N*2 pixels.
    pub means2d: &'a mut [F],
    /// Inverse 2D covariance (a, b, c), N*3.
    pub conics: &'a mut [F],
    /// Camera-space depth z, N.
    pub depths: &'a mut [F],
    /// Opacity used for blending, N.
    pub opacities: &'a mut [F],
    /// Per-axis screen radius, N*2 pixels; 0 means culled.
    pub radii: &'a mut [i32],
}

impl<F> ProjectionMut<'_, F> {
    /// Check the output lengths for `n` Gaussians.
    pub fn check_len(&self, n: usize) -> Result<()> {
        check_len("means2d", self.means2d, n * 2)?;
        check_len("conics", self.conics, n * 3)?;
        check_len("depths", self.depths, n)?;
        check_len("opacities_out", self.opacities, n)?;
        check_len("radii", self.radii, n * 2)
    }
}

/// Borrowed projection outputs (the same layout as [`ProjectionMut`]).
#[derive(Debug, Clone, Copy)]
pub struct Projection<'a, F> {
    /// Projected centres, N*2 pixels.
    pub means2d: &'a [F],
    /// Inverse 2D covariance (a, b, c), N*3.
    pub conics: &'a [F],
    /// Camera-space depth z, N.
    pub depths: &'a [F],
    /// Opacity used for blending, N.
    pub opacities: &'a [F],
    /// Per-axis screen radius, N*2 pixels; 0 means culled.
    pub radii: &'a [i32],
}

/// Gradients of the loss w.r.t. the projection outputs (same layout as [`Projection`]).
#[derive(Debug, Clone, Copy)]
pub struct ProjectionGrads<'a, F> {
    /// dL/d means2d, N*2.
    pub means2d: &'a [F],
    /// dL/d conics, N*3.
    pub conics: &'a [F],
    /// dL/d depths, N.
    pub depths: &'a [F],
    /// dL/d opacities (effective), N.
    pub opacities: &'a [F],
}

impl<F: Real> ProjectionGrads<'_, F> {
    /// Check lengths for `n` Gaussians and finiteness.
    pub fn validate(&self, n: usize) -> Result<()> {
        check_len("v_means2d", self.means2d, n * 2)?;
        check_len("v_conics", self.conics, n * 3)?;
        check_len("v_depths", self.depths, n)?;
        check_len("v_opacities", self.opacities, n)?;
        check_finite("v_means2d", self.means2d)?;
        check_finite("v_conics", self.conics)?;
        check_finite("v_depths", self.depths)?;
        check_finite("v_opacities", self.opacities)
    }
}

/// Gradients of the loss w.r.t. the 3D Gaussian parameters (same layout as [`Gaussians`]).
#[derive(Debug)]
pub struct GaussianGradsMut<'a, F> {
    /// dL/d means, N*3.
    pub means: &'a mut [F],
    /// dL/d quats (unnormalised), N*4.
    pub quats: &'a mut [F],
    /// dL/d scales, N*3.
    pub scales: &'a mut [F],
    /// dL/d opacities, N.
    pub opacities: &'a mut [F],
}

impl<F> GaussianGradsMut<'_, F> {
    /// Check the gradient buffer lengths for `n` Gaussians.
    pub fn check_len(&self, n: usize) -> Result<()> {
        check_len("grad_means", self.means, n * 3)?;
        check_len("grad_quats", self.quats, n * 4)?;
        check_len("grad_scales", self.scales, n * 3)?;
        check_len("grad_opacities", self.opacities, n)
    }
}

/// Camera quantities shared by every Gaussian, in f64.
#[derive(Debug, Clone, Copy)]
struct CameraConsts {
    rot: Mat3<f64>,
    trans: [f64; 3],
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    width: f64,
    height: f64,
    lim_x_pos: f64,
    lim_x_neg: f64,
    lim_y_pos: f64,
    lim_y_neg: f64,
}

impl CameraConsts {
    fn new(cam: &Camera) -> Self {
        let m = &cam.world_to_camera;
        let (w, h) = (cam.width as f64, cam.height as f64);
        let tan_fovx = 0.5 * w / cam.fx;
        let tan_fovy = 0.5 * h / cam.fy;
        CameraConsts {
            rot: [
                [m[0][0], m[0][1], m[0][2]],
                [m[1][0], m[1][1], m[1][2]],
                [m[2][0], m[2][1], m[2][2]],
            ],
            trans: [m[0][3], m[1][3], m[2][3]],
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            width: w,
            height: h,
            lim_x_pos: (w - cam.cx) / cam.fx + 0.3 * tan_fovx,
            lim_x_neg: cam.cx / cam.fx + 0.3 * tan_fovx,
            lim_y_pos: (h - cam.cy) / cam.fy + 0.3 * tan_fovy,
            lim_y_neg: cam.cy / cam.fy + 0.3 * tan_fovy,
        }
    }
}

/// One Gaussian's projection with the intermediates its backward needs (all f64).
#[derive(Debug, Clone, Copy)]
pub struct ProjectedGaussian {
    /// Projected centre, pixels.
    pub mean2d: [f64; 2],
    /// Inverse blurred 2D covariance (a, b, c).
    pub conic: [f64; 3],
    /// Camera depth z.
    pub depth: f64,
    /// Opacity after antialiasing compensation.
    pub opacity: f64,
    /// Per-axis screen radius in pixels (0 when culled from rasterization).
    pub radius: [i32; 2],
    // Intermediates for the backward.
    mean_cam: [f64; 3],
    quat_unit: [f64; 4],
    quat_norm: f64,
    rotmat: Mat3<f64>,
    cov_cam: Mat3<f64>,
    cov2d: [f64; 3],
    det_blur: f64,
    compensation: f64,
    clamped_x: bool,
    clamped_y: bool,
    tx: f64,
    ty: f64,
}

/// Project one Gaussian. Returns `None` when it has no projection (`z <= near`, or a value that
/// does not fit the element type `F`); its outputs are then zero and so are its gradients.
#[inline]
fn project_one<F: Real>(
    k: &CameraConsts,
    s: &ProjectSettings,
    mean: [f64; 3],
    quat: [f64; 4],
    scale: [f64; 3],
    opacity: f64,
) -> Option<ProjectedGaussian> {
    let mc = {
        let r = mul3v(&k.rot, mean);
        [r[0] + k.trans[0], r[1] + k.trans[1], r[2] + k.trans[2]]
    };
    let [x, y, z] = mc;
    if z.is_nan() || z <= s.near || !mc.iter().all(|v| v.is_finite()) {
        return None;
    }
    let qn = (quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3])
        .sqrt()
        .max(QUAT_EPS);
    let qu = [quat[0] / qn, quat[1] / qn, quat[2] / qn, quat[3] / qn];
    let rotmat = quat_to_rotmat(qu);
    // M = R diag(s); Sigma = M M^T; Sigma_cam = W Sigma W^T.
    let mut m = rotmat;
    for row in &mut m {
        for j in 0..3 {
            row[j] *= scale[j];
        }
    }
    let cov = mul33(&m, &transpose(&m));
    let cov_cam = mul33(&mul33(&k.rot, &cov), &transpose(&k.rot));

    let (ux, uy) = (x / z, y / z);
    let clamped_x = ux < -k.lim_x_neg || ux > k.lim_x_pos;
    let clamped_y = uy < -k.lim_y_neg || uy > k.lim_y_pos;
    let tx = z * ux.clamp(-k.lim_x_neg, k.lim_x_pos);
    let ty = z * uy.clamp(-k.lim_y_neg, k.lim_y_pos);
    let j = jacobian(k, z, tx, ty);
    let cov2d = project_cov(&j, &cov_cam);
    let det_orig = cov2d[0] * cov2d[2] - cov2d[1] * cov2d[1];
    let (a, b, d) = (cov2d[0] + s.eps2d, cov2d[1], cov2d[2] + s.eps2d);
    let det_blur = (a * d - b * b).max(DET_EPS);
    // A blurred 2D covariance this ill-conditioned (a needle thinner than a pixel whose length,
    // as a standard deviation, exceeds ~5e4 px at eps2d = 0.3; a degenerate one at eps2d = 0)
    // has lost its small eigenvalue to rounding: the conic came out as large as 1e37 and
    // indefinite, and the gradients as noise that overflows f32. Such a Gaussian gets no
    // projection, like a value that does not fit `F`. (NaN: caught by the checks below.)
    if (a + d) * (a + d) > COND_MAX * det_blur {
        return None;
    }
    let compensation = if s.antialiased {
        (det_orig / det_blur).max(0.0).sqrt()
    } else {
        1.0
    };
    let conic = [d / det_blur, -b / det_blur, a / det_blur];
    let mean2d = [k.fx * x / z + k.cx, k.fy * y / z + k.cy];
    let opacity_eff = opacity * compensation;

    let ok = mean2d.iter().chain(conic.iter()).all(|v| fits::<F>(*v))
        && fits::<F>(z)
        && a.is_finite()
        && d.is_finite();
    if !ok {
        return None;
    }
    let rx = (RADIUS_SIGMAS * a.sqrt()).ceil().min(MAX_RADIUS);
    let ry = (RADIUS_SIGMAS * d.sqrt()).ceil().min(MAX_RADIUS);
    let inside = mean2d[0] + rx > 0.0
        && mean2d[0] - rx < k.width
        && mean2d[1] + ry > 0.0
        && mean2d[1] - ry < k.height;
    let radius = if z < s.far && inside {
        [rx as i32, ry as i32]
    } else {
        [0, 0]
    };
    Some(ProjectedGaussian {
        mean2d,
        conic,
        depth: z,
        opacity: opacity_eff,
        radius,
        mean_cam: mc,
        quat_unit: qu,
        quat_norm: qn,
        rotmat,
        cov_cam,
        cov2d,
        det_blur,
        compensation,
        clamped_x,
        clamped_y,
        tx,
        ty,
    })
}

/// The 2x3 perspective Jacobian at camera point (tx, ty, z), stored as its 4 non-zero entries
/// `[fx/z, -fx tx/z^2, fy/z, -fy ty/z^2]`.
#[inline(always)]
fn jacobian(k: &CameraConsts, z: f64, tx: f64, ty: f64) -> [f64; 4] {
    let rz = 1.0 / z;
    [
        k.fx * rz,
        -k.fx * tx * rz * rz,
        k.fy * rz,
        -k.fy * ty * rz * rz,
    ]
}

/// `J Sigma J^T` for the sparse Jacobian of [`jacobian`]; returns (xx, xy, yy).
#[inline(always)]
fn project_cov(j: &[f64; 4], s: &Mat3<f64>) -> [f64; 3] {
    // Rows of J: r0 = (j0, 0, j1), r1 = (0, j2, j3).
    let r0 = [j[0], 0.0, j[1]];
    let r1 = [0.0, j[2], j[3]];
    let s_r0 = mul3v(s, r0);
    let s_r1 = mul3v(s, r1);
    let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    [dot(r0, s_r0), dot(r0, s_r1), dot(r1, s_r1)]
}

/// Gradients of one Gaussian's parameters given the gradients of its projection outputs.
/// Returns (d mean, d quat, d scale, d opacity).
#[inline]
// The chain rule through one projection, step for step against `project_one`.
#[allow(clippy::too_many_arguments, clippy::too_many_lines)]
fn project_one_vjp(
    k: &CameraConsts,
    s: &ProjectSettings,
    p: &ProjectedGaussian,
    scale: [f64; 3],
    opacity: f64,
    v_mean2d: [f64; 2],
    v_conic: [f64; 3],
    v_depth: f64,
    v_opacity_eff: f64,
) -> ([f64; 3], [f64; 4], [f64; 3], f64) {
    let [x, y, z] = p.mean_cam;
    let cov2d = p.cov2d;
    let (a, b, d) = (cov2d[0] + s.eps2d, cov2d[1], cov2d[2] + s.eps2d);
    let det = p.det_blur;

    // Opacity and antialiasing compensation.
    let v_opacity = v_opacity_eff * p.compensation;
    // Gradient w.r.t. the un-blurred 2D covariance entries (xx, xy, yy), where xy is the single
    // off-diagonal parameter appearing twice in the matrix.
    let mut v_cov2d = [0.0f64; 3];
    if s.antialiased && p.compensation > 1e-12 {
        let det_orig = cov2d[0] * cov2d[2] - cov2d[1] * cov2d[1];
        let v_comp = v_opacity_eff * opacity;
        let v_ratio = v_comp * 0.5 / p.compensation;
        // ratio = det_orig / det; d det_orig = (d, -2b, a) . dcov ; d det = (d', -2b, a') . dcov.
        let r = det_orig / (det * det);
        v_cov2d[0] += v_ratio * (cov2d[2] / det - r * d);
        v_cov2d[1] += v_ratio * (-2.0 * b / det + r * 2.0 * b);
        v_cov2d[2] += v_ratio * (cov2d[0] / det - r * a);
    }
    // Conic = inverse(blurred cov). Q = [[ca, cb], [cb, cc]]; G = -Q V Q with V the symmetric
    // matrix gradient [[va, vb/2], [vb/2, vc]].
    let [ca, cb, cc] = p.conic;
    let (va, vb, vc) = (v_conic[0], 0.5 * v_conic[1], v_conic[2]);
    // Q V
    let qv00 = ca * va + cb * vb;
    let qv01 = ca * vb + cb * vc;
    let qv10 = cb * va + cc * vb;
    let qv11 = cb * vb + cc * vc;
    // (Q V) Q
    let g00 = -(qv00 * ca + qv01 * cb);
    let g01 = -(qv00 * cb + qv01 * cc);
    let g11 = -(qv10 * cb + qv11 * cc);
    v_cov2d[0] += g00;
    v_cov2d[1] += 2.0 * g01;
    v_cov2d[2] += g11;
    let _ = det;

    // Full symmetric matrix gradient of cov2d.
    let g2 = [
        [v_cov2d[0], 0.5 * v_cov2d[1]],
        [0.5 * v_cov2d[1], v_cov2d[2]],
    ];
    let j = jacobian(k, z, p.tx, p.ty);
    let jm: [[f64; 3]; 2] = [[j[0], 0.0, j[1]], [0.0, j[2], j[3]]];
    // v_cov_cam = J^T G J (3x3); v_J = 2 G J Sigma_cam (2x3).
    let mut v_cov_cam = [[0.0f64; 3]; 3];
    for (r, row) in v_cov_cam.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for i in 0..2 {
                for l in 0..2 {
                    acc += jm[i][r] * g2[i][l] * jm[l][c];
                }
            }
            *v = acc;
        }
    }
    let mut gj = [[0.0f64; 3]; 2];
    for i in 0..2 {
        for c in 0..3 {
            gj[i][c] = g2[i][0] * jm[0][c] + g2[i][1] * jm[1][c];
        }
    }
    let mut v_j = [[0.0f64; 3]; 2];
    for i in 0..2 {
        for c in 0..3 {
            let mut acc = 0.0;
            for l in 0..3 {
                acc += gj[i][l] * p.cov_cam[l][c];
            }
            v_j[i][c] = 2.0 * acc;
        }
    }
    // J entries: J00 = fx/z, J02 = -fx tx/z^2, J11 = fy/z, J12 = -fy ty/z^2.
    let rz = 1.0 / z;
    let rz2 = rz * rz;
    let rz3 = rz2 * rz;
    let v_tx = v_j[0][2] * (-k.fx * rz2);
    let v_ty = v_j[1][2] * (-k.fy * rz2);
    let mut v_mc = [0.0f64; 3];
    v_mc[2] += -k.fx * rz2 * v_j[0][0]
        + 2.0 * k.fx * p.tx * rz3 * v_j[0][2]
        + -k.fy * rz2 * v_j[1][1]
        + 2.0 * k.fy * p.ty * rz3 * v_j[1][2];
    // tx = z * clamp(x / z): d tx = dx when not clamped, (tx / z) dz when clamped.
    if p.clamped_x {
        v_mc[2] += v_tx * p.tx * rz;
    } else {
        v_mc[0] += v_tx;
    }
    if p.clamped_y {
        v_mc[2] += v_ty * p.ty * rz;
    } else {
        v_mc[1] += v_ty;
    }
    // means2d = (fx x / z + cx, fy y / z + cy).
    v_mc[0] += v_mean2d[0] * k.fx * rz;
    v_mc[1] += v_mean2d[1] * k.fy * rz;
    v_mc[2] -= (v_mean2d[0] * k.fx * x + v_mean2d[1] * k.fy * y) * rz2;
    v_mc[2] += v_depth;
    let v_mean = mul3tv(&k.rot, v_mc);

    // Sigma_cam = W Sigma W^T  =>  v_Sigma = W^T v_Sigma_cam W.
    let v_cov = mul33(&mul33(&transpose(&k.rot), &v_cov_cam), &k.rot);
    // Sigma = M M^T, M = R diag(s)  =>  v_M = (v_Sigma + v_Sigma^T) M.
    let mut m = p.rotmat;
    for row in &mut m {
        for c in 0..3 {
            row[c] *= scale[c];
        }
    }
    let mut v_cov_sym = v_cov;
    for r in 0..3 {
        for c in 0..3 {
            v_cov_sym[r][c] = v_cov[r][c] + v_cov[c][r];
        }
    }
    let v_m = mul33(&v_cov_sym, &m);
    let mut v_rot = [[0.0f64; 3]; 3];
    let mut v_scale = [0.0f64; 3];
    for r in 0..3 {
        for c in 0..3 {
            v_rot[r][c] = v_m[r][c] * scale[c];
            v_scale[c] += v_m[r][c] * p.rotmat[r][c];
        }
    }
    let v_qu = quat_to_rotmat_vjp(p.quat_unit, &v_rot);
    let qu = p.quat_unit;
    let dot = qu[0] * v_qu[0] + qu[1] * v_qu[1] + qu[2] * v_qu[2] + qu[3] * v_qu[3];
    let v_quat = [
        (v_qu[0] - qu[0] * dot) / p.quat_norm,
        (v_qu[1] - qu[1] * dot) / p.quat_norm,
        (v_qu[2] - qu[2] * dot) / p.quat_norm,
        (v_qu[3] - qu[3] * dot) / p.quat_norm,
    ];
    (v_mean, v_quat, v_scale, v_opacity)
}

#[inline(always)]
fn get3<F: Real>(v: &[F], i: usize) -> [f64; 3] {
    [
        v[3 * i].to_f64(),
        v[3 * i + 1].to_f64(),
        v[3 * i + 2].to_f64(),
    ]
}

#[inline(always)]
fn get4<F: Real>(v: &[F], i: usize) -> [f64; 4] {
    [
        v[4 * i].to_f64(),
        v[4 * i + 1].to_f64(),
        v[4 * i + 2].to_f64(),
        v[4 * i + 3].to_f64(),
    ]
}

/// Gaussians handled per rayon task.
const CHUNK: usize = 1024;

/// Project every Gaussian through `camera`; writes `out` and returns the number of Gaussians
/// with a non-zero radius (visible). Gaussians without a projection get zero outputs.
pub fn project_forward<F: Real>(
    gaussians: &Gaussians<'_, F>,
    camera: &Camera,
    settings: &ProjectSettings,
    out: ProjectionMut<'_, F>,
) -> Result<usize> {
    gaussians.validate()?;
    camera.validate()?;
    settings.validate()?;
    let n = gaussians.len();
    out.check_len(n)?;
    let k = CameraConsts::new(camera);
    let g = gaussians;
    let visible: usize = out
        .means2d
        .par_chunks_mut(2 * CHUNK)
        .zip(out.conics.par_chunks_mut(3 * CHUNK))
        .zip(out.depths.par_chunks_mut(CHUNK))
        .zip(out.opacities.par_chunks_mut(CHUNK))
        .zip(out.radii.par_chunks_mut(2 * CHUNK))
        .enumerate()
        .map(|(ci, ((((m2, co), de), op), ra))| {
            let mut visible = 0;
            for l in 0..de.len() {
                let i = ci * CHUNK + l;
                let proj = project_one::<F>(
                    &k,
                    settings,
                    get3(g.means, i),
                    get4(g.quats, i),
                    get3(g.scales, i),
                    g.opacities[i].to_f64(),
                );
                if let Some(p) = proj {
                    m2[2 * l] = F::from_f64(p.mean2d[0]);
                    m2[2 * l + 1] = F::from_f64(p.mean2d[1]);
                    for c in 0..3 {
                        co[3 * l + c] = F::from_f64(p.conic[c]);
                    }
                    de[l] = F::from_f64(p.depth);
                    op[l] = F::from_f64(p.opacity);
                    ra[2 * l] = p.radius[0];
                    ra[2 * l + 1] = p.radius[1];
                    visible += usize::from(p.radius[0] > 0 && p.radius[1] > 0);
                } else {
                    m2[2 * l..2 * l + 2].fill(F::zero());
                    co[3 * l..3 * l + 3].fill(F::zero());
                    de[l] = F::zero();
                    op[l] = F::zero();
                    ra[2 * l..2 * l + 2].fill(0);
                }
            }
            visible
        })
        .sum();
    Ok(visible)
}

/// Backward of [`project_forward`]: given dL/d(outputs), writes dL/d(means, quats, scales,
/// opacities) into `grads` (overwriting). Inputs must be those of the forward call.
pub fn project_backward<F: Real>(
    gaussians: &Gaussians<'_, F>,
    camera: &Camera,
    settings: &ProjectSettings,
    v_out: &ProjectionGrads<'_, F>,
    grads: GaussianGradsMut<'_, F>,
) -> Result<()> {
    gaussians.validate()?;
    camera.validate()?;
    settings.validate()?;
    let n = gaussians.len();
    v_out.validate(n)?;
    grads.check_len(n)?;
    let k = CameraConsts::new(camera);
    let g = gaussians;
    grads
        .means
        .par_chunks_mut(3 * CHUNK)
        .zip(grads.quats.par_chunks_mut(4 * CHUNK))
        .zip(grads.scales.par_chunks_mut(3 * CHUNK))
        .zip(grads.opacities.par_chunks_mut(CHUNK))
        .enumerate()
        .for_each(|(ci, (((gm, gq), gs), go))| {
            for l in 0..go.len() {
                let i = ci * CHUNK + l;
                let scale = get3(g.scales, i);
                let opacity = g.opacities[i].to_f64();
                let proj = project_one::<F>(
                    &k,
                    settings,
                    get3(g.means, i),
                    get4(g.quats, i),
                    scale,
                    opacity,
                );
                let Some(p) = proj else {
                    gm[3 * l..3 * l + 3].fill(F::zero());
                    gq[4 * l..4 * l + 4].fill(F::zero());
                    gs[3 * l..3 * l + 3].fill(F::zero());
                    go[l] = F::zero();
                    continue;
                };
                let (vm, vq, vs, vo) = project_one_vjp(
                    &k,
                    settings,
                    &p,
                    scale,
                    opacity,
                    [
                        v_out.means2d[2 * i].to_f64(),
                        v_out.means2d[2 * i + 1].to_f64(),
                    ],
                    [
                        v_out.conics[3 * i].to_f64(),
                        v_out.conics[3 * i + 1].to_f64(),
                        v_out.conics[3 * i + 2].to_f64(),
                    ],
                    v_out.depths[i].to_f64(),
                    v_out.opacities[i].to_f64(),
                );
                for c in 0..3 {
                    gm[3 * l + c] = F::from_f64(vm[c]);
                    gs[3 * l + c] = F::from_f64(vs[c]);
                }
                for c in 0..4 {
                    gq[4 * l + c] = F::from_f64(vq[c]);
                }
                go[l] = F::from_f64(vo);
            }
        });
    Ok(())
}
