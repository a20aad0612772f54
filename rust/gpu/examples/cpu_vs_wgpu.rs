//! Time the CPU path and the wgpu path on the same seeded random scene (forward: projection and
//! compositing; backward: both backwards), median and fastest of repeated calls after a warm-up,
//! the backends taking turns call by call.
//!
//! cargo run --release -p sync4d-gpu --example cpu_vs_wgpu -- [N] [WIDTH] [HEIGHT] [REPEATS]
//!
//! With SYNC4D_GPU_PROFILE=1 the wgpu calls also report per-stage times (each stage then waits
//! for the device, so the totals grow a little). SYNC4D_GPU_ROWS=R and SYNC4D_GPU_PIXELS=P
//! override the compositing layout's block rows and pixels per invocation, SYNC4D_GPU_HALVES its
//! column halves (0 never, 2 always, t > 2 in the backward below t tile intersections per
//! splat), to compare layouts;
//! SYNC4D_SCALE=s multiplies the scene's Gaussian scales (0.15: small splats, few saturated
//! pixels, like `python -m sync4d bench raster`'s scene).

use std::time::Instant;
use sync4d_gpu::{AdapterChoice, ColumnHalves, GpuDevice, GpuRasterState, GpuRasterizer};
use sync4d_raster::*;
use sync4d_testing::*;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

// A benchmark script: argument parsing, the scene, and one table row per backend, in order.
#[allow(clippy::too_many_lines)]
fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let n = args.first().copied().unwrap_or(100_000);
    let w = args.get(1).copied().unwrap_or(800) as u32;
    let h = args.get(2).copied().unwrap_or(800) as u32;
    let reps = args.get(3).copied().unwrap_or(5).max(1);
    let s = random_scene(n, w, h, 3, 7);
    // SYNC4D_SCALE multiplies every Gaussian's scales (smaller splats: fewer tile
    // intersections, fewer saturated pixels).
    let scale_factor: f32 = std::env::var("SYNC4D_SCALE")
        .ok()
        .map_or(1.0, |v| v.parse().expect("SYNC4D_SCALE"));
    let sc: Vec<f32> = to_f32(&s.scales).iter().map(|v| v * scale_factor).collect();
    let (m, q, o) = (to_f32(&s.means), to_f32(&s.quats), to_f32(&s.opacities));
    let feats = to_f32(&s.features);
    let bg = to_f32(&s.background);
    let g = Gaussians {
        means: &m,
        quats: &q,
        scales: &sc,
        opacities: &o,
    };
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let npix = (w * h) as usize;
    let v = Image {
        features: vec![0.01f32; npix * 3],
        alpha: vec![0.01; npix],
        depth: vec![0.0; npix],
    };
    let dev = GpuDevice::new(AdapterChoice::Auto).expect("no wgpu adapter");
    println!("adapter: {}  |  N = {n}, {w}x{h}", dev.adapter);
    let mut gpu = GpuRasterizer::new(dev);
    let env_u32 = |name: &str| {
        std::env::var(name)
            .ok()
            .map(|v| v.parse::<u32>().expect(name))
    };
    let mut layout = gpu.blend_layout();
    layout.block_rows = env_u32("SYNC4D_GPU_ROWS").unwrap_or(layout.block_rows);
    layout.column_halves = match env_u32("SYNC4D_GPU_HALVES") {
        Some(0) => ColumnHalves::Never,
        Some(2) => ColumnHalves::Always,
        Some(t) => ColumnHalves::BackwardBelowTilesPerSplat(t),
        None => layout.column_halves,
    };
    layout.pixels_per_invocation =
        env_u32("SYNC4D_GPU_PIXELS").unwrap_or(layout.pixels_per_invocation);
    // Keep subgroup sums only where the chosen layout can have them on this device.
    layout.subgroup_sums &= layout.can_sum_by_subgroups(gpu.device());
    gpu.set_blend_layout(layout).expect("compositing layout");
    println!("layout: {layout:?}");
    let profiling = std::env::var("SYNC4D_GPU_PROFILE").is_ok_and(|v| v == "1");
    gpu.set_profiling(profiling);
    let mut stages: Vec<(&'static str, Vec<f64>, usize)> = Vec::new();

    // The first call's image and counters of each backend, compared before any timing is shown.
    let mut first: Vec<(Vec<f32>, Counters)> = Vec::new();
    let mut cstate = RasterState::new();
    let mut gstate = GpuRasterState::new();
    // Per backend: forward and forward+backward seconds of each timed call.
    let mut times: Vec<(Vec<f64>, Vec<f64>)> = vec![(Vec::new(), Vec::new()); 2];
    // The backends take turns call by call, so that a machine whose speed drifts (a shared one)
    // slows both alike.
    for rep in 0..=reps {
        for (bi, backend) in ["cpu", "wgpu"].into_iter().enumerate() {
            let (fwd, full) = &mut times[bi];
            let t0 = Instant::now();
            let mut p = Proj::zeros(n);
            let out = p.as_mut();
            let mut img = Image::zeros(npix, 3);
            let sp_feats = feats.clone();
            if backend == "cpu" {
                project_forward(&g, &s.camera, &ps, out).unwrap();
                let c = rasterize_forward(
                    &splats(&p, &sp_feats, 3),
                    w,
                    h,
                    &bg,
                    &bs,
                    &mut cstate,
                    img.as_mut(),
                )
                .unwrap();
                if rep == 0 {
                    println!(
                        "work: {} visible, {} tile intersections, {} splat-pixel evaluations",
                        c.visible, c.intersections, c.evaluated
                    );
                    first.push((img.features.clone(), c));
                }
            } else {
                gpu.project_forward(&g, &s.camera, &ps, out).unwrap();
                let c = gpu
                    .rasterize_forward(
                        &splats(&p, &sp_feats, 3),
                        w,
                        h,
                        &bg,
                        &bs,
                        &mut gstate,
                        img.as_mut(),
                    )
                    .unwrap();
                if rep == 0 {
                    first.push((img.features.clone(), c));
                }
            }
            let t_fwd = t0.elapsed().as_secs_f64();
            let mut sg = splat_grad_bufs::<f32>(n, 3);
            let mut gg = [
                vec![0.0f32; 3 * n],
                vec![0.0; 4 * n],
                vec![0.0; 3 * n],
                vec![0.0; n],
            ];
            let sp = splats(&p, &sp_feats, 3);
            if backend == "cpu" {
                rasterize_backward(
                    &sp,
                    w,
                    h,
                    &bg,
                    &bs,
                    &mut cstate,
                    &v.as_grads(),
                    grads_mut(&mut sg),
                )
                .unwrap();
            } else {
                gpu.rasterize_backward(
                    &sp,
                    w,
                    h,
                    &bg,
                    &bs,
                    &mut gstate,
                    &v.as_grads(),
                    grads_mut(&mut sg),
                )
                .unwrap();
            }
            let [g2, gc, gd, go, _] = &sg;
            let vout = ProjectionGrads {
                means2d: g2,
                conics: gc,
                depths: gd,
                opacities: go,
            };
            let [a, b, c, d] = &mut gg;
            let outg = GaussianGradsMut {
                means: a,
                quats: b,
                scales: c,
                opacities: d,
            };
            if backend == "cpu" {
                project_backward(&g, &s.camera, &ps, &vout, outg).unwrap();
            } else {
                gpu.project_backward(&g, &s.camera, &ps, &vout, outg)
                    .unwrap();
            }
            let t_full = t0.elapsed().as_secs_f64();
            let profile = gpu.take_profile();
            if rep > 0 {
                fwd.push(t_fwd);
                full.push(t_full);
                // A stage that runs several times a call (binning stages, compositing
                // windows) is summed per call, with its count.
                let mut call: Vec<(&'static str, f64, usize)> = Vec::new();
                for (name, secs) in profile {
                    match call.iter_mut().find(|(s, _, _)| *s == name) {
                        Some((_, t, k)) => {
                            *t += secs;
                            *k += 1;
                        }
                        None => call.push((name, secs, 1)),
                    }
                }
                for (name, secs, k) in call {
                    match stages.iter_mut().find(|(s, _, _)| *s == name) {
                        Some((_, v, _)) => v.push(secs),
                        None => stages.push((name, vec![secs], k)),
                    }
                }
            }
        }
    }
    // Timings of a wrong image mean nothing: the two backends must agree. Each projects on its
    // own (f32 rounding moves a few pixels across the 1/255 alpha cut: ~1e-3 here), while
    // dropped work shows as errors of 0.1 and more.
    let ((cpu_img, cpu_c), (gpu_img, gpu_c)) = (&first[0], &first[1]);
    let diff = cpu_img
        .iter()
        .zip(gpu_img)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    println!(
        "agreement: max abs image difference {diff:.2e}, blended pairs {} (CPU) vs {} (wgpu)",
        cpu_c.blended, gpu_c.blended
    );
    println!(
        "evaluated: {} (CPU, inside support boxes) vs {} (wgpu, live pixels of visited splats)",
        cpu_c.evaluated, gpu_c.evaluated
    );
    assert!(
        diff <= 1e-2
            && cpu_c.intersections == gpu_c.intersections
            && cpu_c.blended.abs_diff(gpu_c.blended) * 10_000 <= cpu_c.blended,
        "the wgpu image differs from the CPU path's"
    );
    let fastest = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let results: Vec<(&str, f64, f64, f64, f64)> = ["cpu", "wgpu"]
        .into_iter()
        .zip(&times)
        .map(|(b, (f, ff))| {
            (
                b,
                median(f.clone()),
                median(ff.clone()),
                fastest(f),
                fastest(ff),
            )
        })
        .collect();
    println!("backend   forward (median, fastest)   fwd+bwd (median, fastest)");
    for (b, f, ff, fm, ffm) in &results {
        println!(
            "{b:<8} {:>8.1} ms {:>8.1} ms       {:>8.1} ms {:>8.1} ms",
            f * 1e3,
            fm * 1e3,
            ff * 1e3,
            ffm * 1e3
        );
    }
    if profiling {
        println!("wgpu stage        median  (runs per call)");
        for (name, v, k) in stages {
            println!("{name:<16} {:>8.1} ms  ({k})", median(v) * 1e3);
        }
    }
    let (cpu, wgpu) = (&results[0], &results[1]);
    println!(
        "wgpu / cpu: forward {:.2}x, fwd+bwd {:.2}x (medians); {:.2}x, {:.2}x (fastest calls)",
        wgpu.1 / cpu.1,
        wgpu.2 / cpu.2,
        wgpu.3 / cpu.3,
        wgpu.4 / cpu.4
    );
}
