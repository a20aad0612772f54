//! The wgpu path against the CPU path on random scenes: projection outputs, composited
//! images and work counters. Runs on whatever adapter `AdapterChoice::Auto` finds (lavapipe in
//! CI). Without any adapter the tests print why and pass, unless `SYNC4D_REQUIRE_GPU=1`
//! (set by `make test`), which turns a missing adapter into a failure.

use std::sync::{Mutex, OnceLock};
use sync4d_gpu::{
    AdapterChoice, BlendLayout, ColumnHalves, CompositingWindow, GpuDevice, GpuRasterState,
    GpuRasterizer,
};
use sync4d_raster::*;
use sync4d_testing::*;

/// A device on the adapter `AdapterChoice::Auto` picks; None (the caller skips) when there is
/// none, unless `SYNC4D_REQUIRE_GPU=1`, which makes that a failure.
fn open_device() -> Option<GpuDevice> {
    match GpuDevice::new(AdapterChoice::Auto) {
        Ok(dev) => {
            eprintln!("wgpu adapter: {}", dev.adapter);
            Some(dev)
        }
        Err(e) => {
            assert!(
                !std::env::var("SYNC4D_REQUIRE_GPU").is_ok_and(|v| v == "1"),
                "SYNC4D_REQUIRE_GPU=1 but {e}"
            );
            eprintln!("skipping wgpu tests: {e}");
            None
        }
    }
}

/// One rasterizer shared by the tests (kernel compilation is the slow part on lavapipe).
fn gpu() -> Option<&'static Mutex<GpuRasterizer>> {
    static GPU: OnceLock<Option<Mutex<GpuRasterizer>>> = OnceLock::new();
    GPU.get_or_init(|| open_device().map(|dev| Mutex::new(GpuRasterizer::new(dev))))
        .as_ref()
}

/// Compositing layouts every adapter must run identically: the GPU one (one pixel per
/// invocation, atomic gradient sums), the CPU-adapter one (many pixels, row blocks, partial
/// sums) and mixed ones; see [`layouts`] for the subgroup one.
const LAYOUTS: [BlendLayout; 6] = [
    BlendLayout::ONE_PIXEL,
    BlendLayout {
        pixels_per_invocation: 32,
        partials: true,
        block_rows: 16,
        subgroup_sums: false,
        column_halves: ColumnHalves::Never,
        float_atomics: false,
    },
    BlendLayout {
        pixels_per_invocation: 16,
        partials: true,
        block_rows: 0,
        subgroup_sums: false,
        column_halves: ColumnHalves::Never,
        float_atomics: false,
    },
    BlendLayout {
        pixels_per_invocation: 8,
        partials: true,
        block_rows: 4,
        subgroup_sums: false,
        column_halves: ColumnHalves::Never,
        float_atomics: false,
    },
    BlendLayout {
        pixels_per_invocation: 4,
        partials: false,
        block_rows: 8,
        subgroup_sums: false,
        column_halves: ColumnHalves::Never,
        float_atomics: false,
    },
    BlendLayout {
        pixels_per_invocation: 32,
        partials: true,
        block_rows: 4,
        subgroup_sums: false,
        column_halves: ColumnHalves::Always,
        float_atomics: false,
    },
];

/// [`LAYOUTS`] (gradient sums by compare-and-swap), plus the CPU-adapter layout with subgroup
/// gradient sums where the device has subgroups that hold its workgroup, and layouts with
/// float atomic gradient sums where it has those (lavapipe: both; its small-splat layout has
/// both).
fn layouts(r: &GpuRasterizer) -> Vec<BlendLayout> {
    let mut all = LAYOUTS.to_vec();
    let floats = r.device().float_atomics;
    let sub = BlendLayout {
        subgroup_sums: true,
        ..LAYOUTS[1]
    };
    if r.device().subgroup_min_size.is_some_and(|m| m >= 8) {
        all.push(sub);
        // lavapipe's layout for small splats.
        all.push(BlendLayout {
            column_halves: ColumnHalves::Always,
            float_atomics: floats,
            ..sub
        });
    } else {
        eprintln!("no subgroups of 8 or more on this device: skipping {sub:?}");
    }
    if floats {
        // The GPU layout, whose backward adds every splat's sums from every tile.
        all.push(BlendLayout {
            float_atomics: true,
            ..LAYOUTS[0]
        });
    } else {
        eprintln!("no f32 atomics on this device: the float-atomic layouts are skipped");
    }
    all
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

fn gpu_project(r: &mut GpuRasterizer, s: &Scene, ps: &ProjectSettings) -> (Proj<f32>, usize) {
    let n = s.n();
    let (m, q, sc, o) = (
        to_f32(&s.means),
        to_f32(&s.quats),
        to_f32(&s.scales),
        to_f32(&s.opacities),
    );
    let mut p = Proj::zeros(n);
    let visible = r
        .project_forward(
            &Gaussians {
                means: &m,
                quats: &q,
                scales: &sc,
                opacities: &o,
            },
            &s.camera,
            ps,
            p.as_mut(),
        )
        .unwrap();
    (p, visible)
}

fn cpu_project(s: &Scene, ps: &ProjectSettings) -> Proj<f32> {
    let (m, q, sc, o) = (
        to_f32(&s.means),
        to_f32(&s.quats),
        to_f32(&s.scales),
        to_f32(&s.opacities),
    );
    project(&m, &q, &sc, &o, &s.camera, ps)
}

fn composite(
    r: Option<&mut GpuRasterizer>,
    p: &Proj<f32>,
    s: &Scene,
    bs: &BlendSettings,
) -> (Image<f32>, Counters) {
    let (w, h) = (s.camera.width, s.camera.height);
    let feats = to_f32(&s.features);
    let bg = to_f32(&s.background);
    let sp = splats(p, &feats, s.channels);
    let mut img = Image::zeros((w * h) as usize, s.channels);
    let counters = if let Some(r) = r {
        let mut state = GpuRasterState::new();
        r.rasterize_forward(&sp, w, h, &bg, bs, &mut state, img.as_mut())
            .unwrap()
    } else {
        let mut state = RasterState::new();
        rasterize_forward(&sp, w, h, &bg, bs, &mut state, img.as_mut()).unwrap()
    };
    (img, counters)
}

#[test]
fn projection_matches_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    for (seed, antialiased) in [(1u64, false), (2, true), (3, false)] {
        let s = random_scene(400, 96, 80, 3, seed);
        let ps = ProjectSettings {
            antialiased,
            ..Default::default()
        };
        let cpu = cpu_project(&s, &ps);
        let (gpu, _) = gpu_project(&mut r, &s, &ps);
        for i in 0..s.n() {
            let (rc, rg) = (&cpu.radii[2 * i..2 * i + 2], &gpu.radii[2 * i..2 * i + 2]);
            assert!(
                (rc[0] - rg[0]).abs() <= 1 && (rc[1] - rg[1]).abs() <= 1,
                "radii {rc:?} {rg:?}"
            );
            if rc[0] == 0 || rg[0] == 0 {
                continue;
            }
            let close = |a: f32, b: f32, what: &str| {
                let tol = 2e-4 * a.abs().max(b.abs()).max(1.0);
                assert!(
                    (a - b).abs() <= tol,
                    "seed {seed} splat {i} {what}: cpu {a} gpu {b}"
                );
            };
            close(cpu.means2d[2 * i], gpu.means2d[2 * i], "mean x");
            close(cpu.means2d[2 * i + 1], gpu.means2d[2 * i + 1], "mean y");
            for c in 0..3 {
                close(cpu.conics[3 * i + c], gpu.conics[3 * i + c], "conic");
            }
            close(cpu.depths[i], gpu.depths[i], "depth");
            close(cpu.opacities[i], gpu.opacities[i], "opacity");
        }
    }
}

/// Composite scene `s` (projected by the CPU path) on both paths with `r`'s layout and check
/// that every decision agrees: the same images (to f32 summation order), intersections and
/// blended pairs, with enough blends to mean something. Returns the wgpu counters.
fn assert_same_decisions(r: &mut GpuRasterizer, s: &Scene, seed: u64) -> Counters {
    let layout = r.blend_layout();
    let bs = BlendSettings::default();
    let p = cpu_project(s, &ProjectSettings::default());
    let (ci, cc) = composite(None, &p, s, &bs);
    let (gi, gc) = composite(Some(r), &p, s, &bs);
    assert!(
        max_abs(&ci.features, &gi.features) <= 1e-5,
        "features {layout:?} seed {seed}"
    );
    assert!(
        max_abs(&ci.alpha, &gi.alpha) <= 1e-5,
        "alpha {layout:?} seed {seed}"
    );
    assert!(
        max_abs(&ci.depth, &gi.depth) <= 1e-4,
        "depth {layout:?} seed {seed}"
    );
    assert_eq!(cc.visible, gc.visible);
    assert_eq!(cc.intersections, gc.intersections, "{layout:?} seed {seed}");
    assert_eq!(cc.blended, gc.blended, "{layout:?} seed {seed}");
    assert!(
        cc.blended > u64::from(s.camera.width * s.camera.height),
        "{layout:?} seed {seed}: too few blends to compare"
    );
    gc
}

#[test]
fn compositing_matches_the_cpu_path_exactly_in_decisions() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let default = r.blend_layout();
    for (layout, (seed, n, w, h, ch)) in layouts(&r).into_iter().flat_map(|l| {
        [
            (4u64, 300, 64, 64, 3),
            (5, 900, 130, 75, 1),
            (6, 200, 33, 47, 5),
        ]
        .map(|c| (l, c))
    }) {
        r.set_blend_layout(layout).unwrap();
        let gc = assert_same_decisions(&mut r, &random_scene(n, w, h, ch, seed), seed);
        // Each path culls pixels outside a splat's support its own way: only bounds.
        assert!(gc.evaluated >= gc.blended && gc.evaluated <= 256 * gc.intersections);
    }
    r.set_blend_layout(default).unwrap();
}

/// Needle-thin and very wide splats (axis ratios up to ~1000:1, most of them seen edge-on at an
/// angle) stress the row-block kernels' culling, which tests each splat's support ellipse
/// against a block: a block wrongly skipped would drop blends, so the decisions must still
/// be the CPU path's exactly.
#[test]
fn needle_splats_are_composited_exactly() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let default = r.blend_layout();
    for (layout, seed) in layouts(&r)
        .into_iter()
        .filter(|l| l.block_rows > 0)
        .flat_map(|l| [(l, 7u64), (l, 8)])
    {
        r.set_blend_layout(layout).unwrap();
        let mut s = random_scene(500, 120, 96, 3, seed);
        for (i, sc) in s.scales.chunks_exact_mut(3).enumerate() {
            let (long, thin) = [(8.0, 0.01), (3.0, 0.003), (20.0, 0.02)][i % 3];
            sc[0] *= long;
            sc[1] *= thin;
            sc[2] *= if i % 2 == 0 { thin } else { 1.0 };
        }
        assert_same_decisions(&mut r, &s, seed);
    }
    r.set_blend_layout(default).unwrap();
}

#[test]
fn full_forward_matches_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    for seed in [7u64, 8, 9] {
        let s = random_scene(500, 80, 72, 3, seed);
        let ps = ProjectSettings::default();
        let bs = BlendSettings::default();
        let (ci, _) = composite(None, &cpu_project(&s, &ps), &s, &bs);
        let (p, _) = gpu_project(&mut r, &s, &ps);
        let (gi, _) = composite(Some(&mut r), &p, &s, &bs);
        let err = max_abs(&ci.features, &gi.features);
        assert!(err <= 1e-4, "seed {seed}: max abs error {err}");
        assert!(max_abs(&ci.alpha, &gi.alpha) <= 1e-4);
    }
}

#[test]
fn empty_and_fully_culled_scenes() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut s = random_scene(0, 20, 20, 2, 1);
    let bs = BlendSettings::default();
    let (img, c) = composite(
        Some(&mut r),
        &cpu_project(&s, &ProjectSettings::default()),
        &s,
        &bs,
    );
    assert_eq!(c.visible, 0);
    assert!(img.features.chunks(2).all(|px| px == [0.1f32, 0.3f32]));
    s = random_scene(50, 20, 20, 2, 1);
    for z in s.means.iter_mut().skip(2).step_by(3) {
        *z = -10.0; // behind the camera
    }
    let (p, visible) = gpu_project(&mut r, &s, &ProjectSettings::default());
    assert_eq!(visible, 0);
    let (img, c) = composite(Some(&mut r), &p, &s, &bs);
    assert_eq!(c.intersections, 0);
    assert!(img.alpha.iter().all(|a| *a == 0.0));
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let s = random_scene(10, 16, 16, 3, 1);
    let mut p = cpu_project(&s, &ProjectSettings::default());
    p.opacities[3] = f32::NAN;
    let feats = to_f32(&s.features);
    let mut img = Image::zeros(256, 3);
    let err = r
        .rasterize_forward(
            &splats(&p, &feats, 3),
            16,
            16,
            &[0.0; 3],
            &BlendSettings::default(),
            &mut GpuRasterState::new(),
            img.as_mut(),
        )
        .unwrap_err();
    assert!(err.to_string().contains("opacities"), "{err}");
    // Layouts the kernels cannot be built for are errors naming the field; the layout in use
    // stays as it was.
    let before = r.blend_layout();
    for (pixels, rows, field) in [
        (3, 0, "pixels_per_invocation"),
        (512, 0, "pixels_per_invocation"),
        (32, 3, "block_rows"),
        (32, 32, "block_rows"),
        (1, 4, "block_rows"),
        (32, 0, "subgroup_sums"),
        (1, 16, "subgroup_sums"),
        (16, 16, "column_halves"),
        (32, 0, "column_halves"),
    ] {
        let bad = BlendLayout {
            pixels_per_invocation: pixels,
            partials: true,
            block_rows: rows,
            subgroup_sums: field == "subgroup_sums",
            column_halves: if field == "column_halves" {
                ColumnHalves::Always
            } else {
                ColumnHalves::Never
            },
            float_atomics: false,
        };
        let err = r.set_blend_layout(bad).unwrap_err();
        assert!(err.to_string().contains(field), "{bad:?}: {err}");
        assert_eq!(r.blend_layout(), before);
    }
    for bad in [CompositingWindow::Fixed(0), CompositingWindow::Start(0)] {
        let err = r.set_compositing_window(bad).unwrap_err().to_string();
        assert!(
            err.contains("window") && err.contains("at least 1"),
            "{err}"
        );
    }
}

/// Largest |a - b| relative to the largest |a| of the array (gradients of different splats
/// differ by orders of magnitude, so a per-array scale is the meaningful one).
fn rel_err(a: &[f32], b: &[f32]) -> f32 {
    let scale = a.iter().fold(0.0f32, |m, x| m.max(x.abs())).max(1e-12);
    max_abs(a, b) / scale
}

fn random_image(npix: usize, ch: usize, seed: u64) -> Image<f32> {
    let mut rng = Rng::new(seed);
    let mut v = || rng.uniform(-1.0, 1.0) as f32;
    Image {
        features: (0..npix * ch).map(|_| v()).collect(),
        alpha: (0..npix).map(|_| v()).collect(),
        depth: (0..npix).map(|_| 0.1 * v()).collect(),
    }
}

/// Splat gradients of the CPU path and of `r` (its current layout) on a random scene and
/// random image gradients agree to 1e-3 relative, and none is all zero.
fn check_gradients(r: &mut GpuRasterizer, seed: u64, n: usize, w: u32, h: u32, ch: usize) {
    let s = random_scene(n, w, h, ch, seed);
    let p = cpu_project(&s, &ProjectSettings::default());
    let feats = to_f32(&s.features);
    let bg = to_f32(&s.background);
    check_splat_gradients(r, &splats(&p, &feats, ch), w, h, &bg, seed);
}

/// The GPU path's image (<= 1e-4) and gradients (<= 1e-3 relative, not all zero) for `sp` in
/// a `w` x `h` image against the CPU path's, under random dL/d(image) from `seed`.
fn check_splat_gradients(
    r: &mut GpuRasterizer,
    sp: &Splats<'_, f32>,
    w: u32,
    h: u32,
    bg: &[f32],
    seed: u64,
) {
    let layout = r.blend_layout();
    let (n, ch) = (sp.len(), sp.channels);
    let bs = BlendSettings::default();
    let npix = (w * h) as usize;
    let v = random_image(npix, ch, seed);
    // CPU
    let mut cstate = RasterState::new();
    let mut cimg = Image::zeros(npix, ch);
    rasterize_forward(sp, w, h, bg, &bs, &mut cstate, cimg.as_mut()).unwrap();
    let mut cg = splat_grad_bufs::<f32>(n, ch);
    rasterize_backward(
        sp,
        w,
        h,
        bg,
        &bs,
        &mut cstate,
        &v.as_grads(),
        grads_mut(&mut cg),
    )
    .unwrap();
    // GPU
    let mut gstate = GpuRasterState::new();
    let mut img = Image::zeros(npix, ch);
    r.rasterize_forward(sp, w, h, bg, &bs, &mut gstate, img.as_mut())
        .unwrap();
    for (name, a, b) in [
        ("features", &cimg.features, &img.features),
        ("alpha", &cimg.alpha, &img.alpha),
    ] {
        let e = max_abs(a, b);
        assert!(e <= 1e-4, "{layout:?} seed {seed} image {name}: {e}");
    }
    let mut gg = splat_grad_bufs::<f32>(n, ch);
    r.rasterize_backward(
        sp,
        w,
        h,
        bg,
        &bs,
        &mut gstate,
        &v.as_grads(),
        grads_mut(&mut gg),
    )
    .unwrap();
    for (name, a, b) in [
        ("means2d", &cg[0], &gg[0]),
        ("conics", &cg[1], &gg[1]),
        ("depths", &cg[2], &gg[2]),
        ("opacities", &cg[3], &gg[3]),
        ("features", &cg[4], &gg[4]),
    ] {
        let e = rel_err(a, b);
        assert!(
            e <= 1e-3,
            "{layout:?} seed {seed} {name}: relative error {e}"
        );
        assert!(
            a.iter().any(|x| *x != 0.0),
            "{layout:?} seed {seed} {name}: all zero"
        );
    }
}

#[test]
fn compositing_gradients_match_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let default = r.blend_layout();
    for (layout, (seed, n, w, h, ch)) in layouts(&r).into_iter().flat_map(|l| {
        [
            (11u64, 300, 64, 48, 3),
            (12, 150, 40, 40, 1),
            (13, 200, 37, 29, 6),
        ]
        .map(|c| (l, c))
    }) {
        r.set_blend_layout(layout).unwrap();
        check_gradients(&mut r, seed, n, w, h, ch);
    }
    r.set_blend_layout(default).unwrap();
}

#[test]
fn projection_gradients_match_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    for (seed, antialiased) in [(21u64, false), (22, true)] {
        let s = random_scene(300, 80, 64, 3, seed);
        let ps = ProjectSettings {
            antialiased,
            ..Default::default()
        };
        let n = s.n();
        let (m, q, sc, o) = (
            to_f32(&s.means),
            to_f32(&s.quats),
            to_f32(&s.scales),
            to_f32(&s.opacities),
        );
        let g = Gaussians {
            means: &m,
            quats: &q,
            scales: &sc,
            opacities: &o,
        };
        let mut rng = Rng::new(seed);
        let mut rv = |k: usize| {
            (0..k)
                .map(|_| rng.uniform(-1.0, 1.0) as f32)
                .collect::<Vec<_>>()
        };
        let (vm, vc, vd, vo) = (rv(2 * n), rv(3 * n), rv(n), rv(n));
        let vout = ProjectionGrads {
            means2d: &vm,
            conics: &vc,
            depths: &vd,
            opacities: &vo,
        };
        let mut cpu = [
            vec![0.0f32; 3 * n],
            vec![0.0; 4 * n],
            vec![0.0; 3 * n],
            vec![0.0; n],
        ];
        let mut gpu_g = cpu.clone();
        {
            let [a, bq, c, d] = &mut cpu;
            let out = GaussianGradsMut {
                means: a,
                quats: bq,
                scales: c,
                opacities: d,
            };
            project_backward(&g, &s.camera, &ps, &vout, out).unwrap();
        }
        {
            let [a, bq, c, d] = &mut gpu_g;
            let out = GaussianGradsMut {
                means: a,
                quats: bq,
                scales: c,
                opacities: d,
            };
            r.project_backward(&g, &s.camera, &ps, &vout, out).unwrap();
        }
        for (name, a, b) in [
            ("means", &cpu[0], &gpu_g[0]),
            ("quats", &cpu[1], &gpu_g[1]),
            ("scales", &cpu[2], &gpu_g[2]),
            ("opacities", &cpu[3], &gpu_g[3]),
        ] {
            let e = rel_err(a, b);
            assert!(e <= 1e-3, "seed {seed} {name}: relative error {e}");
        }
    }
}

#[test]
fn float_atomics_need_a_device_that_has_them() {
    let Some(dev) = open_device() else { return };
    // The same adapter, described as one without f32 atomics: its default layout adds gradients
    // by compare-and-swap, and a layout asking for float atomics is an error naming the field.
    let plain = GpuDevice {
        float_atomics: false,
        ..dev
    };
    let mut r = GpuRasterizer::new(plain);
    let before = r.blend_layout();
    assert!(!before.float_atomics);
    let err = r
        .set_blend_layout(BlendLayout {
            float_atomics: true,
            ..before
        })
        .unwrap_err();
    assert!(err.to_string().contains("float_atomics"), "{err}");
    assert_eq!(r.blend_layout(), before);
}

#[test]
fn backward_without_its_forward_is_an_error() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let s = random_scene(10, 16, 16, 3, 1);
    let p = cpu_project(&s, &ProjectSettings::default());
    let feats = to_f32(&s.features);
    let v = random_image(256, 3, 1);
    let mut gg = splat_grad_bufs::<f32>(10, 3);
    let err = r
        .rasterize_backward(
            &splats(&p, &feats, 3),
            16,
            16,
            &[0.0; 3],
            &BlendSettings::default(),
            &mut GpuRasterState::new(),
            &v.as_grads(),
            grads_mut(&mut gg),
        )
        .unwrap_err();
    assert!(err.to_string().contains("state"), "{err}");
}

/// A scene whose tile lists and compositing loops are long: llvmpipe ends a shader's loops
/// after 65,535 trips in all, which the binning scatter (one invocation per chunk) and the
/// compositing kernels (one-trip loops per unrolled pixel) once exceeded here, silently
/// dropping list entries on lavapipe (20k Gaussians at 448x448 and larger).
#[test]
fn large_scenes_match_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let s = random_scene(20_000, 448, 448, 3, 21);
    let bs = BlendSettings::default();
    let p = cpu_project(&s, &ProjectSettings::default());
    let (ci, cc) = composite(None, &p, &s, &bs);
    let (gi, gc) = composite(Some(&mut r), &p, &s, &bs);
    assert_eq!(cc.intersections, gc.intersections);
    assert!(cc.intersections > 1_000_000, "{}", cc.intersections);
    assert_eq!(cc.blended, gc.blended);
    assert!(max_abs(&ci.features, &gi.features) <= 1e-4);
    assert!(max_abs(&ci.alpha, &gi.alpha) <= 1e-4);
    check_gradients(&mut r, 21, 20_000, 448, 448, 3);
}

/// The tile scatter has two kernels: one invocation per (chunk, tile row) on GPUs and for
/// scenes with large splats, one per chunk on CPU adapters otherwise. Both write the same
/// tile lists as the CPU path (same intersections and blends, same image).
#[test]
fn both_tile_scatters_match_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let cpu_adapter = r.device().adapter.kind == "cpu";
    let mut seen = Vec::new();
    for (n, size, grow, seed) in [(3000, 160, 1.0, 31u64), (300, 448, 12.0, 32)] {
        let mut s = random_scene(n, size, size, 3, seed);
        for sc in &mut s.scales {
            *sc *= grow;
        }
        let bs = BlendSettings::default();
        let p = cpu_project(&s, &ProjectSettings::default());
        let (ci, cc) = composite(None, &p, &s, &bs);
        r.set_profiling(true);
        let (gi, gc) = composite(Some(&mut r), &p, &s, &bs);
        let stages = r.take_profile();
        r.set_profiling(false);
        let scatter = stages
            .iter()
            .find(|(name, _)| name.starts_with("scatter"))
            .expect("a scatter stage")
            .0;
        seen.push(scatter);
        assert_eq!(cc.intersections, gc.intersections, "{scatter}");
        assert_eq!(cc.blended, gc.blended, "{scatter}");
        assert!(max_abs(&ci.features, &gi.features) <= 1e-4, "{scatter}");
        assert!(max_abs(&ci.depth, &gi.depth) <= 1e-3, "{scatter}");
    }
    let expected = if cpu_adapter {
        ["scatter by chunks", "scatter by rows"]
    } else {
        ["scatter by rows", "scatter by rows"]
    };
    assert_eq!(seen, expected);
}

/// One 16x16 tile whose list holds 70,000 one-pixel splats (alpha ~0.01 near their own pixel
/// centre, below 1/255 at the next), ~270 a pixel: nothing saturates, so forward and backward
/// walk the whole list, more loop trips than lavapipe runs in one shader (65,535). Composited
/// in windows it matches the CPU path; one fixed window on lavapipe is an error naming the
/// cause, never a truncated result.
#[test]
fn long_tile_lists_are_composited_in_windows() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let n = 70_000;
    let p = Proj {
        means2d: (0..n)
            .flat_map(|i| [(i % 16) as f32 + 0.6, (i / 16 % 16) as f32 + 0.45])
            .collect(),
        conics: (0..n).flat_map(|_| [4.0f32, 0.0, 4.0]).collect(),
        depths: (0..n).map(|i| 1.0 + i as f32).collect(),
        opacities: vec![0.01; n],
        radii: vec![2; 2 * n],
    };
    let feats: Vec<f32> = (0..3 * n).map(|i| (i * 7 % 11) as f32 / 11.0).collect();
    let bg = [0.1f32, 0.2, 0.3];
    let sp = splats(&p, &feats, 3);
    check_splat_gradients(&mut r, &sp, 16, 16, &bg, 31);
    // From one dispatch for the whole list, halved on each cut (lavapipe).
    r.set_compositing_window(CompositingWindow::Start(u32::MAX))
        .unwrap();
    check_splat_gradients(&mut r, &sp, 16, 16, &bg, 32);

    r.set_compositing_window(CompositingWindow::Fixed(u32::MAX))
        .unwrap();
    let mut img = Image::zeros(256, 3);
    let got = r.rasterize_forward(
        &sp,
        16,
        16,
        &bg,
        &BlendSettings::default(),
        &mut GpuRasterState::new(),
        img.as_mut(),
    );
    r.set_compositing_window(CompositingWindow::Auto).unwrap();
    if r.device().adapter.kind == "cpu" {
        let err = got.unwrap_err().to_string();
        assert!(
            err.contains("65,535") && err.contains("CPU backend") && err.contains("compositing"),
            "{err}"
        );
    } else {
        assert_eq!(got.unwrap().intersections, n as u64);
    }
}

/// Lists composited a few entries per dispatch (windows of 7, crossing every batch boundary)
/// give the CPU path's images, counters and gradients, in every layout.
#[test]
fn windowed_compositing_matches_the_cpu_path() {
    let Some(gpu) = gpu() else { return };
    let mut r = gpu
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let default = r.blend_layout();
    r.set_compositing_window(CompositingWindow::Fixed(7))
        .unwrap();
    for layout in layouts(&r) {
        r.set_blend_layout(layout).unwrap();
        let s = random_scene(300, 64, 48, 3, 41);
        let bs = BlendSettings::default();
        let p = cpu_project(&s, &ProjectSettings::default());
        let (_, cc) = composite(None, &p, &s, &bs);
        let (_, gc) = composite(Some(&mut r), &p, &s, &bs);
        assert_eq!(cc.intersections, gc.intersections, "{layout:?}");
        assert_eq!(cc.blended, gc.blended, "{layout:?}");
        check_gradients(&mut r, 41, 300, 64, 48, 3);
    }
    r.set_compositing_window(CompositingWindow::Auto).unwrap();
    r.set_blend_layout(default).unwrap();
}
