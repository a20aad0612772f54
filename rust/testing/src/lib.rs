//! Shared helpers for the rasterizer tests: a seeded RNG and random scenes in front of a camera.
//!
//! A crate of its own (dev-dependency of sync4d-raster and sync4d-gpu, not published) so that
//! the CPU tests, the wgpu parity tests and the cpu_vs_wgpu example share one copy instead of
//! including a test module by path.
// Test helpers, named for what they build; they panic (unwrap) on a failed call as the tests
// using them would. Documenting every field and panic would repeat the signatures.
#![allow(missing_docs, clippy::missing_panics_doc)]

use sync4d_raster::*;

/// SplitMix64: small, seeded, reproducible.
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Rng(seed.wrapping_add(0x9E37_79B9_7F4A_7C15))
    }
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    pub fn normal(&mut self) -> f64 {
        let u1 = self.uniform(1e-12, 1.0);
        let u2 = self.uniform(0.0, 1.0);
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// An owned scene: Gaussians (f64), features, camera, background.
#[derive(Clone, Debug)]
pub struct Scene {
    pub means: Vec<f64>,
    pub quats: Vec<f64>,
    pub scales: Vec<f64>,
    pub opacities: Vec<f64>,
    pub features: Vec<f64>,
    pub channels: usize,
    pub background: Vec<f64>,
    pub camera: Camera,
}

/// A rotation about a unit axis, row-major, and a world-to-camera matrix with it.
pub fn look_camera(width: u32, height: u32, seed: u64) -> Camera {
    let mut rng = Rng::new(seed ^ 0xCAFE);
    let (ax, ay, az) = (rng.normal(), rng.normal(), rng.normal());
    let n = (ax * ax + ay * ay + az * az).sqrt();
    let (x, y, z) = (ax / n, ay / n, az / n);
    let th = rng.uniform(-0.3, 0.3);
    let (c, s) = (th.cos(), th.sin());
    let t = 1.0 - c;
    let r = [
        [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
        [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
        [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
    ];
    // Camera looks at the origin from distance 4 along its z axis: t = (0, 0, 4).
    let view = [
        r[0][0], r[0][1], r[0][2], 0.1, //
        r[1][0], r[1][1], r[1][2], -0.05, //
        r[2][0], r[2][1], r[2][2], 4.0, //
        0.0, 0.0, 0.0, 1.0,
    ];
    let f = 0.9 * width.max(height) as f64;
    Camera::new(
        &view,
        f,
        f * 1.05,
        width as f64 * 0.52,
        height as f64 * 0.47,
        width,
        height,
    )
    .unwrap()
}

/// `n` random Gaussians around the origin (so in front of [`look_camera`]), overlapping.
pub fn random_scene(n: usize, width: u32, height: u32, channels: usize, seed: u64) -> Scene {
    let mut rng = Rng::new(seed);
    let mut s = Scene {
        means: vec![],
        quats: vec![],
        scales: vec![],
        opacities: vec![],
        features: vec![],
        channels,
        background: (0..channels).map(|c| 0.1 + 0.2 * c as f64).collect(),
        camera: look_camera(width, height, seed),
    };
    for _ in 0..n {
        for _ in 0..3 {
            s.means.push(rng.uniform(-1.2, 1.2));
        }
        for _ in 0..4 {
            s.quats.push(rng.normal());
        }
        let base = rng.uniform(-3.0, -1.2f64).exp();
        for _ in 0..3 {
            s.scales.push(base * rng.uniform(0.3, 1.5));
        }
        s.opacities.push(rng.uniform(0.05, 0.98));
        for _ in 0..channels {
            s.features.push(rng.uniform(0.0, 1.0));
        }
    }
    s
}

impl Scene {
    /// The scene's Gaussians, borrowed.
    pub fn gaussians(&self) -> Gaussians<'_, f64> {
        Gaussians {
            means: &self.means,
            quats: &self.quats,
            scales: &self.scales,
            opacities: &self.opacities,
        }
    }

    pub fn n(&self) -> usize {
        self.opacities.len()
    }
}

pub fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|x| *x as f32).collect()
}

/// Projection outputs (owned).
#[derive(Clone, Debug)]
pub struct Proj<F> {
    pub means2d: Vec<F>,
    pub conics: Vec<F>,
    pub depths: Vec<F>,
    pub opacities: Vec<F>,
    pub radii: Vec<i32>,
}

impl<F: real::Real> Proj<F> {
    /// Zeroed outputs for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        Proj {
            means2d: vec![F::zero(); 2 * n],
            conics: vec![F::zero(); 3 * n],
            depths: vec![F::zero(); n],
            opacities: vec![F::zero(); n],
            radii: vec![0; 2 * n],
        }
    }

    /// The projection's output view of these buffers.
    pub fn as_mut(&mut self) -> ProjectionMut<'_, F> {
        ProjectionMut {
            means2d: &mut self.means2d,
            conics: &mut self.conics,
            depths: &mut self.depths,
            opacities: &mut self.opacities,
            radii: &mut self.radii,
        }
    }
}

/// [`project`] of f64 Gaussians on the f32 fast path (each input rounded to f32).
pub fn project_f32(
    means: &[f64],
    quats: &[f64],
    scales: &[f64],
    opacities: &[f64],
    cam: &Camera,
    settings: &ProjectSettings,
) -> Proj<f32> {
    let (m, q, s, o) = (
        to_f32(means),
        to_f32(quats),
        to_f32(scales),
        to_f32(opacities),
    );
    project(&m, &q, &s, &o, cam, settings)
}

pub fn project<F: real::Real>(
    means: &[F],
    quats: &[F],
    scales: &[F],
    opacities: &[F],
    cam: &Camera,
    settings: &ProjectSettings,
) -> Proj<F> {
    let mut p = Proj::zeros(opacities.len());
    let g = Gaussians {
        means,
        quats,
        scales,
        opacities,
    };
    project_forward(&g, cam, settings, p.as_mut()).unwrap();
    p
}

/// Image outputs (owned).
#[derive(Clone, Debug, PartialEq)]
pub struct Image<F> {
    pub features: Vec<F>,
    pub alpha: Vec<F>,
    pub depth: Vec<F>,
}

impl<F: real::Real> Image<F> {
    pub fn zeros(npix: usize, ch: usize) -> Self {
        Image {
            features: vec![F::zero(); npix * ch],
            alpha: vec![F::zero(); npix],
            depth: vec![F::zero(); npix],
        }
    }

    /// The image as the compositor's output buffers.
    pub fn as_mut(&mut self) -> ImageMut<'_, F> {
        ImageMut {
            features: &mut self.features,
            alpha: &mut self.alpha,
            depth: &mut self.depth,
        }
    }

    /// The image as upstream gradients for a backward pass.
    pub fn as_grads(&self) -> ImageGrads<'_, F> {
        ImageGrads {
            features: &self.features,
            alpha: &self.alpha,
            depth: &self.depth,
        }
    }
}

/// Zeroed per-splat gradient buffers (means2d, conics, depths, opacities, features).
pub fn splat_grad_bufs<F: real::Real>(n: usize, ch: usize) -> [Vec<F>; 5] {
    [
        vec![F::zero(); 2 * n],
        vec![F::zero(); 3 * n],
        vec![F::zero(); n],
        vec![F::zero(); n],
        vec![F::zero(); n * ch],
    ]
}

/// `splat_grad_bufs` as the backward pass's output view.
pub fn grads_mut<F>(b: &mut [Vec<F>; 5]) -> SplatGradsMut<'_, F> {
    let [g2, gc, gd, go, gf] = b;
    SplatGradsMut {
        means2d: g2,
        conics: gc,
        depths: gd,
        opacities: go,
        features: gf,
    }
}

/// Zeroed per-Gaussian gradient buffers (means, quats, scales, opacities).
pub fn gaussian_grad_bufs<F: real::Real>(n: usize) -> [Vec<F>; 4] {
    [
        vec![F::zero(); 3 * n],
        vec![F::zero(); 4 * n],
        vec![F::zero(); 3 * n],
        vec![F::zero(); n],
    ]
}

/// `gaussian_grad_bufs` as the projection backward's output view.
pub fn gaussian_grads_mut<F>(b: &mut [Vec<F>; 4]) -> GaussianGradsMut<'_, F> {
    let [vm, vq, vs, vo] = b;
    GaussianGradsMut {
        means: vm,
        quats: vq,
        scales: vs,
        opacities: vo,
    }
}

pub fn splats<'a, F>(p: &'a Proj<F>, features: &'a [F], channels: usize) -> Splats<'a, F> {
    Splats {
        means2d: &p.means2d,
        conics: &p.conics,
        depths: &p.depths,
        opacities: &p.opacities,
        radii: &p.radii,
        features,
        channels,
    }
}

/// Render a scene in f64 with the reference compositor.
pub fn render_reference(
    s: &Scene,
    ps: &ProjectSettings,
    bs: &BlendSettings,
) -> (Proj<f64>, Image<f64>) {
    let p = project(&s.means, &s.quats, &s.scales, &s.opacities, &s.camera, ps);
    let npix = (s.camera.width * s.camera.height) as usize;
    let mut img = Image::zeros(npix, s.channels);
    rasterize_forward_reference(
        &splats(&p, &s.features, s.channels),
        s.camera.width,
        s.camera.height,
        &s.background,
        bs,
        img.as_mut(),
    )
    .unwrap();
    (p, img)
}

/// Render a scene with the f32 fast path.
pub fn render_fast(
    s: &Scene,
    ps: &ProjectSettings,
    bs: &BlendSettings,
    state: &mut RasterState,
) -> (Proj<f32>, Image<f32>, Counters) {
    let p = project_f32(&s.means, &s.quats, &s.scales, &s.opacities, &s.camera, ps);
    let npix = (s.camera.width * s.camera.height) as usize;
    let mut img = Image::zeros(npix, s.channels);
    let feats = to_f32(&s.features);
    let counters = rasterize_forward(
        &splats(&p, &feats, s.channels),
        s.camera.width,
        s.camera.height,
        &to_f32(&s.background),
        bs,
        state,
        img.as_mut(),
    )
    .unwrap();
    (p, img, counters)
}

/// Random upstream gradients for an image of `npix` pixels and `ch` channels.
pub fn random_image_grads(npix: usize, ch: usize, seed: u64) -> Image<f64> {
    let mut rng = Rng::new(seed);
    Image {
        features: (0..npix * ch).map(|_| rng.uniform(-1.0, 1.0)).collect(),
        alpha: (0..npix).map(|_| rng.uniform(-1.0, 1.0)).collect(),
        depth: (0..npix).map(|_| rng.uniform(-0.3, 0.3)).collect(),
    }
}

/// `sum(w * out)` over every image output.
pub fn weighted(img: &Image<f64>, w: &Image<f64>) -> f64 {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    dot(&img.features, &w.features) + dot(&img.alpha, &w.alpha) + dot(&img.depth, &w.depth)
}

/// Central finite differences of `f` at each index of `x`, with a discontinuity filter: an entry
/// whose step-h and step-h/2 estimates disagree straddles a cut-off (alpha < 1/255, the
/// transmittance stop or the alpha clamp) and is reported as `None`.
pub fn finite_diff(x: &[f64], h: f64, f: &mut dyn FnMut(&[f64]) -> f64) -> Vec<Option<f64>> {
    let mut xs = x.to_vec();
    let mut out = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let mut est = |step: f64, xs: &mut Vec<f64>| {
            let orig = xs[i];
            xs[i] = orig + step;
            let fp = f(xs);
            xs[i] = orig - step;
            let fm = f(xs);
            xs[i] = orig;
            (fp - fm) / (2.0 * step)
        };
        let g1 = est(h, &mut xs);
        let g2 = est(0.5 * h, &mut xs);
        let scale = g1.abs().max(g2.abs()).max(1e-3);
        out.push(((g1 - g2).abs() <= 1e-3 * scale).then_some(g2));
    }
    out
}

/// Compare analytic gradients with finite differences: every entry whose FD is defined must
/// agree within `rtol * max(|fd|, floor)`; at most `max_skipped` entries may straddle a cut-off.
pub fn assert_grad_close(
    name: &str,
    analytic: &[f64],
    fd: &[Option<f64>],
    rtol: f64,
    floor: f64,
    max_skipped: f64,
) {
    assert_eq!(analytic.len(), fd.len());
    let mut skipped = 0usize;
    let mut worst = (0.0f64, 0usize);
    for (i, (a, f)) in analytic.iter().zip(fd).enumerate() {
        let Some(f) = f else {
            skipped += 1;
            continue;
        };
        let err = (a - f).abs() / f.abs().max(floor);
        if err > worst.0 {
            worst = (err, i);
        }
        assert!(
            err <= rtol,
            "{name}[{i}]: analytic {a:.9e} vs finite difference {f:.9e} (rel err {err:.2e})"
        );
    }
    let frac = skipped as f64 / analytic.len().max(1) as f64;
    assert!(
        frac <= max_skipped,
        "{name}: {skipped} of {} entries straddle a cut-off",
        analytic.len()
    );
    let nonzero = analytic.iter().filter(|v| v.abs() > 0.0).count();
    assert!(
        nonzero > 0,
        "{name}: gradient is identically zero; the test checks nothing"
    );
    eprintln!(
        "{name}: worst rel err {:.2e} at {}, skipped {skipped}",
        worst.0, worst.1
    );
}

/// Splat gradients `[means2d, conics, depths, opacities, features]` under upstream image
/// gradients `v`, through the compositor of element type `F` (f32: fast path, which needs the
/// forward's `state`; f64: reference).
#[allow(clippy::too_many_arguments)]
pub fn splat_grads<F: Composite>(
    sp: &Splats<'_, F>,
    width: u32,
    height: u32,
    background: &[F],
    bs: &BlendSettings,
    state: &mut RasterState,
    v: &Image<F>,
) -> Result<[Vec<F>; 5]> {
    let (n, ch) = (sp.len(), sp.channels);
    let mut gb = splat_grad_bufs::<F>(n, ch);
    F::composite_backward(
        sp,
        width,
        height,
        background,
        bs,
        state,
        &v.as_grads(),
        grads_mut(&mut gb),
    )?;
    Ok(gb)
}

/// The reference (f64) compositing backward of scene `s`'s projection `p` given the image
/// gradients `w`: dL/d(means2d, conics, depths, opacities, features).
pub fn reference_splat_grads(
    p: &Proj<f64>,
    s: &Scene,
    bs: &BlendSettings,
    w: &Image<f64>,
) -> [Vec<f64>; 5] {
    let sp = splats(p, &s.features, s.channels);
    let (width, height) = (s.camera.width, s.camera.height);
    splat_grads(
        &sp,
        width,
        height,
        &s.background,
        bs,
        &mut RasterState::new(),
        w,
    )
    .unwrap()
}
