//! Robustness properties: scenes mixing edge cases (zero, tiny and huge scales; Gaussians behind,
//! on or just in front of the camera plane; opacity 0 and 1; coincident means; extreme
//! anisotropy; zero and huge quaternions; 1x1, 1xN, Nx1 and 4096x4096 images) never panic and
//! give finite outputs and gradients, with alpha in [0, 1] and the background wherever
//! alpha == 0. NaN/inf inputs are rejected with an error naming the argument.
//!
//! Run: `cargo test -p sync4d-raster --release --test robustness`.

use proptest::prelude::*;
use proptest::sample::{select, Index};
use sync4d_raster::*;
use sync4d_testing::Rng;
use sync4d_testing::*;

/// `near` as an f32 value, so a Gaussian at z == near is exactly on the plane for f32 inputs too.
const NEAR: f64 = 0.01f32 as f64;
const F32_MAX: f64 = f32::MAX as f64;

/// The smallest f32 above `v` (as f64): a Gaussian just in front of the near plane.
fn next_up_f32(v: f64) -> f64 {
    f32::from_bits((v as f32).to_bits() + 1) as f64
}

// ---------------------------------------------------------------------------------------------
// Strategies.
// ---------------------------------------------------------------------------------------------

/// One Gaussian; the mean is in camera space (mapped to world space with the scene's camera).
#[derive(Debug, Clone)]
struct G {
    mean_cam: [f64; 3],
    quat: [f64; 4],
    scale: [f64; 3],
    opacity: f64,
}

/// One scale axis: typical, exactly zero, tiny, huge, up to f32::MAX, and log-uniform over the
/// whole f32 range (which crosses the regime where the 2D covariance determinant cancels).
/// `wide` adds values only f64 can hold.
fn axis_scale(wide: bool) -> BoxedStrategy<f64> {
    let base = prop_oneof![
        4 => (-4.5f64..-0.7).prop_map(f64::exp),
        2 => Just(0.0),
        1 => Just(1e-30),
        1 => Just(1e-6),
        1 => Just(1e3),
        1 => Just(1e30),
        1 => Just(F32_MAX),
        3 => (-38.0f64..38.0).prop_map(|e| 10f64.powf(e)),
    ];
    if wide {
        prop_oneof![8 => base, 1 => (38.0f64..300.0).prop_map(|e| 10f64.powf(e))].boxed()
    } else {
        base.boxed()
    }
}

fn scale3(wide: bool) -> impl Strategy<Value = [f64; 3]> {
    let axis = axis_scale(wide);
    prop_oneof![
        4 => [axis.clone(), axis.clone(), axis.clone()],
        1 => axis.prop_map(|s| [s, s, s]),
        // Extreme anisotropy: needles and discs, in any axis order.
        1 => (select(vec![[1e-6, 1e3, 1e3], [1e-6, 1e-6, 1e3], [0.0, 1e3, 1e-6]]), 0usize..3)
            .prop_map(|(s, r)| [s[r], s[(r + 1) % 3], s[(r + 2) % 3]]),
    ]
}

fn quat() -> impl Strategy<Value = [f64; 4]> {
    let q = [-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0];
    prop_oneof![
        4 => q.clone(),
        1 => Just([1.0, 0.0, 0.0, 0.0]),
        1 => Just([0.0; 4]),
        // In-plane rotations: rank-deficient covariances get off-diagonal 2D terms.
        1 => (0.0f64..6.3).prop_map(|t| [(0.5 * t).cos(), 0.0, 0.0, (0.5 * t).sin()]),
        1 => q.clone().prop_map(|q| q.map(|v| v * 1e30)),
        1 => Just([F32_MAX, 1.0, -F32_MAX, 1e-30]),
        1 => q.prop_map(|q| q.map(|v| v * 1e-30)),
    ]
}

fn opacity() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => 0.0f64..=1.0,
        1 => Just(0.0),
        2 => Just(1.0),
        1 => Just(1e-30),
        1 => Just(1.0 / 255.0),
    ]
}

/// Camera-space mean: in view, on the camera plane, behind it, exactly on the near plane, just
/// in front of it, far away, and far off to the side.
fn mean_cam() -> impl Strategy<Value = [f64; 3]> {
    let xy = (-1.0f64..1.0, -1.0f64..1.0);
    prop_oneof![
        5 => (xy.clone(), 0.3f64..6.0).prop_map(|((x, y), z)| [0.6 * x * z, 0.6 * y * z, z]),
        1 => xy.clone().prop_map(|(x, y)| [x, y, 0.0]),
        1 => (xy.clone(), select(vec![-1e-30, -1e-6, -1e-3, -2.0, -1e30]))
            .prop_map(|((x, y), z)| [x, y, z]),
        1 => xy.clone().prop_map(|(x, y)| [x * NEAR, y * NEAR, NEAR]),
        1 => xy.clone().prop_map(|(x, y)| {
            let z = next_up_f32(NEAR);
            [x * z, y * z, z]
        }),
        1 => (xy, select(vec![1e3, 1e6, 1e10, 1e20, 1e30, 1e38]))
            .prop_map(|((x, y), z)| [0.6 * x * z, 0.6 * y * z, z]),
        1 => (select(vec![1e30, -1e30, F32_MAX, 1e6]), 0.3f64..3.0).prop_map(|(x, z)| [x, 0.1, z]),
    ]
}

fn gaussian(wide: bool) -> impl Strategy<Value = G> {
    (mean_cam(), quat(), scale3(wide), opacity()).prop_map(|(mean_cam, quat, scale, opacity)| G {
        mean_cam,
        quat,
        scale,
        opacity,
    })
}

/// Image sizes: 1x1, one row, one column, tile-sized and random.
fn image_size(max_side: u32) -> impl Strategy<Value = (u32, u32)> {
    prop_oneof![
        1 => Just((1, 1)),
        1 => Just((1, max_side)),
        1 => Just((max_side, 1)),
        1 => Just((1, 17)),
        1 => Just((16, 16)),
        4 => (1..=max_side, 1..=max_side),
    ]
}

#[derive(Debug, Clone)]
struct EdgeScene {
    gs: Vec<G>,
    width: u32,
    height: u32,
    channels: usize,
    /// None: identity camera; Some(seed): a rotated, translated camera.
    cam_seed: Option<u64>,
    /// Focal length as a multiple of the longer image side.
    focal: f64,
    settings: ProjectSettings,
    alpha_max: f64,
    /// Seed of features, background and upstream gradients.
    seed: u64,
}

prop_compose! {
    fn edge_scene(max_n: usize, max_side: u32, wide: bool)(
        mut gs in prop::collection::vec(gaussian(wide), 0..=max_n),
        dups in prop::collection::vec((any::<Index>(), any::<Index>(), any::<bool>()), 0..4),
        (width, height) in image_size(max_side),
        channels in 1usize..=5,
        cam_seed in prop::option::of(any::<u64>()),
        focal in prop_oneof![6 => Just(0.9), 1 => Just(1e-3), 1 => Just(1e3)],
        eps2d in select(vec![0.3, 0.0, 1e-4]),
        antialiased in any::<bool>(),
        far in prop_oneof![5 => Just(1e10), 1 => Just(1e12)],
        alpha_max in select(vec![0.99, 0.999, 0.5, 1.0 / 255.0]),
        seed in any::<u64>(),
    ) -> EdgeScene {
        // Coincident means (and sometimes fully duplicated Gaussians).
        if !gs.is_empty() {
            for (src, dst, whole) in dups {
                let (s, d) = (src.index(gs.len()), dst.index(gs.len()));
                if whole {
                    gs[d] = gs[s].clone();
                } else {
                    gs[d].mean_cam = gs[s].mean_cam;
                }
            }
        }
        let settings = ProjectSettings { near: NEAR, far, eps2d, antialiased };
        EdgeScene { gs, width, height, channels, cam_seed, focal, settings, alpha_max, seed }
    }
}

// ---------------------------------------------------------------------------------------------
// Scene assembly and checks.
// ---------------------------------------------------------------------------------------------

/// World-space inputs of a scene, in f64.
struct Inputs {
    camera: Camera,
    means: Vec<f64>,
    quats: Vec<f64>,
    scales: Vec<f64>,
    opacities: Vec<f64>,
    features: Vec<f64>,
    background: Vec<f64>,
}

fn inputs(s: &EdgeScene) -> Inputs {
    let (w, h) = (s.width, s.height);
    let view: [f64; 16] = match s.cam_seed {
        None => [
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ],
        Some(seed) => {
            let m = look_camera(w, h, seed).world_to_camera;
            std::array::from_fn(|i| m[i / 4][i % 4])
        }
    };
    let f = s.focal * w.max(h) as f64;
    let camera = Camera::new(&view, f, 1.05 * f, 0.52 * w as f64, 0.47 * h as f64, w, h).unwrap();
    let r = camera.rotation();
    let t = camera.translation();
    let mut means = Vec::new();
    for g in &s.gs {
        // World mean = R^T (p_cam - t).
        let p = glam::DVec3::from_array(g.mean_cam) - t;
        means.extend_from_slice(&(r.transpose() * p).to_array());
    }
    let mut rng = Rng::new(s.seed);
    let ch = s.channels;
    Inputs {
        camera,
        means,
        quats: s.gs.iter().flat_map(|g| g.quat).collect(),
        scales: s.gs.iter().flat_map(|g| g.scale).collect(),
        opacities: s.gs.iter().map(|g| g.opacity).collect(),
        features: (0..s.gs.len() * ch)
            .map(|_| rng.uniform(-1.0, 2.0))
            .collect(),
        background: (0..ch).map(|_| rng.uniform(0.0, 1.0)).collect(),
    }
}

fn assert_finite<F: real::Real>(name: &str, v: &[F]) {
    if let Some(i) = v.iter().position(|x| !x.is_finite()) {
        panic!("{name}[{i}] is not finite: {:?}", v[i]);
    }
}

/// Projection outputs: finite, radii >= 0, Gaussians at or behind the near plane culled with
/// all-zero outputs, and conics inverses of a covariance dilated by `eps2d`: diagonal >= 0 and
/// every entry <= 1 / eps2d (up to rounding).
fn check_projection<F: real::Real>(p: &Proj<F>, cam_z: &[f64], ps: &ProjectSettings) {
    let near = ps.near;
    assert_finite("means2d", &p.means2d);
    assert_finite("conics", &p.conics);
    assert_finite("depths", &p.depths);
    assert_finite("opacities (projected)", &p.opacities);
    assert!(p.radii.iter().all(|r| *r >= 0), "negative radius");
    assert!(
        p.opacities
            .iter()
            .all(|o| *o >= F::zero() && *o <= F::one()),
        "projected opacity outside [0, 1]"
    );
    for (i, c) in p.conics.chunks_exact(3).enumerate() {
        let c = [c[0].to_f64(), c[1].to_f64(), c[2].to_f64()];
        assert!(c[0] >= 0.0 && c[2] >= 0.0, "conic {i} = {c:?}");
        if ps.eps2d > 0.0 {
            let bound = (1.0 + 1e-4) / ps.eps2d;
            assert!(
                c.iter().all(|v| v.abs() <= bound),
                "conic {i} = {c:?} exceeds 1 / eps2d = {}",
                1.0 / ps.eps2d
            );
        }
    }
    for (i, z) in cam_z.iter().enumerate() {
        if *z <= near * (1.0 - 1e-6) {
            assert_eq!(
                &p.radii[2 * i..2 * i + 2],
                &[0, 0],
                "Gaussian {i} at z={z} drawn"
            );
            assert_eq!(p.depths[i], F::zero(), "Gaussian {i} at z={z} has a depth");
        }
    }
}

/// Image outputs: finite, alpha in [0, 1], depth >= 0, and background (with zero depth)
/// exactly where alpha == 0.
fn check_image<F: real::Real>(img: &Image<F>, bg: &[F]) {
    assert_finite("out features", &img.features);
    assert_finite("out alpha", &img.alpha);
    assert_finite("out depth", &img.depth);
    let ch = bg.len();
    for (p, a) in img.alpha.iter().enumerate() {
        assert!(*a >= F::zero() && *a <= F::one(), "alpha[{p}] = {a:?}");
        assert!(img.depth[p] >= F::zero(), "depth[{p}] = {:?}", img.depth[p]);
        if *a == F::zero() {
            assert_eq!(
                &img.features[p * ch..(p + 1) * ch],
                bg,
                "pixel {p}: alpha 0 but not the background"
            );
            assert_eq!(img.depth[p], F::zero(), "pixel {p}: alpha 0 but depth");
        }
    }
}

/// Camera-space z of every Gaussian, from the inputs as the element type `F` sees them.
fn cam_z<F: real::Real>(cam: &Camera, means: &[F]) -> Vec<f64> {
    let m = &cam.world_to_camera;
    means
        .chunks_exact(3)
        .map(|v| {
            m[2][0] * v[0].to_f64() + m[2][1] * v[1].to_f64() + m[2][2] * v[2].to_f64() + m[2][3]
        })
        .collect()
}

/// Gradients of the projection inputs, given gradients of its outputs.
fn project_grads<F: real::Real>(
    g: &Gaussians<'_, F>,
    cam: &Camera,
    ps: &ProjectSettings,
    v: [&[F]; 4],
) -> [Vec<F>; 4] {
    let n = g.len();
    let mut bufs = gaussian_grad_bufs(n);
    project_backward(
        g,
        cam,
        ps,
        &ProjectionGrads {
            means2d: v[0],
            conics: v[1],
            depths: v[2],
            opacities: v[3],
        },
        gaussian_grads_mut(&mut bufs),
    )
    .unwrap();
    bufs
}

/// Splats over buffers ordered (means2d, conics, depths, opacities, features, ...).
fn splats_from<'a, F>(b: &'a [Vec<F>], radii: &'a [i32], channels: usize) -> Splats<'a, F> {
    Splats {
        means2d: &b[0],
        conics: &b[1],
        depths: &b[2],
        opacities: &b[3],
        radii,
        features: &b[4],
        channels,
    }
}

const GRAD_NAMES: [&str; 5] = [
    "grad means2d",
    "grad conics",
    "grad depths",
    "grad opacities",
    "grad features",
];
const INPUT_GRAD_NAMES: [&str; 4] = ["grad means", "grad quats", "grad scales", "grad opacities"];

/// The f32 fast path: project, composite, composite backward, project backward.
fn run_fast(s: &EdgeScene) {
    let inp = inputs(s);
    let (w, h, ch) = (s.width, s.height, s.channels);
    let npix = (w * h) as usize;
    let (means, quats, scales, ops) = (
        to_f32(&inp.means),
        to_f32(&inp.quats),
        to_f32(&inp.scales),
        to_f32(&inp.opacities),
    );
    let (feats, bg) = (to_f32(&inp.features), to_f32(&inp.background));
    let ps = s.settings;
    let bs = BlendSettings {
        alpha_max: s.alpha_max,
    };
    let p = project(&means, &quats, &scales, &ops, &inp.camera, &ps);
    check_projection(&p, &cam_z(&inp.camera, &means), &ps);

    let mut state = RasterState::new();
    let mut img = Image::<f32>::zeros(npix, ch);
    let sp = splats(&p, &feats, ch);
    let counters = rasterize_forward(&sp, w, h, &bg, &bs, &mut state, img.as_mut()).unwrap();
    check_image(&img, &bg);
    if counters.visible == 0 || ops.iter().all(|o| *o == 0.0) {
        assert!(img.alpha.iter().all(|a| *a == 0.0), "alpha without a splat");
    }

    // Upstream gradients drawn straight in f32 (no f64 copy of a 4096x4096 image).
    let mut rng = Rng::new(s.seed ^ 0x5EED);
    let mut draw =
        |len: usize| -> Vec<f32> { (0..len).map(|_| rng.uniform(-1.0, 1.0) as f32).collect() };
    let v = Image {
        features: draw(npix * ch),
        alpha: draw(npix),
        depth: draw(npix),
    };
    let [g2, gc, gd, go, gf] = splat_grads(&sp, w, h, &bg, &bs, &mut state, &v).unwrap();
    for (name, g) in GRAD_NAMES.iter().zip([&g2, &gc, &gd, &go, &gf]) {
        assert_finite(name, g);
    }
    let gauss = Gaussians {
        means: &means,
        quats: &quats,
        scales: &scales,
        opacities: &ops,
    };
    let gi = project_grads(&gauss, &inp.camera, &ps, [&g2, &gc, &gd, &go]);
    for (name, g) in INPUT_GRAD_NAMES.iter().zip(&gi) {
        assert_finite(name, g);
    }
}

/// The f64 path: project, reference composite and its backward, project backward.
fn run_reference(s: &EdgeScene) {
    let inp = inputs(s);
    let (w, h, ch) = (s.width, s.height, s.channels);
    let npix = (w * h) as usize;
    let ps = s.settings;
    let bs = BlendSettings {
        alpha_max: s.alpha_max,
    };
    let p = project(
        &inp.means,
        &inp.quats,
        &inp.scales,
        &inp.opacities,
        &inp.camera,
        &ps,
    );
    check_projection(&p, &cam_z(&inp.camera, &inp.means), &ps);
    let sp = splats(&p, &inp.features, ch);
    let mut img = Image::<f64>::zeros(npix, ch);
    let counters =
        rasterize_forward_reference(&sp, w, h, &inp.background, &bs, img.as_mut()).unwrap();
    check_image(&img, &inp.background);
    if counters.visible == 0 || inp.opacities.iter().all(|o| *o == 0.0) {
        assert!(img.alpha.iter().all(|a| *a == 0.0), "alpha without a splat");
    }
    let v = random_image_grads(npix, ch, s.seed ^ 0x5EED);
    let bg = &inp.background;
    let [g2, gc, gd, go, gf] =
        splat_grads(&sp, w, h, bg, &bs, &mut RasterState::new(), &v).unwrap();
    for (name, g) in GRAD_NAMES.iter().zip([&g2, &gc, &gd, &go, &gf]) {
        assert_finite(name, g);
    }
    let gauss = Gaussians {
        means: &inp.means,
        quats: &inp.quats,
        scales: &inp.scales,
        opacities: &inp.opacities,
    };
    let gi = project_grads(&gauss, &inp.camera, &ps, [&g2, &gc, &gd, &go]);
    for (name, g) in INPUT_GRAD_NAMES.iter().zip(&gi) {
        assert_finite(name, g);
    }
}

fn sh_dir() -> impl Strategy<Value = [f64; 3]> {
    let d = [-1.0f64..1.0, -1.0f64..1.0, -1.0f64..1.0];
    prop_oneof![
        3 => d.clone(),
        1 => Just([0.0; 3]),
        1 => d.clone().prop_map(|d| d.map(|v| v * 1e-30)),
        1 => d.prop_map(|d| d.map(|v| v * 1e30)),
        1 => Just([F32_MAX, -F32_MAX, F32_MAX]),
    ]
}

fn run_sh<F: real::Real>(degree: u32, dirs: &[[f64; 3]], bases: usize, ch: usize, seed: u64) {
    let n = dirs.len();
    let mut rng = Rng::new(seed);
    let d: Vec<F> = dirs.iter().flatten().map(|v| F::from_f64(*v)).collect();
    let coeffs: Vec<F> = (0..n * bases * ch)
        .map(|_| F::from_f64(rng.uniform(-1.0, 1.0)))
        .collect();
    let mut out = vec![F::zero(); n * ch];
    sh_forward(degree, &d, &coeffs, bases, ch, &mut out).unwrap();
    assert_finite("sh out", &out);
    let v: Vec<F> = (0..n * ch)
        .map(|_| F::from_f64(rng.uniform(-1.0, 1.0)))
        .collect();
    let (mut vd, mut vc) = (vec![F::zero(); 3 * n], vec![F::zero(); n * bases * ch]);
    sh_backward(degree, &d, &coeffs, bases, ch, &v, &mut vd, &mut vc).unwrap();
    assert_finite("sh grad dirs", &vd);
    assert_finite("sh grad coeffs", &vc);
}

proptest! {
    // 64 cases each (a few seconds); PROPTEST_CASES=N runs more. A fixed seed keeps CI
    // deterministic; PROPTEST_RNG_SEED=N explores other cases.
    #![proptest_config(ProptestConfig {
        cases: std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(64),
        rng_seed: proptest::test_runner::RngSeed::Fixed(
            std::env::var("PROPTEST_RNG_SEED").ok().and_then(|v| v.parse().ok()).unwrap_or(20_261_123),
        ),
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// f32 fast path on edge-case scenes up to 70x70 (and 1x70, 70x1, 1x17, 1x1).
    #[test]
    fn fast_path_edge_scenes_stay_finite(s in edge_scene(24, 70, false)) {
        run_fast(&s);
    }

    /// Wide and tall one-pixel strips of 300 pixels.
    #[test]
    fn fast_path_strips_stay_finite(
        s in edge_scene(12, 8, false),
        tall in any::<bool>(),
    ) {
        let mut s = s;
        (s.width, s.height) = if tall { (1, 300) } else { (300, 1) };
        run_fast(&s);
    }

    /// f64 projection + reference compositor on small images, with scales beyond f32's range.
    #[test]
    fn reference_path_edge_scenes_stay_finite(s in edge_scene(12, 24, true)) {
        run_reference(&s);
    }

    /// Spherical harmonics at zero, tiny and huge view directions.
    #[test]
    fn sh_edge_directions_stay_finite(
        degree in 0u32..=3,
        dirs in prop::collection::vec(sh_dir(), 0..8),
        extra in 0usize..3,
        ch in 1usize..=4,
        seed in any::<u64>(),
    ) {
        let bases = sh::num_bases(degree) + extra;
        run_sh::<f32>(degree, &dirs, bases, ch, seed);
        run_sh::<f64>(degree, &dirs, bases, ch, seed);
    }
}

// ---------------------------------------------------------------------------------------------
// Dedicated cases.
// ---------------------------------------------------------------------------------------------

fn g(mean_cam: [f64; 3], scale: [f64; 3], opacity: f64) -> G {
    G {
        mean_cam,
        quat: [0.9, 0.1, -0.2, 0.3],
        scale,
        opacity,
    }
}

/// A 4096x4096 image with a handful of edge-case Gaussians, one channel (about 0.5 GB peak).
#[test]
fn large_image_4096_stays_finite() {
    let gs = vec![
        g([0.0, 0.0, 3.0], [0.2, 0.1, 0.05], 0.8),
        g([0.0, 0.0, 3.0], [0.2, 0.1, 0.05], 1.0), // coincident, opaque
        g([0.3, -0.2, 2.0], [0.0, 0.0, 0.0], 1.0), // zero scale
        g([-0.5, 0.4, 4.0], [1e30, 1e30, 1e30], 0.5), // huge
        g([0.1, 0.1, NEAR], [0.1, 0.1, 0.1], 1.0), // on the near plane
        g([0.1, 0.1, 0.0], [0.1, 0.1, 0.1], 1.0),  // on the camera plane
        g([0.2, 0.0, -1.0], [0.1, 0.1, 0.1], 1.0), // behind
        g([0.4, 0.3, 5.0], [1e-6, 1e3, 1e3], 0.0), // disc, transparent
    ];
    let s = EdgeScene {
        gs,
        width: 4096,
        height: 4096,
        channels: 1,
        cam_seed: None,
        focal: 0.9,
        settings: ProjectSettings {
            near: NEAR,
            ..Default::default()
        },
        alpha_max: 0.99,
        seed: 7,
    };
    run_fast(&s);
}

/// Many coincident opaque Gaussians: every pixel saturates and stops early.
#[test]
fn coincident_opaque_stack_stays_finite() {
    for (w, h) in [(1, 1), (16, 16), (37, 5)] {
        let s = EdgeScene {
            gs: vec![g([0.0, 0.0, 2.0], [0.5, 0.5, 0.5], 1.0); 300],
            width: w,
            height: h,
            channels: 3,
            cam_seed: None,
            focal: 0.9,
            settings: ProjectSettings::default(),
            alpha_max: 0.999,
            seed: 3,
        };
        run_fast(&s);
        run_reference(&s);
    }
}

/// Regressions found by the properties above: needles so long that f64 loses their width
/// (their conic came out ~1e37 and indefinite, their gradients NaN or inf) get no projection;
/// shorter needles and huge well-conditioned Gaussians are still drawn.
#[test]
fn ill_conditioned_needles_are_culled_and_others_kept() {
    let scene = |gs: Vec<G>, (width, height): (u32, u32), eps2d: f64| EdgeScene {
        gs,
        width,
        height,
        channels: 1,
        cam_seed: None,
        focal: 0.9,
        settings: ProjectSettings {
            near: NEAR,
            eps2d,
            ..Default::default()
        },
        alpha_max: 0.99,
        seed: 0,
    };
    let needle = |mean_cam, quat, scale| G {
        mean_cam,
        quat,
        scale,
        opacity: 1.0,
    };
    let cases = [
        // Conic ~4e37 and indefinite: NaN means2d gradients.
        scene(
            vec![needle(
                [-0.249, 0.0, 0.657],
                [0.45297483, 0.56187649, 0.0, 0.0],
                [0.4965853, 1.0, 1.4936737e11],
            )],
            (300, 1),
            0.3,
        ),
        // Gradient noise ~1e48: inf mean gradients.
        scene(
            vec![needle(
                [0.0, 0.0, 3.3196990],
                [-0.31772973, 0.0, 0.0, 0.94818132],
                [0.4965853, 1e30, 0.4965853],
            )],
            (300, 1),
            0.3,
        ),
        // eps2d = 0: a degenerate (rank-1) needle.
        scene(
            vec![needle(
                [0.0, 0.0, 2.0],
                [0.9, 0.1, -0.2, 0.3],
                [0.0, 0.0, 1e10],
            )],
            (40, 30),
            0.0,
        ),
    ];
    for s in &cases {
        run_fast(s);
        run_reference(s);
        let inp = inputs(s);
        let p = project(
            &inp.means,
            &inp.quats,
            &inp.scales,
            &inp.opacities,
            &inp.camera,
            &s.settings,
        );
        assert_eq!(p.radii, vec![0, 0], "ill-conditioned needle was drawn");
    }
    // Kept: a needle ~700 px long (sigma) and a Gaussian enclosing the camera.
    let s = scene(
        vec![
            needle([0.0, 0.0, 2.0], [0.9, 0.1, -0.2, 0.3], [0.0, 0.0, 40.0]),
            needle([0.0, 0.0, 2.0], [0.9, 0.1, -0.2, 0.3], [1e30, 1e30, 1e30]),
        ],
        (40, 30),
        0.3,
    );
    run_fast(&s);
    let inp = inputs(&s);
    let p = project_f32(
        &inp.means,
        &inp.quats,
        &inp.scales,
        &inp.opacities,
        &inp.camera,
        &s.settings,
    );
    assert!(p.radii.iter().all(|r| *r > 0), "radii {:?}", p.radii);
}

/// Splats whose sigma overflows to NaN (inf - inf, from huge finite conics) are skipped by both
/// compositors: the f64 reference used to draw them at alpha_max, whatever their opacity, and
/// the portable f32 exponential fed the NaN to `to_int_unchecked`.
#[test]
fn nan_sigma_splats_are_skipped() {
    let (w, h) = (24u32, 20u32);
    let npix = (w * h) as usize;
    // Indefinite conics: at every pixel sigma is negative, +inf or NaN, so nothing is drawn.
    let run_f64 = |conic: [f64; 3], opacity: f64| {
        let (m, o, d, r, f) = ([12.0, 10.0], [opacity], [2.0], [16, 16], [0.7]);
        let sp = Splats {
            means2d: &m,
            conics: &conic,
            depths: &d,
            opacities: &o,
            radii: &r,
            features: &f,
            channels: 1,
        };
        let mut img = Image::<f64>::zeros(npix, 1);
        let bs = BlendSettings::default();
        rasterize_forward_reference(&sp, w, h, &[0.25], &bs, img.as_mut()).unwrap();
        check_image(&img, &[0.25]);
        assert!(img.alpha.iter().all(|a| *a == 0.0), "f64: NaN sigma drawn");
        let v = random_image_grads(npix, 1, 4);
        let [g2, gc, gd, go, gf] =
            splat_grads(&sp, w, h, &[0.25], &bs, &mut RasterState::new(), &v).unwrap();
        for (name, g) in GRAD_NAMES.iter().zip([&g2, &gc, &gd, &go, &gf]) {
            assert_finite(name, g);
        }
    };
    run_f64([1e307, 2e307, 1e307], 0.0);
    run_f64([1e307, 2e307, 1e307], 0.8);

    let conic = [1e38f32, 3e38, 1e38];
    let (m, o, d, r, f) = ([12.0f32, 10.0], [0.8f32], [2.0f32], [16, 16], [0.7f32]);
    let sp = Splats {
        means2d: &m,
        conics: &conic,
        depths: &d,
        opacities: &o,
        radii: &r,
        features: &f,
        channels: 1,
    };
    let simd = blend::simd_active();
    let mut images = Vec::new();
    for enabled in [false, true] {
        blend::set_simd_enabled(enabled);
        let mut img = Image::<f32>::zeros(npix, 1);
        rasterize_forward(
            &sp,
            w,
            h,
            &[0.25],
            &BlendSettings::default(),
            &mut RasterState::new(),
            img.as_mut(),
        )
        .unwrap();
        check_image(&img, &[0.25]);
        assert!(img.alpha.iter().all(|a| *a == 0.0), "f32: NaN sigma drawn");
        images.push(img);
    }
    blend::set_simd_enabled(simd);
    assert_eq!(images[0], images[1]);
}

// ---------------------------------------------------------------------------------------------
// NaN/inf rejection.
// ---------------------------------------------------------------------------------------------

const BAD: [f64; 3] = [f64::NAN, f64::INFINITY, f64::NEG_INFINITY];

fn expect_arg<T: std::fmt::Debug>(r: Result<T>, arg: &str, what: &str) {
    match r {
        Err(e) => assert_eq!(e.arg(), arg, "{what}: wrong argument named in `{e}`"),
        Ok(v) => panic!("{what}: accepted ({v:?})"),
    }
}

/// A valid small scene for the rejection tests.
fn valid_scene() -> Scene {
    random_scene(6, 20, 16, 3, 11)
}

fn project_with<F: real::Real>(s: &Scene, arg: &str, bad: f64) -> Result<usize> {
    let mut v: [Vec<F>; 4] = [&s.means, &s.quats, &s.scales, &s.opacities]
        .map(|x| x.iter().map(|y| F::from_f64(*y)).collect());
    let i = ["means", "quats", "scales", "opacities"]
        .iter()
        .position(|a| *a == arg)
        .unwrap();
    v[i][1] = F::from_f64(bad);
    let n = s.n();
    let mut p = Proj::<F>::zeros(n);
    project_forward(
        &Gaussians {
            means: &v[0],
            quats: &v[1],
            scales: &v[2],
            opacities: &v[3],
        },
        &s.camera,
        &ProjectSettings::default(),
        p.as_mut(),
    )
}

#[test]
fn non_finite_projection_inputs_are_rejected() {
    let s = valid_scene();
    for bad in BAD {
        for arg in ["means", "quats", "scales", "opacities"] {
            expect_arg(project_with::<f32>(&s, arg, bad), arg, "f32 project");
            expect_arg(project_with::<f64>(&s, arg, bad), arg, "f64 project");
        }
        // Camera and settings.
        let m = s.camera.world_to_camera;
        let view: Vec<f64> = m.iter().flatten().copied().collect();
        for i in [0, 3, 10, 11, 15] {
            let mut v = view.clone();
            v[i] = bad;
            let c = s.camera;
            expect_arg(
                Camera::new(&v, c.fx, c.fy, c.cx, c.cy, c.width, c.height),
                "viewmat",
                "viewmat",
            );
        }
        for (field, arg) in [(0, "K (fx)"), (1, "K (fy)"), (2, "K"), (3, "K")] {
            let mut c = s.camera;
            *[&mut c.fx, &mut c.fy, &mut c.cx, &mut c.cy][field] = bad;
            expect_arg(c.validate(), arg, "intrinsics");
        }
        let ok = ProjectSettings::default();
        expect_arg(
            ProjectSettings { near: bad, ..ok }.validate(),
            "near",
            "near",
        );
        expect_arg(
            ProjectSettings { eps2d: bad, ..ok }.validate(),
            "eps2d",
            "eps2d",
        );
        expect_arg(
            BlendSettings { alpha_max: bad }.validate(),
            "alpha_max",
            "alpha_max",
        );
    }
    let ok = ProjectSettings::default();
    expect_arg(
        ProjectSettings {
            far: f64::NAN,
            ..ok
        }
        .validate(),
        "far",
        "far",
    );
}

const SPLAT_ARGS: [&str; 6] = [
    "means2d",
    "conics",
    "depths",
    "opacities",
    "features",
    "background",
];

#[test]
fn non_finite_splat_inputs_are_rejected() {
    let s = valid_scene();
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let (w, h, ch) = (s.camera.width, s.camera.height, s.channels);
    let npix = (w * h) as usize;
    let (p64, _) = render_reference(&s, &ps, &bs);
    for bad in BAD {
        for (ai, arg) in SPLAT_ARGS.iter().enumerate() {
            let mut bufs: [Vec<f64>; 6] = [
                p64.means2d.clone(),
                p64.conics.clone(),
                p64.depths.clone(),
                p64.opacities.clone(),
                s.features.clone(),
                s.background.clone(),
            ];
            bufs[ai][1] = bad;
            let sp = splats_from(&bufs, &p64.radii, ch);
            let mut img = Image::<f64>::zeros(npix, ch);
            let r = rasterize_forward_reference(&sp, w, h, &bufs[5], &bs, img.as_mut());
            expect_arg(r, arg, "reference forward");

            let b32 = bufs.clone().map(|b| to_f32(&b));
            let sp = splats_from(&b32, &p64.radii, ch);
            let mut img = Image::<f32>::zeros(npix, ch);
            let r = rasterize_forward(
                &sp,
                w,
                h,
                &b32[5],
                &bs,
                &mut RasterState::new(),
                img.as_mut(),
            );
            expect_arg(r, arg, "fast forward");
        }
    }
}

#[test]
fn non_finite_upstream_gradients_are_rejected() {
    let s = valid_scene();
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let (w, h, ch) = (s.camera.width, s.camera.height, s.channels);
    let npix = (w * h) as usize;
    let (p64, _) = render_reference(&s, &ps, &bs);
    let mut state = RasterState::new();
    let (p32, _, _) = render_fast(&s, &ps, &bs, &mut state);
    let (f32s, bg32) = (to_f32(&s.features), to_f32(&s.background));
    let n = s.n();
    for bad in BAD {
        for (ai, arg) in ["v_features", "v_alpha", "v_depth"].iter().enumerate() {
            let mut v = random_image_grads(npix, ch, 1);
            [&mut v.features, &mut v.alpha, &mut v.depth][ai][1] = bad;
            let mut gb = splat_grad_bufs::<f64>(n, ch);
            let r = rasterize_backward_reference(
                &splats(&p64, &s.features, ch),
                w,
                h,
                &s.background,
                &bs,
                &v.as_grads(),
                grads_mut(&mut gb),
            );
            expect_arg(r, arg, "reference backward");

            let (vf, va, vd) = (to_f32(&v.features), to_f32(&v.alpha), to_f32(&v.depth));
            let mut gb = splat_grad_bufs::<f32>(n, ch);
            let r = rasterize_backward(
                &splats(&p32, &f32s, ch),
                w,
                h,
                &bg32,
                &bs,
                &mut state,
                &ImageGrads {
                    features: &vf,
                    alpha: &va,
                    depth: &vd,
                },
                grads_mut(&mut gb),
            );
            expect_arg(r, arg, "fast backward");
        }
    }
}

#[test]
fn non_finite_sh_inputs_are_rejected() {
    let (n, bases, ch) = (4usize, 9usize, 3usize);
    let dirs: Vec<f64> = (0..3 * n).map(|i| (i as f64 * 0.7).sin()).collect();
    let coeffs: Vec<f64> = (0..n * bases * ch)
        .map(|i| (i as f64 * 0.3).cos())
        .collect();
    for bad in BAD {
        for arg in ["dirs", "coeffs"] {
            let (mut d, mut c) = (dirs.clone(), coeffs.clone());
            if arg == "dirs" {
                d[4] = bad;
            } else {
                c[7] = bad;
            }
            let mut out = vec![0.0; n * ch];
            expect_arg(sh_forward(2, &d, &c, bases, ch, &mut out), arg, "f64 sh");
            let (d32, c32) = (to_f32(&d), to_f32(&c));
            let mut out = vec![0.0f32; n * ch];
            expect_arg(
                sh_forward(2, &d32, &c32, bases, ch, &mut out),
                arg,
                "f32 sh",
            );
        }
        let mut v = vec![0.5; n * ch];
        v[2] = bad;
        let (mut vd, mut vc) = (vec![0.0; 3 * n], vec![0.0; n * bases * ch]);
        expect_arg(
            sh_backward(2, &dirs, &coeffs, bases, ch, &v, &mut vd, &mut vc),
            "v_out",
            "sh backward",
        );
    }
}
