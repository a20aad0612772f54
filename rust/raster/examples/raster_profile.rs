//! Time the stages of one render (projection, binning, compositing, backward) on a seeded
//! random scene, without Python: `cargo run --release --example raster_profile -- N W H THREADS`.

use std::time::Instant;
use sync4d_raster::*;
use sync4d_testing::{grads_mut, splat_grad_bufs};

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("integer argument"))
        .collect();
    let (n, w, h, threads, iters) = match args.as_slice() {
        [n, w, h, t] => (*n, *w as u32, *h as u32, *t, 6),
        [n, w, h, t, i] => (*n, *w as u32, *h as u32, *t, *i),
        _ => (100_000, 800, 800, 1, 6),
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| run(n, w, h, iters));
}

/// xorshift for a reproducible scene.
struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

// A profiling script: scene, timed stages and the report, in order.
#[allow(clippy::too_many_lines)]
fn run(n: usize, w: u32, h: u32, iters: usize) {
    let mut r = Rng(0x1234_5678_9abc_def1);
    let f = 0.8 * w as f64;
    let (mut means, mut quats, mut scales, mut ops, mut cols) =
        (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let z = 2.0 + 4.0 * r.f();
        let hx = z * w as f32 / (2.0 * f as f32) * 1.1;
        let hy = z * h as f32 / (2.0 * f as f32) * 1.1;
        means.extend([(2.0 * r.f() - 1.0) * hx, (2.0 * r.f() - 1.0) * hy, z]);
        quats.extend([r.f() - 0.5, r.f() - 0.5, r.f() - 0.5, r.f() - 0.5]);
        for _ in 0..3 {
            scales.push(0.012 * (1.0 * (r.f() - 0.5)).exp());
        }
        ops.push(0.05 + 0.9 * r.f());
        cols.extend([r.f(), r.f(), r.f()]);
    }
    let eye = [
        1.0, 0., 0., 0., 0., 1., 0., 0., 0., 0., 1., 0., 0., 0., 0., 1.,
    ];
    let cam = Camera::new(&eye, f, f, w as f64 / 2.0, h as f64 / 2.0, w, h).unwrap();
    let ps = ProjectSettings::default();
    let bs = BlendSettings::default();
    let (mut m2, mut co, mut de, mut op, mut ra) = (
        vec![0f32; 2 * n],
        vec![0f32; 3 * n],
        vec![0f32; n],
        vec![0f32; n],
        vec![0i32; 2 * n],
    );
    let npix = (w * h) as usize;
    let (mut img, mut alpha, mut depth) =
        (vec![0f32; 3 * npix], vec![0f32; npix], vec![0f32; npix]);
    let mut state = RasterState::new();
    let mut bufs = splat_grad_bufs(n, 3);
    let (vi, va, vd) = (vec![1f32; 3 * npix], vec![1f32; npix], vec![0f32; npix]);
    for it in 0..iters {
        let t0 = Instant::now();
        project_forward(
            &Gaussians {
                means: &means,
                quats: &quats,
                scales: &scales,
                opacities: &ops,
            },
            &cam,
            &ps,
            ProjectionMut {
                means2d: &mut m2,
                conics: &mut co,
                depths: &mut de,
                opacities: &mut op,
                radii: &mut ra,
            },
        )
        .unwrap();
        let t1 = Instant::now();
        let sp = Splats {
            means2d: &m2,
            conics: &co,
            depths: &de,
            opacities: &op,
            radii: &ra,
            features: &cols,
            channels: 3,
        };
        state.bins.build(&m2, &ra, &de, w, h).unwrap();
        let t2 = Instant::now();
        let c = rasterize_forward(
            &sp,
            w,
            h,
            &[0.0; 3],
            &bs,
            &mut state,
            ImageMut {
                features: &mut img,
                alpha: &mut alpha,
                depth: &mut depth,
            },
        )
        .unwrap();
        let t3 = Instant::now();
        rasterize_backward(
            &sp,
            w,
            h,
            &[0.0; 3],
            &bs,
            &mut state,
            &ImageGrads {
                features: &vi,
                alpha: &va,
                depth: &vd,
            },
            grads_mut(&mut bufs),
        )
        .unwrap();
        let t4 = Instant::now();
        let ms = |a: Instant, b: Instant| (b - a).as_secs_f64() * 1e3;
        if it >= iters.saturating_sub(4) {
            println!(
                "project {:.1} ms | bins {:.1} ms | forward (incl. bins) {:.1} ms | backward {:.1} ms | {c:?}",
                ms(t0, t1),
                ms(t1, t2),
                ms(t2, t3),
                ms(t3, t4)
            );
        }
    }
}
