//! D_theta evaluated in Rust (f32), exactly as `sync4d/phase1/deform.py`: the input
//! [x0 or its encoding; z; gamma(t)] with gamma(t) = [t, sin(2^0 pi t), cos(2^0 pi t), ...]
//! (the position encoding: x0, then per band sin and cos of the 3 coordinates), ReLU trunk, linear
//! head scaled to (dx, dw, dl), then Eqs. 2-4: x = x0 + dx, q = normalize(aa2q(dw) (x) q0),
//! s = exp(log s0 + dl). D_theta reads the position in `position_unit`s (x0 / position_unit).
//!
//! Node checkpoints (`"motion": "nodes"`, SC-GS style control nodes, `sync4d/phase1/nodes.py`):
//! D_theta is evaluated once per node j and time on [p_j or its encoding; z_j; gamma(t)], giving
//! the node's rigid motion (q_j = aa2q(dw_j) on the w >= 0 hemisphere, p_j -> p_j + dx_j) and
//! its dl_j. Gaussian i blends its K nodes with w_ij = softmax_j(-|x0_i - p_j|^2 / (2 r_j^2)):
//! linearly (x = sum_j w_ij (R_j (x0 - p_j) + p_j + dx_j), computed as Python does as
//! (sum_j w_ij R_j) x0 + sum_j w_ij T_j; q = normalize((sum_j w_ij q_j) (x) q0)) or as dual
//! quaternions (the normalised sum of the nodes' (q_j, 0.5 (0, T_j) (x) q_j),
//! T_j = p_j + dx_j - R_j p_j); s = exp(log s0 + sum_j w_ij dl_j) for both.

use rayon::prelude::*;

use crate::checkpoint::{Blend, Checkpoint, DeformMlp, Linear, Nodes};
use sync4d_motion::{
    linear_epilogue_forward, node_weighted_sum_forward, LinearEpilogue, LinearEpilogueOut,
    NodeBlend, LINEAR_COLUMNS,
};
use sync4d_raster::linalg::mul3v;
use sync4d_scalar::quat::{quat_conj, quat_mul, quat_to_rotmat};

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

/// gamma(t): [t, sin(2^0 w t), cos(2^0 w t), ..., sin(2^(L-1) w t), cos(2^(L-1) w t)], w =
/// `frequency` (the paper's pi; `DeformMlp::time_frequency`).
pub fn time_encoding(t: f32, bands: usize, frequency: f32) -> Vec<f32> {
    let mut out = Vec::with_capacity(1 + 2 * bands);
    out.push(t);
    for b in 0..bands {
        let a = t * (2.0f32.powi(b as i32) * frequency);
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

fn normalize(q: [f32; 4]) -> [f32; 4] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        .sqrt()
        .max(1e-12);
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

/// aa2q as `sync4d.geometry.axis_angle_to_quat`: (cos(theta / 2), w sin(theta / 2) / theta),
/// with its Taylor series below 1e-4 rad, normalised.
fn axis_angle_to_quat(w: [f32; 3]) -> [f32; 4] {
    let theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    let (half_sinc, cos_half) = if theta2 < 1e-8 {
        (0.5 - theta2 / 48.0, 1.0 - theta2 / 8.0)
    } else {
        let theta = theta2.max(1e-24).sqrt();
        ((0.5 * theta).sin() / theta, (0.5 * theta).cos())
    };
    let q = [
        cos_half,
        w[0] * half_sinc,
        w[1] * half_sinc,
        w[2] * half_sinc,
    ];
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

/// The rotation matrix (row-major) of quaternion `q` (normalised first), as
/// `sync4d.geometry.quat_to_matrix`.
fn quat_to_matrix(q: [f32; 4]) -> [[f32; 3]; 3] {
    quat_to_rotmat(normalize(q))
}

/// D_theta's input for canonical position `x` and embedding `z` at the time encoding `gamma`
/// (the position read in `position_unit`s, as Python does).
fn mlp_input(
    mlp: &DeformMlp,
    x: &[f32],
    z: &[f32],
    gamma: &[f32],
    freqs: &[f32],
    out: &mut Vec<f32>,
) {
    out.clear();
    if mlp.position_unit == 1.0 {
        push_position_encoding(x, freqs, out);
    } else {
        let u = mlp.position_unit;
        push_position_encoding(&[x[0] / u, x[1] / u, x[2] / u], freqs, out);
    }
    out.extend_from_slice(z);
    out.extend_from_slice(gamma);
}

/// The checkpoint's Gaussians deformed to time `t` (parallel over Gaussians; a node
/// checkpoint evaluates D_theta once per node, then blends per Gaussian).
pub fn deform_at(ck: &Checkpoint, t: f32) -> Deformed {
    /// Gaussians a parallel task deforms.
    const CHUNK: usize = 256;
    if let Some(nodes) = &ck.nodes {
        let offsets = node_offsets(ck, nodes, t);
        return blend_nodes(ck, nodes, &offsets);
    }
    let n = ck.n;
    let gamma = time_encoding(t, ck.mlp.bands, ck.mlp.time_frequency);
    let freqs = position_frequencies(ck.mlp.position_bands);
    let e = ck.embed_dim;
    let mut d = Deformed {
        means: vec![0.0; 3 * n],
        quats: vec![0.0; 4 * n],
        scales: vec![0.0; 3 * n],
    };
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
                    let (x0, z) = (
                        &ck.means[3 * i..3 * i + 3],
                        &ck.embeddings[e * i..e * (i + 1)],
                    );
                    mlp_input(&ck.mlp, x0, z, &gamma, &freqs, &mut input);
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

/// D_theta's (dx, dw, dl) of every node at time `t`: M rows of 9 (parallel over nodes).
pub fn node_offsets(ck: &Checkpoint, nodes: &Nodes, t: f32) -> Vec<[f32; 9]> {
    let gamma = time_encoding(t, ck.mlp.bands, ck.mlp.time_frequency);
    let freqs = position_frequencies(ck.mlp.position_bands);
    let e = ck.embed_dim;
    (0..nodes.m)
        .into_par_iter()
        .with_min_len(32)
        .map_init(
            || (Vec::new(), Vec::new(), Vec::new()),
            |(input, a, b), j| {
                let p = &nodes.positions[3 * j..3 * j + 3];
                let z = &nodes.embeddings[e * j..e * (j + 1)];
                mlp_input(&ck.mlp, p, z, &gamma, &freqs, input);
                mlp_eval(&ck.mlp, input, a, b)
            },
        )
        .collect()
}

/// One node's rigid motion at a time, x -> R x + T: its unit quaternion on the w >= 0
/// hemisphere, that rotation as a matrix (row-major, 9 values), T = p + dx - R p, the dual part
/// 0.5 (0, T) (x) q, and the log-scale offset D_theta gave it.
struct NodeMotion {
    q: [f32; 4],
    r: [f32; 9],
    t: [f32; 3],
    dual: [f32; 4],
    dl: [f32; 3],
}

fn node_motion(p: [f32; 3], o: &[f32; 9]) -> NodeMotion {
    let mut q = axis_angle_to_quat([o[3], o[4], o[5]]);
    if q[0] < 0.0 {
        q = [-q[0], -q[1], -q[2], -q[3]];
    }
    let r = quat_to_matrix(q);
    let rp = mul3v(&r, p);
    let t = [
        p[0] + o[0] - rp[0],
        p[1] + o[1] - rp[1],
        p[2] + o[2] - rp[2],
    ];
    let d = quat_mul([0.0, t[0], t[1], t[2]], q);
    NodeMotion {
        q,
        r: [
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
        ],
        t,
        dual: [0.5 * d[0], 0.5 * d[1], 0.5 * d[2], 0.5 * d[3]],
        dl: [o[6], o[7], o[8]],
    }
}

/// The table of node values each Gaussian blends, M rows as `sync4d.phase1.nodes.blend`
/// builds it: the linear blend's 19 columns (R row-major, T, q, dl) or the dual quaternions'
/// 11 (q, its dual part, dl).
fn node_table(nodes: &Nodes, offsets: &[[f32; 9]]) -> (Vec<f32>, usize) {
    let channels = match nodes.blend {
        Blend::Linear => LINEAR_COLUMNS,
        Blend::DualQuaternion => 11,
    };
    let mut table = Vec::with_capacity(nodes.m * channels);
    for (j, o) in offsets.iter().enumerate() {
        let p = &nodes.positions[3 * j..3 * j + 3];
        let nm = node_motion([p[0], p[1], p[2]], o);
        match nodes.blend {
            Blend::Linear => {
                table.extend_from_slice(&nm.r);
                table.extend_from_slice(&nm.t);
                table.extend_from_slice(&nm.q);
            }
            Blend::DualQuaternion => {
                table.extend_from_slice(&nm.q);
                table.extend_from_slice(&nm.dual);
            }
        }
        table.extend_from_slice(&nm.dl);
    }
    (table, channels)
}

/// The blend weights [N, K] of the checkpoint's Gaussians on their nodes, by the node motion
/// crate's softmax (`sync4d.phase1.nodes.blend_weights`); each row sums to 1.
///
/// # Panics
/// If the nodes do not fit the Gaussians, which the checkpoint reader has checked.
#[must_use]
pub fn node_weights(ck: &Checkpoint, nodes: &Nodes) -> Vec<f32> {
    let ones = vec![1.0f32; nodes.m];
    let mut sums = vec![0.0f32; ck.n];
    let mut w = vec![0.0f32; ck.n * nodes.k];
    node_weighted_sum_forward(&blend_input(ck, nodes, &ones, 1), &mut sums, Some(&mut w))
        .expect("the checkpoint reader checks the node tables");
    w
}

fn blend_input<'a>(
    ck: &'a Checkpoint,
    nodes: &'a Nodes,
    table: &'a [f32],
    channels: usize,
) -> NodeBlend<'a, f32, u32> {
    NodeBlend {
        x0: &ck.means,
        positions: &nodes.positions,
        inv_r2: &nodes.inv_sq_radii,
        table,
        index: &nodes.index,
        neighbours: nodes.k,
        channels,
    }
}

/// The checkpoint's Gaussians moved by the nodes, whose D_theta outputs are `offsets` (M rows
/// of (dx, dw, dl), as [`node_offsets`] gives), with the node motion crate's forward, the
/// kernels training runs (`sync4d-motion`): the softmax-weighted sum of each Gaussian's nodes'
/// values, then the linear blend's epilogue, or the dual quaternions' normalisation.
///
/// # Panics
/// If the nodes do not fit the Gaussians, which the checkpoint reader has checked.
#[must_use]
pub fn blend_nodes(ck: &Checkpoint, nodes: &Nodes, offsets: &[[f32; 9]]) -> Deformed {
    /// Gaussians a parallel task deforms.
    const CHUNK: usize = 256;
    const CHECKED: &str = "the checkpoint reader checks the node tables";
    let n = ck.n;
    let (table, channels) = node_table(nodes, offsets);
    let mut b = vec![0.0f32; n * channels];
    node_weighted_sum_forward(&blend_input(ck, nodes, &table, channels), &mut b, None)
        .expect(CHECKED);
    let q0: Vec<f32> = ck
        .quats
        .chunks_exact(4)
        .flat_map(|q| {
            let norm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
                .sqrt()
                .max(1e-12);
            [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]
        })
        .collect();
    let mut d = Deformed {
        means: vec![0.0; 3 * n],
        quats: vec![0.0; 4 * n],
        scales: vec![0.0; 3 * n],
    };
    if nodes.blend == Blend::Linear {
        let e = LinearEpilogue {
            blended: &b,
            x0: &ck.means,
            q0: &q0,
            log_s0: &ck.log_scales,
        };
        let out = LinearEpilogueOut {
            means: &mut d.means,
            quats: &mut d.quats,
            scales: &mut d.scales,
        };
        linear_epilogue_forward(&e, out).expect(CHECKED);
        return d;
    }
    d.means
        .par_chunks_mut(3 * CHUNK)
        .zip(d.quats.par_chunks_mut(4 * CHUNK))
        .zip(d.scales.par_chunks_mut(3 * CHUNK))
        .enumerate()
        .for_each(|(c, ((m, q), s))| {
            for l in 0..m.len() / 3 {
                let i = c * CHUNK + l;
                let row = &b[channels * i..channels * (i + 1)];
                let x0 = [ck.means[3 * i], ck.means[3 * i + 1], ck.means[3 * i + 2]];
                let norm = (row[0] * row[0] + row[1] * row[1] + row[2] * row[2] + row[3] * row[3])
                    .sqrt()
                    .max(1e-12);
                let r = [row[0] / norm, row[1] / norm, row[2] / norm, row[3] / norm];
                let dd = [row[4] / norm, row[5] / norm, row[6] / norm, row[7] / norm];
                let rx = mul3v(&quat_to_matrix(r), x0);
                let tr = quat_mul(dd, quat_conj(r));
                m[3 * l..3 * l + 3].copy_from_slice(&[
                    rx[0] + 2.0 * tr[1],
                    rx[1] + 2.0 * tr[2],
                    rx[2] + 2.0 * tr[3],
                ]);
                let q0i = [q0[4 * i], q0[4 * i + 1], q0[4 * i + 2], q0[4 * i + 3]];
                q[4 * l..4 * l + 4].copy_from_slice(&normalize(quat_mul(r, q0i)));
                for a in 0..3 {
                    s[3 * l + a] = (ck.log_scales[3 * i + a] + row[8 + a]).exp();
                }
            }
        });
    d
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::checkpoint::{Blend, Checkpoint, DeformMlp, Linear, Nodes};

    const E: usize = 2;
    const HIDDEN: usize = 4;
    const SCALES: [f32; 3] = [0.1, 0.1, 0.05];

    /// A small deterministic pseudo-random stream in [-1, 1).
    fn stream(seed: u64) -> impl FnMut() -> f32 {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        }
    }

    /// Gaussians at `means` moved by the nodes at `positions` (radii `radius`), each
    /// reading the nodes `index` (K per Gaussian); D_theta has a random trunk and a head whose
    /// weights are zero and whose bias is `head_bias` (so every node gets the same (dx, dw, dl)
    /// at every time: the bias times the output scales).
    fn model(
        means: Vec<f32>,
        positions: Vec<f32>,
        radius: f32,
        index: Vec<u32>,
        blend: Blend,
        head_bias: [f32; 9],
    ) -> Checkpoint {
        let n = means.len() / 3;
        let m = positions.len() / 3;
        let k = index.len() / n;
        let mut r = stream(7);
        let input = 3 + E + 3;
        Checkpoint {
            n,
            means,
            quats: (0..4 * n).map(|_| r()).collect(),
            log_scales: (0..3 * n).map(|_| r() - 3.0).collect(),
            opacities: vec![0.5; n],
            sh: vec![0.0; 3 * n],
            sh_degree: 0,
            embeddings: (0..E * n).map(|_| r()).collect(),
            embed_dim: E,
            is_static: Vec::new(),
            nodes: Some(Nodes {
                m,
                k,
                positions,
                inv_sq_radii: vec![1.0 / (radius * radius); m],
                embeddings: (0..E * m).map(|_| r()).collect(),
                index,
                blend,
            }),
            mlp: DeformMlp {
                trunk: vec![Linear {
                    weight: (0..HIDDEN * input).map(|_| r()).collect(),
                    bias: (0..HIDDEN).map(|_| r()).collect(),
                    inputs: input,
                    outputs: HIDDEN,
                }],
                head: Linear {
                    weight: vec![0.0; 9 * HIDDEN],
                    bias: head_bias.to_vec(),
                    inputs: HIDDEN,
                    outputs: 9,
                },
                bands: 1,
                time_frequency: std::f32::consts::PI,
                position_bands: 0,
                scales: SCALES,
                position_unit: 1.0,
            },
            near: 0.01,
            background: [1.0; 3],
            cameras: Vec::new(),
        }
    }

    fn random_model(n: usize, m: usize, k: usize, blend: Blend, head_bias: [f32; 9]) -> Checkpoint {
        let mut r = stream(3);
        let means = (0..3 * n).map(|_| r()).collect();
        let positions = (0..3 * m).map(|_| r()).collect();
        let index = (0..n * k).map(|i| ((i * 7 + i / k) % m) as u32).collect();
        model(means, positions, 0.4, index, blend, head_bias)
    }

    fn close(a: &[f32], b: &[f32], tol: f32) -> bool {
        a.len() == b.len() && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol)
    }

    /// The rotation of unit quaternion `q` applied to `v`.
    fn rotate(q: [f32; 4], v: [f32; 3]) -> [f32; 3] {
        mul3v(&quat_to_matrix(q), v)
    }

    #[test]
    fn identity_motion_gives_the_canonical_gaussians() {
        for blend in [Blend::Linear, Blend::DualQuaternion] {
            let ck = random_model(40, 6, 3, blend, [0.0; 9]);
            for t in [0.0, 0.37, 1.0] {
                let d = deform_at(&ck, t);
                assert!(close(&d.means, &ck.means, 1e-6), "{blend:?}");
                let q0: Vec<f32> = ck
                    .quats
                    .chunks(4)
                    .flat_map(|q| normalize([q[0], q[1], q[2], q[3]]))
                    .collect();
                assert!(close(&d.quats, &q0, 1e-6), "{blend:?}");
                let s0: Vec<f32> = ck.log_scales.iter().map(|v| v.exp()).collect();
                assert!(close(&d.scales, &s0, 1e-7), "{blend:?}");
            }
        }
    }

    #[test]
    fn a_single_node_moves_a_point_by_its_rigid_motion() {
        // A quarter turn about z, then dx: the point one unit along x from the node ends one
        // unit along y from the moved node.
        let (dx, dw, dl) = (
            [0.5, -0.25, 1.0],
            [0.0, 0.0, std::f32::consts::FRAC_PI_2],
            [0.1, -0.2, 0.05],
        );
        let mut bias = [0.0; 9];
        for a in 0..3 {
            bias[a] = dx[a] / SCALES[0];
            bias[3 + a] = dw[a] / SCALES[1];
            bias[6 + a] = dl[a] / SCALES[2];
        }
        for blend in [Blend::Linear, Blend::DualQuaternion] {
            let mut ck = model(
                vec![2.0, 2.0, 3.0],
                vec![1.0, 2.0, 3.0],
                0.5,
                vec![0],
                blend,
                bias,
            );
            ck.quats = vec![1.0, 0.0, 0.0, 0.0];
            let d = deform_at(&ck, 0.6);
            assert!(
                close(&d.means, &[1.5, 2.75, 4.0], 2e-6),
                "{blend:?} {:?}",
                d.means
            );
            let h = std::f32::consts::FRAC_1_SQRT_2;
            assert!(
                close(&d.quats, &[h, 0.0, 0.0, h], 1e-6),
                "{blend:?} {:?}",
                d.quats
            );
            let s: Vec<f32> = (0..3).map(|a| (ck.log_scales[a] + dl[a]).exp()).collect();
            assert!(close(&d.scales, &s, 1e-6), "{blend:?}");
        }
    }

    #[test]
    fn blends_agree_on_one_shared_rigid_motion() {
        // Every node follows x -> R x + T: node j's offsets are dw = omega, dx = R p_j + T - p_j.
        let omega = [0.4f32, -0.9, 0.7];
        let tr = [0.3f32, -0.1, 0.25];
        let rq = axis_angle_to_quat(omega);
        let lin = random_model(60, 8, 4, Blend::Linear, [0.0; 9]);
        let nodes = lin.nodes.as_ref().unwrap();
        let offsets: Vec<[f32; 9]> = nodes
            .positions
            .chunks(3)
            .map(|p| {
                let rp = rotate(rq, [p[0], p[1], p[2]]);
                let mut o = [0.0; 9];
                for a in 0..3 {
                    o[a] = rp[a] + tr[a] - p[a];
                    o[3 + a] = omega[a];
                    o[6 + a] = 0.1 * a as f32;
                }
                o
            })
            .collect();
        let mut dq = lin.clone();
        dq.nodes.as_mut().unwrap().blend = Blend::DualQuaternion;
        let a = blend_nodes(&lin, nodes, &offsets);
        let b = blend_nodes(&dq, dq.nodes.as_ref().unwrap(), &offsets);
        assert!(close(&a.means, &b.means, 1e-5));
        assert!(close(&a.quats, &b.quats, 1e-6));
        assert!(close(&a.scales, &b.scales, 1e-6));
        for i in 0..lin.n {
            let x0 = [lin.means[3 * i], lin.means[3 * i + 1], lin.means[3 * i + 2]];
            let rx = rotate(rq, x0);
            let want = [rx[0] + tr[0], rx[1] + tr[1], rx[2] + tr[2]];
            assert!(close(&a.means[3 * i..3 * i + 3], &want, 1e-5));
            let q0 = &lin.quats[4 * i..4 * i + 4];
            let qw = normalize(quat_mul(rq, normalize([q0[0], q0[1], q0[2], q0[3]])));
            assert!(close(&a.quats[4 * i..4 * i + 4], &qw, 1e-6));
            for c in 0..3 {
                let s = (lin.log_scales[3 * i + c] + 0.1 * c as f32).exp();
                assert!((a.scales[3 * i + c] - s).abs() <= 1e-6 * s.max(1.0));
            }
        }
    }

    #[test]
    fn blends_differ_on_opposite_rotations_as_skinning_does() {
        // Two nodes at the origin turn by +-theta about z; a point one unit out weighs them
        // equally. Linear blending averages the two positions (the point moves in, to
        // cos theta: the candy-wrapper collapse), dual quaternions average the rotations (the
        // identity: the point stays, at its distance).
        let theta = 1.2f32;
        let offsets = [
            [0.0, 0.0, 0.0, 0.0, 0.0, theta, 0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, 0.0, 0.0, -theta, 0.0, 0.0, 0.0],
        ];
        let mut got = Vec::new();
        for blend in [Blend::Linear, Blend::DualQuaternion] {
            let ck = model(
                vec![1.0, 0.0, 0.0],
                vec![0.0; 6],
                0.5,
                vec![0, 1],
                blend,
                [0.0; 9],
            );
            let d = blend_nodes(&ck, ck.nodes.as_ref().unwrap(), &offsets);
            got.push(d.means);
        }
        assert!(
            close(&got[0], &[theta.cos(), 0.0, 0.0], 1e-6),
            "{:?}",
            got[0]
        );
        assert!(close(&got[1], &[1.0, 0.0, 0.0], 1e-6), "{:?}", got[1]);
        // Translations alone blend the same way in both: x0 + sum_j w_j dx_j.
        let offsets = [
            [0.2, 0.0, -0.4, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            [0.0, 0.6, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        ];
        for blend in [Blend::Linear, Blend::DualQuaternion] {
            let ck = model(
                vec![1.0, 0.0, 0.0],
                vec![0.0; 6],
                0.5,
                vec![0, 1],
                blend,
                [0.0; 9],
            );
            let d = blend_nodes(&ck, ck.nodes.as_ref().unwrap(), &offsets);
            assert!(
                close(&d.means, &[1.1, 0.3, -0.1], 1e-6),
                "{blend:?} {:?}",
                d.means
            );
        }
    }

    #[test]
    fn weights_sum_to_one_and_survive_far_gaussians() {
        // One Gaussian per case, each blending all 5 nodes.
        let cases = |nodes: &Nodes| -> Vec<[f32; 3]> {
            vec![
                [0.1, -0.2, 0.3],
                [30.0, 0.0, 0.0],
                [1e6, -1e6, 1e6],
                [1e20, 1e20, -1e20], // squared distances overflow to inf
                nodes.positions[3..6].try_into().unwrap(),
                [0.5, 0.5, 0.5],
            ]
        };
        let weights = |ck: &Checkpoint, xs: &[[f32; 3]]| -> Vec<f32> {
            let mut ck = ck.clone();
            ck.n = xs.len();
            ck.means = xs.iter().flatten().copied().collect();
            let nodes = ck.nodes.as_mut().unwrap();
            nodes.index = (0..xs.len() * 5).map(|i| (i % 5) as u32).collect();
            let nodes = ck.nodes.clone().unwrap();
            node_weights(&ck, &nodes)
        };
        let ck = random_model(10, 5, 5, Blend::Linear, [0.0; 9]);
        let xs = cases(ck.nodes.as_ref().unwrap());
        let w = weights(&ck, &xs);
        for (x0, row) in xs.iter().zip(w.chunks(5)) {
            assert!(
                row.iter().all(|v| v.is_finite() && *v >= 0.0),
                "{x0:?} {row:?}"
            );
            assert!(
                (row.iter().sum::<f32>() - 1.0).abs() < 1e-6,
                "{x0:?} {row:?}"
            );
        }
        // The nearest node takes all the weight far away.
        assert!(w[10..15].iter().any(|v| *v > 0.999));
        // Radii at Python's clamp (1 / r^2 = 1e20), and radii so large that 1 / r^2 is 0.
        // The infinitely far Gaussian is left out of the second: 0 * inf is NaN in training's
        // forward (and in torch's `blend_weights`), which the renderer now shares.
        for (radii, far) in [
            (vec![1e20; 5], true),
            (vec![0.0, 0.0, 1.0, 1.0, 1.0], false),
        ] {
            let mut other = ck.clone();
            other.nodes.as_mut().unwrap().inv_sq_radii = radii;
            let xs: Vec<[f32; 3]> = xs.iter().copied().filter(|x| far || x[0] < 1e19).collect();
            let w = weights(&other, &xs);
            for (x0, row) in xs.iter().zip(w.chunks(5)) {
                assert!(row.iter().all(|v| v.is_finite()), "{x0:?} {row:?}");
                assert!(
                    (row.iter().sum::<f32>() - 1.0).abs() < 1e-6,
                    "{x0:?} {row:?}"
                );
            }
        }
        // And the whole deformation stays finite with far Gaussians in it, for both blends.
        for blend in [Blend::Linear, Blend::DualQuaternion] {
            let mut far = random_model(
                12,
                5,
                3,
                blend,
                [1.0, -2.0, 0.5, 3.0, 1.0, -1.0, 0.2, 0.1, 0.3],
            );
            far.means[0..3].copy_from_slice(&[1e6, -1e6, 1e6]);
            far.means[3..6].copy_from_slice(&[1e20, 1e20, -1e20]);
            let d = deform_at(&far, 0.5);
            assert!(
                d.means
                    .iter()
                    .chain(&d.quats)
                    .chain(&d.scales)
                    .all(|v| v.is_finite()),
                "{blend:?}"
            );
        }
    }
}
