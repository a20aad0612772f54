//! The tiled f32 fast path against the f64 reference: forward outputs, gradients, determinism
//! across runs and thread counts, and work counters.

use sync4d_raster::*;
use sync4d_testing::*;

fn max_abs(a: &[f32], b: &[f64]) -> f64 {
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((*x as f64 - y).abs()))
}

fn fast_backward(
    p: &Proj<f32>,
    s: &Scene,
    bs: &BlendSettings,
    state: &mut RasterState,
    w: &Image<f64>,
) -> [Vec<f32>; 5] {
    let feats = to_f32(&s.features);
    let w32 = Image {
        features: to_f32(&w.features),
        alpha: to_f32(&w.alpha),
        depth: to_f32(&w.depth),
    };
    let (width, height) = (s.camera.width, s.camera.height);
    let sp = splats(p, &feats, s.channels);
    splat_grads(&sp, width, height, &to_f32(&s.background), bs, state, &w32).unwrap()
}

/// Relative L2 error of a whole gradient tensor.
fn rel_l2(a: &[f32], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (*x as f64 - y).powi(2)).sum();
    let den: f64 = b.iter().map(|y| y * y).sum();
    (num / den.max(1e-300)).sqrt()
}

fn check_scene(n: usize, width: u32, height: u32, ch: usize, seed: u64, antialiased: bool) {
    let s = random_scene(n, width, height, ch, seed);
    let ps = ProjectSettings {
        antialiased,
        ..Default::default()
    };
    let bs = BlendSettings::default();
    let (pr, ir) = render_reference(&s, &ps, &bs);
    let mut state = RasterState::new();
    let (pf, imf, counters) = render_fast(&s, &ps, &bs, &mut state);
    assert_eq!(
        pf.radii, pr.radii,
        "radii differ between f32 and f64 projection"
    );
    assert!(counters.blended > 0 && counters.visible > 0);
    let e_img = max_abs(&imf.features, &ir.features);
    let e_alpha = max_abs(&imf.alpha, &ir.alpha);
    let e_depth = max_abs(&imf.depth, &ir.depth);
    eprintln!("n={n} {width}x{height} C={ch} aa={antialiased}: max abs err image {e_img:.2e} alpha {e_alpha:.2e} depth {e_depth:.2e}; {counters:?}");
    assert!(
        e_img <= 1e-4 && e_alpha <= 1e-4,
        "forward differs: {e_img} {e_alpha}"
    );
    assert!(e_depth <= 1e-3, "depth differs: {e_depth}");

    let w = random_image_grads((width * height) as usize, ch, seed + 100);
    let gf = fast_backward(&pf, &s, &bs, &mut state, &w);
    let gr = reference_splat_grads(&pr, &s, &bs, &w);
    for (name, (a, b)) in ["means2d", "conics", "depths", "opacities", "features"]
        .iter()
        .zip(gf.iter().zip(gr.iter()))
    {
        let e = rel_l2(a, b);
        eprintln!("  grad {name}: rel L2 {e:.2e}");
        assert!(e <= 1e-3, "grad {name}: relative L2 error {e:.2e}");
    }
}

#[test]
fn fast_matches_reference_small() {
    check_scene(60, 70, 45, 3, 1, false);
}

#[test]
fn fast_matches_reference_antialiased_wide_channels() {
    check_scene(80, 50, 40, 7, 2, true);
}

#[test]
fn fast_matches_reference_one_channel_dense() {
    check_scene(400, 64, 64, 1, 3, false);
}

#[test]
fn fast_is_deterministic_across_runs_and_threads() {
    let s = random_scene(3000, 96, 80, 3, 5);
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let mut state = RasterState::new();
            let (p, img, c) = render_fast(&s, &ps, &bs, &mut state);
            let w = random_image_grads(96 * 80, 3, 9);
            let g = fast_backward(&p, &s, &bs, &mut state, &w);
            (img, c, g)
        })
    };
    let a = run(1);
    let b = run(2);
    let c = run(2);
    assert_eq!(a.0, b.0, "image differs between 1 and 2 threads");
    assert_eq!(b.0, c.0, "image differs run to run");
    assert_eq!(a.1, b.1);
    for i in 0..5 {
        assert_eq!(
            a.2[i], b.2[i],
            "gradient {i} differs between 1 and 2 threads"
        );
        assert_eq!(b.2[i], c.2[i], "gradient {i} differs run to run");
    }
}

/// Reusing one state across calls of different sizes gives the same answer as a fresh state.
#[test]
fn state_reuse_is_clean() {
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let mut state = RasterState::new();
    let big = random_scene(500, 120, 90, 4, 8);
    let small = random_scene(50, 33, 17, 4, 9);
    let _ = render_fast(&big, &ps, &bs, &mut state);
    let (_, reused, _) = render_fast(&small, &ps, &bs, &mut state);
    let (_, fresh, _) = render_fast(&small, &ps, &bs, &mut RasterState::new());
    assert_eq!(reused, fresh);
}

#[test]
fn empty_scene_gives_background() {
    let s = random_scene(0, 20, 10, 3, 1);
    let mut state = RasterState::new();
    let (_, img, c) = render_fast(
        &s,
        &ProjectSettings::default(),
        &BlendSettings::default(),
        &mut state,
    );
    assert_eq!(c, Counters::default());
    for px in img.features.chunks(3) {
        for (v, b) in px.iter().zip(&s.background) {
            assert_eq!(*v as f64, *b as f32 as f64);
        }
    }
    assert!(img.alpha.iter().all(|a| *a == 0.0));
}

#[test]
fn backward_without_forward_is_an_error() {
    let s = random_scene(5, 20, 10, 3, 1);
    let p = project_f32(
        &s.means,
        &s.quats,
        &s.scales,
        &s.opacities,
        &s.camera,
        &ProjectSettings::default(),
    );
    let w = random_image_grads(200, 3, 1);
    let r = std::panic::catch_unwind(|| {
        let mut st = RasterState::new();
        let feats = to_f32(&s.features);
        let (wf, wa, wd) = (to_f32(&w.features), to_f32(&w.alpha), to_f32(&w.depth));
        let (mut g2, mut gc, mut gd, mut go, mut gf) = (
            vec![0.0; 10],
            vec![0.0; 15],
            vec![0.0; 5],
            vec![0.0; 5],
            vec![0.0; 15],
        );
        rasterize_backward(
            &splats(&p, &feats, 3),
            20,
            10,
            &[0.0; 3],
            &BlendSettings::default(),
            &mut st,
            &ImageGrads {
                features: &wf,
                alpha: &wa,
                depth: &wd,
            },
            SplatGradsMut {
                means2d: &mut g2,
                conics: &mut gc,
                depths: &mut gd,
                opacities: &mut go,
                features: &mut gf,
            },
        )
    });
    let err = r.expect("no panic").unwrap_err();
    assert_eq!(err.arg(), "state");
}

/// The AVX2 row kernels and the portable ones are bit-identical, forward and backward.
#[test]
fn simd_and_portable_paths_are_bit_identical() {
    let s = random_scene(2000, 80, 72, 3, 12);
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let run = || {
        let mut state = RasterState::new();
        let (p, img, c) = render_fast(&s, &ps, &bs, &mut state);
        let w = random_image_grads(80 * 72, 3, 2);
        let g = fast_backward(&p, &s, &bs, &mut state, &w);
        (img, c, g)
    };
    let with_simd = run();
    blend::set_simd_enabled(false);
    let portable = run();
    blend::set_simd_enabled(true);
    assert_eq!(with_simd.0, portable.0);
    assert_eq!(with_simd.1, portable.1);
    for i in 0..5 {
        assert_eq!(with_simd.2[i], portable.2[i], "gradient {i}");
    }
}
