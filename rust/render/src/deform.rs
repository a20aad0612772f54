//! D_theta evaluated in Rust (f32), exactly as `sync4d/phase1/deform.py`: the input
//! [x0 or its encoding; z; gamma(t)] with gamma(t) = [t, sin(2^0 pi t), cos(2^0 pi t), ...]
//! (the position encoding: x0, then per band sin and cos of the 3 coordinates), ReLU trunk, linear
//! head scaled to (dx, dw, dl), then Eqs. 2-4: x = x0 + dx, q = normalize(aa2q(dw) (x) q0),
//! s = exp(log s0 + dl).

use rayon::prelude::*;

use crate::checkpoint::{Checkpoint, DeformMlp, Linear};

/// Gaussians deformed to one time: means N*3, unit quaternions N*4, scales N*3.
#[derive(Debug, Clone)]
pub struct Deformed {
    /// Means, N*3 world units.
    pub means: Vec<f32>,
    /// Unit quaternions (w, x, y, z), N*4.
    pub quats: Vec<f32>,
    /// Standard deviations, N*3.
    pub scales: Vec<f32>,
}

/// gamma(t): [t, sin(2^0 pi t), cos(2^0 pi t), ..., sin(2^(L-1) pi t), cos(2^(L-1) pi t)].
pub fn time_encoding(t: f32, bands: usize) -> Vec<f32> {
    let mut out = Vec::with_capacity(1 + 2 * bands);
    out.push(t);
    for b in 0..bands {
        let a = t * (2.0f32.powi(b as i32) * std::f32::consts::PI);
        out.push(a.sin());
        out.push(a.cos());
    }
    out
}

/// The frequencies 2^k pi, k < `bands`, of the position encoding.
pub fn position_frequencies(bands: usize) -> Vec<f32> {
    (0..bands)
        .map(|b| 2.0f32.powi(b as i32) * std::f32::consts::PI)
        .collect()
}

/// The position encoding appended to `out`: x, then for each frequency f of
/// `position_frequencies(L)` sin(f x) and cos(f x) of the 3 coordinates (3 (1 + 2L) values; x
/// alone when L = 0).
pub fn push_position_encoding(x: &[f32], freqs: &[f32], out: &mut Vec<f32>) {
    out.extend_from_slice(&x[..3]);
    for &f in freqs {
        out.extend(x[..3].iter().map(|v| (v * f).sin()));
        out.extend(x[..3].iter().map(|v| (v * f).cos()));
    }
}

fn linear(l: &Linear, x: &[f32], y: &mut Vec<f32>, relu: bool) {
    y.clear();
    for o in 0..l.outputs {
        let row = &l.weight[o * l.inputs..(o + 1) * l.inputs];
        let mut acc = l.bias[o];
        for (w, v) in row.iter().zip(x) {
            acc += w * v;
        }
        y.push(if relu { acc.max(0.0) } else { acc });
    }
}

/// D_theta's (dx, dw, dl) for one Gaussian.
fn mlp_eval(mlp: &DeformMlp, input: &[f32], a: &mut Vec<f32>, b: &mut Vec<f32>) -> [f32; 9] {
    a.clear();
    a.extend_from_slice(input);
    for l in &mlp.trunk {
        linear(l, a, b, true);
        std::mem::swap(a, b);
    }
    linear(&mlp.head, a, b, false);
    let mut out = [0.0; 9];
    for (i, v) in b.iter().enumerate() {
        out[i] = v * mlp.scales[i / 3];
    }
    out
}

fn quat_mul(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    let [aw, ax, ay, az] = a;
    let [bw, bx, by, bz] = b;
    [
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ]
}

fn normalize(q: [f32; 4]) -> [f32; 4] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        .sqrt()
        .max(1e-12);
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

fn axis_angle_to_quat(w: [f32; 3]) -> [f32; 4] {
    let theta = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt();
    let s = (0.5 * theta).sin() / (theta + 1e-8);
    let q = [(0.5 * theta).cos(), w[0] * s, w[1] * s, w[2] * s];
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

/// The checkpoint's Gaussians deformed to time `t` (parallel over Gaussians).
pub fn deform_at(ck: &Checkpoint, t: f32) -> Deformed {
    let n = ck.n;
    let gamma = time_encoding(t, ck.mlp.bands);
    let freqs = position_frequencies(ck.mlp.position_bands);
    let e = ck.embed_dim;
    let mut d = Deformed {
        means: vec![0.0; 3 * n],
        quats: vec![0.0; 4 * n],
        scales: vec![0.0; 3 * n],
    };
    const CHUNK: usize = 256;
    d.means
        .par_chunks_mut(3 * CHUNK)
        .zip(d.quats.par_chunks_mut(4 * CHUNK))
        .zip(d.scales.par_chunks_mut(3 * CHUNK))
        .enumerate()
        .for_each(|(c, ((m, q), s))| {
            let (mut a, mut b) = (Vec::new(), Vec::new());
            let mut input =
                Vec::with_capacity(3 * (1 + 2 * ck.mlp.position_bands) + e + gamma.len());
            for l in 0..m.len() / 3 {
                let i = c * CHUNK + l;
                let o = if ck.is_static.get(i).copied().unwrap_or(false) {
                    [0.0; 9] // static: the canonical state at every time
                } else {
                    input.clear();
                    push_position_encoding(&ck.means[3 * i..3 * i + 3], &freqs, &mut input);
                    input.extend_from_slice(&ck.embeddings[e * i..e * (i + 1)]);
                    input.extend_from_slice(&gamma);
                    mlp_eval(&ck.mlp, &input, &mut a, &mut b)
                };
                for k in 0..3 {
                    m[3 * l + k] = ck.means[3 * i + k] + o[k];
                    s[3 * l + k] = (ck.log_scales[3 * i + k] + o[6 + k]).exp();
                }
                let q0 = normalize([
                    ck.quats[4 * i],
                    ck.quats[4 * i + 1],
                    ck.quats[4 * i + 2],
                    ck.quats[4 * i + 3],
                ]);
                let qt = normalize(quat_mul(axis_angle_to_quat([o[3], o[4], o[5]]), q0));
                q[4 * l..4 * l + 4].copy_from_slice(&qt);
            }
        });
    d
}
