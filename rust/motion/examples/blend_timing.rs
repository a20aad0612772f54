//! Timing of the node-weighted sum, forward and backward: N = 15000 Gaussians, K = 8 nodes of
//! M = 500, C = 19 (the linear blend's table). `cargo run --release -p sync4d-motion --example
//! blend_timing [threads]`; prints the best and median of 50 calls each, in ms.

use std::time::Instant;
use sync4d_motion::{
    node_weighted_sum_backward, node_weighted_sum_forward, NodeBlend, NodeBlendGradsMut,
};

fn main() {
    let threads: usize = std::env::args().nth(1).map_or(1, |a| a.parse().unwrap());
    let (n, m, k, c) = (15_000, 500, 8, 19);
    let mut state = 1u64;
    let mut rand = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 40) as f32 / (1u64 << 24) as f32
    };
    let x0: Vec<f32> = (0..3 * n).map(|_| 2.0 * rand() - 1.0).collect();
    let positions: Vec<f32> = (0..3 * m).map(|_| 2.0 * rand() - 1.0).collect();
    let inv_r2: Vec<f32> = (0..m).map(|_| 4.0 + 8.0 * rand()).collect();
    let table: Vec<f32> = (0..m * c).map(|_| rand() - 0.5).collect();
    let index: Vec<i64> = (0..n * k)
        .map(|_| (rand() * m as f32) as i64 % m as i64)
        .collect();
    let gb: Vec<f32> = (0..n * c).map(|_| rand() - 0.5).collect();
    let blend = NodeBlend {
        x0: &x0,
        positions: &positions,
        inv_r2: &inv_r2,
        table: &table,
        index: &index,
        neighbours: k,
        channels: c,
    };
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    let time = |f: &mut dyn FnMut()| {
        let mut t: Vec<f64> = (0..50)
            .map(|_| {
                let t0 = Instant::now();
                f();
                t0.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        t.sort_by(f64::total_cmp);
        (t[0], t[25])
    };
    let mut out = vec![0.0f32; n * c];
    let fwd =
        pool.install(|| time(&mut || node_weighted_sum_forward(&blend, &mut out, None).unwrap()));
    let (mut gx, mut gp, mut gr, mut gt) = (
        vec![0.0; 3 * n],
        vec![0.0; 3 * m],
        vec![0.0; m],
        vec![0.0; m * c],
    );
    let bwd = pool.install(|| {
        time(&mut || {
            let grads = NodeBlendGradsMut {
                x0: &mut gx,
                positions: &mut gp,
                inv_r2: &mut gr,
                table: &mut gt,
            };
            node_weighted_sum_backward(&blend, &gb, grads).unwrap();
        })
    });
    println!(
        "{threads} threads: forward {:.3} ms (median {:.3}), backward {:.3} ms (median {:.3})",
        fwd.0, fwd.1, bwd.0, bwd.1
    );
}
