//! Finite-difference checks (f64) of every backward: projection, the reference compositor, the
//! whole pipeline, and spherical harmonics.

use sync4d_raster::*;
use sync4d_testing::*;

/// Analytic gradients of `weighted(render(scene), w)` w.r.t. (means, quats, scales, opacities,
/// features) through projection + reference compositing.
fn pipeline_grads(
    s: &Scene,
    ps: &ProjectSettings,
    bs: &BlendSettings,
    w: &Image<f64>,
) -> [Vec<f64>; 5] {
    let (p, _) = render_reference(s, ps, bs);
    let n = s.n();
    let [g2, gc, gd, go, gf] = reference_splat_grads(&p, s, bs, w);
    let mut bufs = gaussian_grad_bufs(n);
    project_backward(
        &s.gaussians(),
        &s.camera,
        ps,
        &ProjectionGrads {
            means2d: &g2,
            conics: &gc,
            depths: &gd,
            opacities: &go,
        },
        gaussian_grads_mut(&mut bufs),
    )
    .unwrap();
    let [vm, vq, vs, vo] = bufs;
    [vm, vq, vs, vo, gf]
}

fn check_pipeline(antialiased: bool, seed: u64) {
    let s = random_scene(14, 40, 32, 3, seed);
    let ps = ProjectSettings {
        antialiased,
        ..Default::default()
    };
    let bs = BlendSettings::default();
    let npix = 40 * 32;
    let w = random_image_grads(npix, s.channels, seed + 1);
    let grads = pipeline_grads(&s, &ps, &bs, &w);
    let names = ["means", "quats", "scales", "opacities", "features"];
    for (which, name) in names.iter().enumerate() {
        let x0 = match which {
            0 => s.means.clone(),
            1 => s.quats.clone(),
            2 => s.scales.clone(),
            3 => s.opacities.clone(),
            _ => s.features.clone(),
        };
        let mut f = |x: &[f64]| {
            let mut t = s.clone();
            match which {
                0 => t.means = x.to_vec(),
                1 => t.quats = x.to_vec(),
                2 => t.scales = x.to_vec(),
                3 => t.opacities = x.to_vec(),
                _ => t.features = x.to_vec(),
            }
            weighted(&render_reference(&t, &ps, &bs).1, &w)
        };
        let fd = finite_diff(&x0, 1e-6, &mut f);
        let floor = grads[which].iter().fold(0.0f64, |a, b| a.max(b.abs())) * 1e-3;
        assert_grad_close(
            &format!("{name} (antialiased={antialiased})"),
            &grads[which],
            &fd,
            1e-4,
            floor.max(1e-9),
            0.05,
        );
    }
}

#[test]
fn pipeline_gradients_match_finite_differences() {
    check_pipeline(false, 7);
}

#[test]
fn pipeline_gradients_match_finite_differences_antialiased() {
    check_pipeline(true, 11);
}

/// The compositing stage alone, w.r.t. its own inputs (means2d, conics, depths, opacities).
#[test]
fn compositor_gradients_match_finite_differences() {
    let s = random_scene(16, 36, 30, 2, 3);
    let ps = ProjectSettings::default();
    let bs = BlendSettings { alpha_max: 0.99 };
    let (p, _) = render_reference(&s, &ps, &bs);
    let n = s.n();
    let w = random_image_grads(36 * 30, 2, 5);
    let mut bufs = splat_grad_bufs(n, 2);
    rasterize_backward_reference(
        &splats(&p, &s.features, 2),
        36,
        30,
        &s.background,
        &bs,
        &w.as_grads(),
        grads_mut(&mut bufs),
    )
    .unwrap();
    let [g2, gc, gd, go, _] = bufs;
    let render = |q: &Proj<f64>| {
        let mut img = Image::zeros(36 * 30, 2);
        rasterize_forward_reference(
            &splats(q, &s.features, 2),
            36,
            30,
            &s.background,
            &bs,
            img.as_mut(),
        )
        .unwrap();
        weighted(&img, &w)
    };
    for (name, analytic) in [
        ("means2d", &g2),
        ("conics", &gc),
        ("depths", &gd),
        ("opacities", &go),
    ] {
        let x0 = match name {
            "means2d" => p.means2d.clone(),
            "conics" => p.conics.clone(),
            "depths" => p.depths.clone(),
            _ => p.opacities.clone(),
        };
        let mut f = |x: &[f64]| {
            let mut q = p.clone();
            match name {
                "means2d" => q.means2d = x.to_vec(),
                "conics" => q.conics = x.to_vec(),
                "depths" => q.depths = x.to_vec(),
                _ => q.opacities = x.to_vec(),
            }
            render(&q)
        };
        let fd = finite_diff(&x0, 1e-7, &mut f);
        let floor = analytic.iter().fold(0.0f64, |a, b| a.max(b.abs())) * 1e-3;
        assert_grad_close(name, analytic, &fd, 1e-4, floor.max(1e-9), 0.05);
    }
}

#[test]
fn projection_gradients_match_finite_differences() {
    // Include Gaussians off the side of the frustum so the clamped Jacobian branch is exercised.
    let mut s = random_scene(20, 64, 48, 1, 21);
    for i in 0..4 {
        s.means[3 * i] = 3.0 + i as f64;
    }
    for antialiased in [false, true] {
        let ps = ProjectSettings {
            antialiased,
            ..Default::default()
        };
        let n = s.n();
        let mut rng = Rng::new(99);
        let v2: Vec<f64> = (0..2 * n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let vc: Vec<f64> = (0..3 * n).map(|_| rng.uniform(-30.0, 30.0)).collect();
        let vd: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let vo: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let loss = |p: &Proj<f64>| {
            let d = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
            d(&p.means2d, &v2) + d(&p.conics, &vc) + d(&p.depths, &vd) + d(&p.opacities, &vo)
        };
        let mut bufs = gaussian_grad_bufs(n);
        project_backward(
            &s.gaussians(),
            &s.camera,
            &ps,
            &ProjectionGrads {
                means2d: &v2,
                conics: &vc,
                depths: &vd,
                opacities: &vo,
            },
            gaussian_grads_mut(&mut bufs),
        )
        .unwrap();
        let [gm, gq, gs, go] = bufs;
        for (name, analytic, x0) in [
            ("means", &gm, s.means.clone()),
            ("quats", &gq, s.quats.clone()),
            ("scales", &gs, s.scales.clone()),
            ("opacities", &go, s.opacities.clone()),
        ] {
            let mut f = |x: &[f64]| {
                let mut t = s.clone();
                match name {
                    "means" => t.means = x.to_vec(),
                    "quats" => t.quats = x.to_vec(),
                    "scales" => t.scales = x.to_vec(),
                    _ => t.opacities = x.to_vec(),
                }
                loss(&project(
                    &t.means,
                    &t.quats,
                    &t.scales,
                    &t.opacities,
                    &t.camera,
                    &ps,
                ))
            };
            let fd = finite_diff(&x0, 1e-6, &mut f);
            let floor = analytic.iter().fold(0.0f64, |a, b| a.max(b.abs())) * 1e-3;
            assert_grad_close(
                &format!("projection {name} aa={antialiased}"),
                analytic,
                &fd,
                1e-4,
                floor.max(1e-9),
                0.0,
            );
        }
    }
}

#[test]
fn sh_gradients_match_finite_differences() {
    let mut rng = Rng::new(4);
    for degree in 0..=3u32 {
        let (n, bases, ch) = (6, 16, 3);
        let dirs: Vec<f64> = (0..3 * n).map(|_| rng.normal()).collect();
        let coeffs: Vec<f64> = (0..n * bases * ch).map(|_| rng.normal()).collect();
        let w: Vec<f64> = (0..n * ch).map(|_| rng.normal()).collect();
        let eval = |d: &[f64], c: &[f64]| {
            let mut out = vec![0.0; n * ch];
            sh_forward(degree, d, c, bases, ch, &mut out).unwrap();
            out.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let (mut vd, mut vc) = (vec![0.0; 3 * n], vec![0.0; n * bases * ch]);
        sh_backward(degree, &dirs, &coeffs, bases, ch, &w, &mut vd, &mut vc).unwrap();
        let fd_d = finite_diff(&dirs, 1e-6, &mut |x| eval(x, &coeffs));
        let fd_c = finite_diff(&coeffs, 1e-6, &mut |x| eval(&dirs, x));
        if degree > 0 {
            assert_grad_close(
                &format!("sh dirs deg {degree}"),
                &vd,
                &fd_d,
                1e-5,
                1e-4,
                0.0,
            );
        } else {
            assert!(
                vd.iter().all(|v| *v == 0.0),
                "degree 0 does not depend on the direction"
            );
        }
        assert_grad_close(
            &format!("sh coeffs deg {degree}"),
            &vc,
            &fd_c,
            1e-5,
            1e-4,
            0.0,
        );
    }
}

/// Known values: degree 1 along +z gives the constant term plus 0.4886 * coeff[2].
#[test]
fn sh_known_values() {
    let dirs = [0.0, 0.0, 2.0];
    let mut coeffs = vec![0.0; 4];
    coeffs[0] = 1.0;
    coeffs[2] = 1.0;
    let mut out = [0.0f64; 1];
    sh_forward(1, &dirs, &coeffs, 4, 1, &mut out).unwrap();
    assert!((out[0] - (0.282_094_791_773_878_1 + 0.488_602_511_902_92)).abs() < 1e-12);
}
