//! The node-weighted sum against a plain f64 reference (forward and every gradient), central
//! finite differences of the f64 kernel, bit-identical results across thread counts, far-away
//! Gaussians, K = 1, and the argument checks.

use sync4d_motion::blend::baseline;
use sync4d_motion::{
    node_weighted_sum_backward, node_weighted_sum_forward, MotionError, NodeBlend,
    NodeBlendGradsMut,
};

/// SplitMix64: a seeded, dependency-free generator.
struct Rng(u64);

impl Rng {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }
}

/// A random problem in f64: (x0, positions, inv_r2, table, index, k, c). Some Gaussians far
/// from all their nodes (`far` of them, 1e3 away with radii ~0.1).
struct Problem {
    x0: Vec<f64>,
    positions: Vec<f64>,
    inv_r2: Vec<f64>,
    table: Vec<f64>,
    index: Vec<i64>,
    k: usize,
    c: usize,
}

impl Problem {
    fn random(n: usize, m: usize, k: usize, c: usize, far: usize, seed: u64) -> Self {
        let mut rng = Rng(seed);
        let positions: Vec<f64> = (0..3 * m).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let inv_r2 = (0..m)
            .map(|_| {
                let r: f64 = rng.uniform(0.2, 0.8);
                1.0 / (r * r)
            })
            .collect();
        let table = (0..m * c).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let mut x0: Vec<f64> = (0..3 * n).map(|_| rng.uniform(-1.2, 1.2)).collect();
        for i in 0..far.min(n) {
            x0[3 * i] += 1e3;
        }
        let index = (0..n * k).map(|_| rng.below(m) as i64).collect();
        Problem {
            x0,
            positions,
            inv_r2,
            table,
            index,
            k,
            c,
        }
    }
    fn n(&self) -> usize {
        self.x0.len() / 3
    }
    fn m(&self) -> usize {
        self.inv_r2.len()
    }
    fn blend<'a, T>(
        &self,
        x0: &'a [T],
        positions: &'a [T],
        inv_r2: &'a [T],
        table: &'a [T],
        index: &'a [i64],
    ) -> NodeBlend<'a, T, i64> {
        NodeBlend {
            x0,
            positions,
            inv_r2,
            table,
            index,
            neighbours: self.k,
            channels: self.c,
        }
    }
}

fn to_f32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// The plain f64 reference: b [N, C] and (g_x0, g_positions, g_inv_r2, g_table) for `gb`.
#[allow(clippy::type_complexity)]
fn reference(p: &Problem, gb: &[f64]) -> (Vec<f64>, [Vec<f64>; 4]) {
    let (n, m, k, c) = (p.n(), p.m(), p.k, p.c);
    let mut b = vec![0.0; n * c];
    let (mut gx, mut gp, mut gr, mut gt) = (
        vec![0.0; 3 * n],
        vec![0.0; 3 * m],
        vec![0.0; m],
        vec![0.0; m * c],
    );
    for i in 0..n {
        let js: Vec<usize> = (0..k).map(|s| p.index[i * k + s] as usize).collect();
        let d: Vec<[f64; 3]> = js
            .iter()
            .map(|&j| std::array::from_fn(|a| p.x0[3 * i + a] - p.positions[3 * j + a]))
            .collect();
        let d2: Vec<f64> = d.iter().map(|d| d.iter().map(|v| v * v).sum()).collect();
        let a: Vec<f64> = (0..k).map(|s| -0.5 * d2[s] * p.inv_r2[js[s]]).collect();
        let max = a.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let e: Vec<f64> = a.iter().map(|a| (a - max).exp()).collect();
        let sum: f64 = e.iter().sum();
        let w: Vec<f64> = e.iter().map(|e| e / sum).collect();
        for s in 0..k {
            for ch in 0..c {
                b[i * c + ch] += w[s] * p.table[js[s] * c + ch];
            }
        }
        let g = &gb[i * c..(i + 1) * c];
        let gw: Vec<f64> = js
            .iter()
            .map(|&j| (0..c).map(|ch| g[ch] * p.table[j * c + ch]).sum())
            .collect();
        let dot: f64 = (0..k).map(|s| w[s] * gw[s]).sum();
        for s in 0..k {
            let j = js[s];
            let ga = w[s] * (gw[s] - dot);
            for ch in 0..c {
                gt[j * c + ch] += w[s] * g[ch];
            }
            gr[j] += ga * (-0.5 * d2[s]);
            let gd2 = ga * (-0.5 * p.inv_r2[j]);
            for a in 0..3 {
                gx[3 * i + a] += 2.0 * gd2 * d[s][a];
                gp[3 * j + a] -= 2.0 * gd2 * d[s][a];
            }
        }
    }
    (b, [gx, gp, gr, gt])
}

fn forward<T: sync4d_motion::Real>(b: &NodeBlend<'_, T, i64>) -> Vec<T> {
    let mut out = vec![T::zero(); b.x0.len() / 3 * b.channels];
    node_weighted_sum_forward(b, &mut out, None).unwrap();
    out
}

fn backward<T: sync4d_motion::Real>(b: &NodeBlend<'_, T, i64>, gb: &[T]) -> [Vec<T>; 4] {
    let (n, m) = (b.x0.len() / 3, b.inv_r2.len());
    let mut g = [
        vec![T::nan(); 3 * n],
        vec![T::nan(); 3 * m],
        vec![T::nan(); m],
        vec![T::nan(); m * b.channels],
    ];
    let [gx, gp, gr, gt] = &mut g;
    let grads = NodeBlendGradsMut {
        x0: gx,
        positions: gp,
        inv_r2: gr,
        table: gt,
    };
    node_weighted_sum_backward(b, gb, grads).unwrap();
    g
}

/// max |got - want| <= atol + rtol max |want|, per named array.
fn assert_close(name: &str, got: &[f64], want: &[f64], rtol: f64, atol: f64) {
    assert_eq!(got.len(), want.len(), "{name}: length");
    let scale = want.iter().fold(0.0f64, |s, v| s.max(v.abs()));
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        assert!(g.is_finite(), "{name}[{i}] = {g}");
        assert!(
            (g - w).abs() <= atol + rtol * scale,
            "{name}[{i}]: got {g}, want {w} (scale {scale})"
        );
    }
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

const NAMES: [&str; 4] = ["grad_x0", "grad_positions", "grad_inv_r2", "grad_table"];

#[test]
fn f32_kernel_matches_f64_reference() {
    for &(n, m, k, c, far) in &[
        (700, 40, 8, 19, 20),
        (300, 25, 4, 11, 5),
        (200, 10, 1, 19, 3),
        (150, 9, 3, 5, 2),
    ] {
        let p = Problem::random(n, m, k, c, far, 7 + (k * c) as u64);
        let gb: Vec<f64> = {
            let mut rng = Rng(99);
            (0..n * c).map(|_| rng.uniform(-1.0, 1.0)).collect()
        };
        let (b_ref, g_ref) = reference(&p, &gb);
        let (x0, pos, ir, t) = (
            to_f32(&p.x0),
            to_f32(&p.positions),
            to_f32(&p.inv_r2),
            to_f32(&p.table),
        );
        let blend = p.blend(&x0, &pos, &ir, &t, &p.index);
        let b: Vec<f64> = forward(&blend).iter().map(|&v| v as f64).collect();
        assert_close("b", &b, &b_ref, 1e-5, 1e-6);
        let g = pool(2).install(|| backward(&blend, &to_f32(&gb)));
        for (name, (g, r)) in NAMES.iter().zip(g.iter().zip(&g_ref)) {
            let g: Vec<f64> = g.iter().map(|&v| v as f64).collect();
            assert_close(name, &g, r, 1e-4, 1e-6);
        }
        // The f64 kernel agrees with the reference to rounding.
        let blend = p.blend(&p.x0, &p.positions, &p.inv_r2, &p.table, &p.index);
        assert_close("b (f64)", &forward(&blend), &b_ref, 1e-12, 1e-14);
        for (name, (g, r)) in NAMES.iter().zip(backward(&blend, &gb).iter().zip(&g_ref)) {
            assert_close(name, g, r, 1e-11, 1e-14);
        }
        if k == 1 {
            // One node: weight 1, so b is its row and nothing flows to the geometry.
            for i in 0..n {
                let j = p.index[i] as usize;
                assert_eq!(
                    &b[i * c..(i + 1) * c],
                    &t[j * c..(j + 1) * c]
                        .iter()
                        .map(|&v| v as f64)
                        .collect::<Vec<_>>()[..]
                );
            }
            for name in [0, 1, 2] {
                assert!(g_ref[name].iter().all(|&v| v == 0.0), "{}", NAMES[name]);
            }
        }
    }
}

#[test]
fn backward_matches_finite_differences() {
    let (n, m, k, c) = (60, 12, 5, 7);
    let p = Problem::random(n, m, k, c, 0, 3);
    let mut rng = Rng(5);
    let gb: Vec<f64> = (0..n * c).map(|_| rng.uniform(-1.0, 1.0)).collect();
    let loss = |x0: &[f64], pos: &[f64], ir: &[f64], t: &[f64]| -> f64 {
        let b = forward(&p.blend(x0, pos, ir, t, &p.index));
        b.iter().zip(&gb).map(|(b, g)| b * g).sum()
    };
    let g = backward(
        &p.blend(&p.x0, &p.positions, &p.inv_r2, &p.table, &p.index),
        &gb,
    );
    let h = 1e-6;
    let inputs = [&p.x0, &p.positions, &p.inv_r2, &p.table];
    for (a, name) in NAMES.iter().enumerate() {
        let mut fd = vec![0.0; inputs[a].len()];
        for (idx, fd) in fd.iter_mut().enumerate() {
            let mut args: Vec<Vec<f64>> = inputs.iter().map(|v| (*v).clone()).collect();
            args[a][idx] += h;
            let up = loss(&args[0], &args[1], &args[2], &args[3]);
            args[a][idx] -= 2.0 * h;
            let down = loss(&args[0], &args[1], &args[2], &args[3]);
            *fd = (up - down) / (2.0 * h);
        }
        assert_close(name, &g[a], &fd, 1e-6, 1e-7);
    }
}

#[test]
fn bit_identical_across_thread_counts_instruction_sets_and_index_types() {
    let (n, m, k, c) = (5_000, 300, 8, 19);
    let p = Problem::random(n, m, k, c, 50, 11);
    let (x0, pos, ir, t) = (
        to_f32(&p.x0),
        to_f32(&p.positions),
        to_f32(&p.inv_r2),
        to_f32(&p.table),
    );
    let mut rng = Rng(13);
    let gb: Vec<f32> = (0..n * c).map(|_| rng.uniform(-1.0, 1.0) as f32).collect();
    let blend = p.blend(&x0, &pos, &ir, &t, &p.index);
    let run = |threads: usize| pool(threads).install(|| (forward(&blend), backward(&blend, &gb)));
    let one = run(1);
    for threads in [2, 3, 4, 7] {
        let other = run(threads);
        assert_eq!(one.0, other.0, "b, {threads} threads");
        for (a, name) in NAMES.iter().enumerate() {
            let same = one.1[a]
                .iter()
                .zip(&other.1[a])
                .all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same, "{name}, {threads} threads");
        }
    }
    assert_eq!(one.0, run(1).0, "b, a second call");
    // The baseline copy of the kernels gives the AVX2 copy's bits.
    let mut out = vec![0.0f32; n * c];
    baseline::node_weighted_sum_forward(&blend, &mut out, None).unwrap();
    assert_eq!(out, one.0, "b, baseline");
    let mut g = [
        vec![0.0f32; 3 * n],
        vec![0.0; 3 * m],
        vec![0.0; m],
        vec![0.0; m * c],
    ];
    let [gx, gp, gr, gt] = &mut g;
    let grads = NodeBlendGradsMut {
        x0: gx,
        positions: gp,
        inv_r2: gr,
        table: gt,
    };
    baseline::node_weighted_sum_backward(&blend, &gb, grads).unwrap();
    for (a, name) in NAMES.iter().enumerate() {
        let same = one.1[a]
            .iter()
            .zip(&g[a])
            .all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same, "{name}, baseline");
    }
    // int32 indices give the same results as int64.
    let index32: Vec<i32> = p.index.iter().map(|&j| j as i32).collect();
    let b32 = NodeBlend {
        x0: &x0[..],
        positions: &pos,
        inv_r2: &ir,
        table: &t,
        index: &index32[..],
        neighbours: k,
        channels: c,
    };
    let mut out = vec![0.0f32; n * c];
    let mut w = vec![0.0f32; n * k];
    node_weighted_sum_forward(&b32, &mut out, Some(&mut w)).unwrap();
    assert_eq!(out, one.0);
    for i in 0..n {
        let s: f32 = w[i * k..(i + 1) * k].iter().sum();
        assert!((s - 1.0).abs() < 1e-5, "weights of Gaussian {i} sum to {s}");
    }
}

#[test]
fn far_gaussians_take_their_nearest_node() {
    let (k, c) = (3, 2);
    // Nodes at x = 0, 1, 2 (radius 0.1); a Gaussian at x = 1e4 is nearest to node 2.
    let positions = [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0];
    let inv_r2 = [100.0f32; 3];
    let table = [1.0f32, -1.0, 2.0, -2.0, 3.0, -3.0];
    let x0 = [1e4f32, 0.0, 0.0];
    let index = [0i64, 1, 2];
    let blend = NodeBlend {
        x0: &x0,
        positions: &positions,
        inv_r2: &inv_r2,
        table: &table,
        index: &index,
        neighbours: k,
        channels: c,
    };
    let mut out = [0.0f32; 2];
    let mut w = [0.0f32; 3];
    node_weighted_sum_forward(&blend, &mut out, Some(&mut w)).unwrap();
    assert_eq!(w, [0.0, 0.0, 1.0]);
    assert_eq!(out, [3.0, -3.0]);
    let g = backward(&blend, &[1.0, 0.5]);
    assert!(g.iter().flatten().all(|v| v.is_finite()), "{g:?}");
    // Logits all -inf (infinite inv_r2): equal weights, not NaN.
    let inv_r2 = [f32::INFINITY; 3];
    let blend = NodeBlend {
        inv_r2: &inv_r2,
        ..blend
    };
    node_weighted_sum_forward(&blend, &mut out, Some(&mut w)).unwrap();
    assert_eq!(w, [1.0 / 3.0; 3]);
    assert!(out.iter().all(|v| v.is_finite()));
}

#[test]
fn no_gaussians() {
    let p = Problem::random(0, 4, 2, 3, 0, 1);
    let blend = p.blend(&p.x0, &p.positions, &p.inv_r2, &p.table, &p.index);
    assert!(forward(&blend).is_empty());
    let g = backward(&blend, &[]);
    assert!(g.iter().flatten().all(|&v| v == 0.0));
}

#[test]
fn bad_arguments_name_the_argument() {
    let p = Problem::random(4, 3, 2, 2, 0, 1);
    let blend = p.blend(&p.x0, &p.positions, &p.inv_r2, &p.table, &p.index);
    let fwd = |b: &NodeBlend<'_, f64, i64>| -> Result<(), MotionError> {
        let mut out = vec![0.0; 4 * 2];
        node_weighted_sum_forward(b, &mut out, None)
    };
    let arg = |b: &NodeBlend<'_, f64, i64>| fwd(b).unwrap_err().arg();
    let mut index = p.index.clone();
    index[5] = 3;
    assert_eq!(
        arg(&NodeBlend {
            index: &index,
            ..blend
        }),
        "index"
    );
    index[5] = -1;
    assert_eq!(
        arg(&NodeBlend {
            index: &index,
            ..blend
        }),
        "index"
    );
    assert_eq!(
        arg(&NodeBlend {
            index: &index[..7],
            ..blend
        }),
        "index"
    );
    assert_eq!(
        arg(&NodeBlend {
            x0: &p.x0[..11],
            ..blend
        }),
        "x0"
    );
    assert_eq!(
        arg(&NodeBlend {
            positions: &p.positions[..8],
            ..blend
        }),
        "positions"
    );
    assert_eq!(
        arg(&NodeBlend {
            inv_r2: &p.inv_r2[..2],
            ..blend
        }),
        "inv_r2"
    );
    assert_eq!(
        arg(&NodeBlend {
            table: &p.table[..5],
            ..blend
        }),
        "table"
    );
    assert_eq!(
        arg(&NodeBlend {
            neighbours: 0,
            ..blend
        }),
        "neighbours"
    );
    assert_eq!(
        arg(&NodeBlend {
            channels: 0,
            ..blend
        }),
        "channels"
    );
    let mut out = vec![0.0; 7];
    assert_eq!(
        node_weighted_sum_forward(&blend, &mut out, None)
            .unwrap_err()
            .arg(),
        "out"
    );
    let (mut gx, mut gp, mut gr, mut gt) =
        (vec![0.0; 12], vec![0.0; 9], vec![0.0; 3], vec![0.0; 6]);
    let grads = NodeBlendGradsMut {
        x0: &mut gx,
        positions: &mut gp,
        inv_r2: &mut gr,
        table: &mut gt,
    };
    let err = node_weighted_sum_backward(&blend, &[0.0; 7], grads).unwrap_err();
    assert_eq!(err.arg(), "grad_out");
}
