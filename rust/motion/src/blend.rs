//! The node-weighted sum of the node motion model and its exact backward.
//!
//! N Gaussians at canonical means `x0` [N, 3] each blend K of M nodes (`index` [N, K]); node j
//! sits at `p_j` (`positions` [M, 3]) with inverse squared radius `inv_r2_j` ([M]) and carries a
//! row `T_j` of a table [M, C]:
//!
//! ```text
//! d2_ik = |x0_i - p_j|^2,  a_ik = -0.5 d2_ik inv_r2_j,  j = index[i, k]
//! w_ik  = softmax_k(a_ik)                      (the row's maximum subtracted)
//! b_i   = sum_k w_ik T_j                       [N, C]
//! ```
//!
//! Backward, given `gb` = dL/db [N, C]:
//!
//! ```text
//! gw_ik = gb_i . T_j,   ga_ik = w_ik (gw_ik - sum_k' w_ik' gw_ik')
//! dL/dT_j      += w_ik gb_i
//! dL/dinv_r2_j += ga_ik (-0.5 d2_ik)
//! v_ik          = 2 ga_ik (-0.5 inv_r2_j) (x0_i - p_j)
//! dL/dx0_i     += v_ik,   dL/dp_j -= v_ik
//! ```
//!
//! Parallel over chunks of Gaussians in the calling rayon pool. The node-side gradients are
//! scattered by each task of the backward into node rows of its own (the tasks are chunks of
//! Gaussians whose size depends on N, M and K alone, never on the pool); then, in parallel over
//! nodes, each node adds its tasks' rows in task order. Every output value is therefore the
//! same sequence of operations whatever the pool's size: results are bit-identical across
//! thread counts. On x86-64 CPUs with AVX2 the per-Gaussian loops run an AVX2 copy of the same
//! code, which gives the same bits as the baseline one.
//!
//! The softmax subtracts each row's largest logit, so a Gaussian far from all its nodes gets
//! finite weights (its nearest node's weight tends to 1); a row whose logits are all `-inf`
//! gets equal weights on its nodes instead of NaN.

use crate::error::{check_len, MotionError, Result};
use rayon::prelude::*;
use sync4d_scalar::Real;

/// Gaussians per parallel task of the forward.
const ROWS: usize = 256;
/// Nodes per parallel task of the backward's reduction.
const NODES: usize = 32;

/// An integer type of node indices (`index`): i32 (checkpoints) or i64 (torch's default).
pub trait NodeIndex: Copy + Send + Sync {
    /// The index as a `usize` when it is in `0..m`.
    fn checked(self, m: usize) -> Option<usize>;
    /// The index as a `usize`, once checked.
    fn get(self) -> usize;
}

macro_rules! node_index {
    ($($t:ty),*) => {$(
        impl NodeIndex for $t {
            #[inline(always)]
            fn checked(self, m: usize) -> Option<usize> {
                usize::try_from(self).ok().filter(|&j| j < m)
            }
            #[inline(always)]
            fn get(self) -> usize {
                self as usize
            }
        }
    )*};
}
node_index!(i32, i64, u32, usize);

/// Inputs of the node-weighted sum: flat row-major slices.
#[derive(Debug, Clone, Copy)]
pub struct NodeBlend<'a, T, I> {
    /// Canonical means of the Gaussians, [N, 3].
    pub x0: &'a [T],
    /// Node positions, [M, 3].
    pub positions: &'a [T],
    /// Inverse squared node radii 1 / r_j^2, [M].
    pub inv_r2: &'a [T],
    /// Node values, [M, C].
    pub table: &'a [T],
    /// Each Gaussian's K nodes, [N, K], every entry in `0..M`.
    pub index: &'a [I],
    /// K, nodes per Gaussian (at least 1).
    pub neighbours: usize,
    /// C, values per node (at least 1).
    pub channels: usize,
}

/// Gradient outputs of [`node_weighted_sum_backward`], overwritten (not added to).
#[derive(Debug)]
pub struct NodeBlendGradsMut<'a, T> {
    /// dL/dx0, [N, 3].
    pub x0: &'a mut [T],
    /// dL/dpositions, [M, 3].
    pub positions: &'a mut [T],
    /// dL/dinv_r2, [M].
    pub inv_r2: &'a mut [T],
    /// dL/dtable, [M, C].
    pub table: &'a mut [T],
}

impl<T: Real, I: NodeIndex> NodeBlend<'_, T, I> {
    /// Check every length and index; returns (N, M).
    pub fn validate(&self) -> Result<(usize, usize)> {
        let (k, c) = (self.neighbours, self.channels);
        if k == 0 {
            return Err(MotionError::invalid(
                "neighbours",
                "expected at least 1 node per Gaussian",
            ));
        }
        if c == 0 {
            return Err(MotionError::invalid(
                "channels",
                "expected at least 1 value per node",
            ));
        }
        if !self.x0.len().is_multiple_of(3) {
            return Err(MotionError::invalid(
                "x0",
                format!("expected N * 3 values, got {}", self.x0.len()),
            ));
        }
        if !self.positions.len().is_multiple_of(3) {
            return Err(MotionError::invalid(
                "positions",
                format!("expected M * 3 values, got {}", self.positions.len()),
            ));
        }
        let (n, m) = (self.x0.len() / 3, self.positions.len() / 3);
        check_len("inv_r2", self.inv_r2, m)?;
        check_len("table", self.table, m * c)?;
        check_len("index", self.index, n * k)?;
        if n * k > u32::MAX as usize {
            return Err(MotionError::invalid(
                "index",
                format!("at most {} entries, got {}", u32::MAX, n * k),
            ));
        }
        if let Some(p) = self.index.iter().position(|j| j.checked(m).is_none()) {
            return Err(MotionError::invalid(
                "index",
                format!("entry {p} (Gaussian {}) is not a node of 0..{m}", p / k),
            ));
        }
        Ok((n, m))
    }

    /// Gaussian `i`'s weights into `w` [K], its squared distances into `d2` [K] and its offsets
    /// x0_i - p_j into `diff` [K].
    #[inline(always)]
    fn row_weights(&self, i: usize, s: &mut Scratch<T>) {
        let k = self.neighbours;
        let x = [self.x0[3 * i], self.x0[3 * i + 1], self.x0[3 * i + 2]];
        let nodes = &self.index[i * k..(i + 1) * k];
        let half = T::from(0.5).unwrap();
        let mut max = T::neg_infinity();
        for (slot, ((w, d2), diff)) in s.w.iter_mut().zip(&mut s.d2).zip(&mut s.diff).enumerate() {
            let j = nodes[slot].get();
            let p = &self.positions[3 * j..3 * j + 3];
            let d = [x[0] - p[0], x[1] - p[1], x[2] - p[2]];
            let dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
            let a = -(half * dd) * self.inv_r2[j];
            (*diff, *d2, *w) = (d, dd, a);
            // Not Float::max, which would drop a NaN logit (its exp below is NaN anyway).
            max = if a > max { a } else { max };
        }
        let mut sum = T::zero();
        for a in &mut s.w {
            // exp(0) = 1 exactly; also keeps a row of all -inf finite (equal weights).
            let e = if *a == max {
                T::one()
            } else {
                (*a - max).exp_neg()
            };
            *a = e;
            sum = sum + e;
        }
        for a in &mut s.w {
            *a = *a / sum;
        }
    }

    /// Row `j` of the table, `c` (= C) values wide: a constant where the caller's is.
    #[inline(always)]
    fn row(&self, j: usize, c: usize) -> &[T] {
        &self.table[j * c..(j + 1) * c]
    }
}

/// Scratch of one task: weights, squared distances and offsets of one Gaussian's K nodes, and
/// the weights' gradients.
struct Scratch<T> {
    w: Vec<T>,
    d2: Vec<T>,
    diff: Vec<[T; 3]>,
    gw: Vec<T>,
}

impl<T: Real> Scratch<T> {
    fn new(k: usize) -> Self {
        Scratch {
            w: vec![T::zero(); k],
            d2: vec![T::zero(); k],
            diff: vec![[T::zero(); 3]; k],
            gw: vec![T::zero(); k],
        }
    }
}

/// Call `$f::<T, I, C>($args)` with the channel count `$c` as the constant C for the blends'
/// widths (19: linear, 11: dual quaternions), so that their loops over channels unroll; C = 0
/// (the width read at run time) for any other.
macro_rules! by_channels {
    ($c:expr, $f:ident($($args:expr),*)) => {
        match $c {
            19 => $f::<T, I, 19>($($args),*),
            11 => $f::<T, I, 11>($($args),*),
            _ => $f::<T, I, 0>($($args),*),
        }
    };
}

/// Whether the tasks run their AVX2 copies: where the CPU has AVX2 (x86-64 only). They are the
/// same operations in the same order on wider registers (Rust never contracts a * b + c into
/// an FMA, nor reorders a sum), so both copies give the same bits.
fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `$task` compiled for AVX2 as `$avx2`, and `$dispatch` running either copy: `$avx2` only
/// when its first argument is true, which callers derive from [`has_avx2`].
macro_rules! multiversion {
    ($task:ident, $avx2:ident, $dispatch:ident, ($($arg:ident: $ty:ty),*)) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        fn $avx2<T: Real, I: NodeIndex, const C: usize>($($arg: $ty),*) {
            $task::<T, I, C>($($arg),*)
        }

        fn $dispatch<T: Real, I: NodeIndex, const C: usize>(avx2: bool, $($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            if avx2 {
                // SAFETY: `avx2` is true only where the CPU has AVX2 (`has_avx2`).
                return unsafe { $avx2::<T, I, C>($($arg),*) };
            }
            let _ = avx2;
            $task::<T, I, C>($($arg),*)
        }
    };
}

/// a . b of equal-length slices in four interleaved partial sums (which vectorise; a single
/// running sum is a chain of dependent adds), added in a fixed order.
#[inline(always)]
fn dot4<T: Real>(a: &[T], b: &[T]) -> T {
    let mut acc = [T::zero(); 4];
    let (a4, b4) = (a.chunks_exact(4), b.chunks_exact(4));
    let (ra, rb) = (a4.remainder(), b4.remainder());
    for (a, b) in a4.zip(b4) {
        for l in 0..4 {
            acc[l] = acc[l] + a[l] * b[l];
        }
    }
    for (l, (&a, &b)) in ra.iter().zip(rb).enumerate() {
        acc[l] = acc[l] + a * b;
    }
    (acc[0] + acc[1]) + (acc[2] + acc[3])
}

/// Forward of the Gaussians from `i0`: b rows into `out`, their weights into `w_out`.
#[inline(always)]
fn forward_task<T: Real, I: NodeIndex, const C: usize>(
    blend: &NodeBlend<'_, T, I>,
    i0: usize,
    out: &mut [T],
    mut w_out: Option<&mut [T]>,
) {
    let (k, c) = (blend.neighbours, if C > 0 { C } else { blend.channels });
    let mut s = Scratch::new(k);
    for (r, b) in out.chunks_exact_mut(c).enumerate() {
        let i = i0 + r;
        blend.row_weights(i, &mut s);
        let nodes = &blend.index[i * k..(i + 1) * k];
        let w0 = s.w[0];
        for (o, &t) in b.iter_mut().zip(blend.row(nodes[0].get(), c)) {
            *o = w0 * t;
        }
        for (&ws, j) in s.w.iter().zip(nodes).skip(1) {
            for (o, &t) in b.iter_mut().zip(blend.row(j.get(), c)) {
                *o = *o + ws * t;
            }
        }
        if let Some(w_out) = w_out.as_deref_mut() {
            w_out[r * k..(r + 1) * k].copy_from_slice(&s.w);
        }
    }
}

multiversion!(
    forward_task,
    forward_task_avx2,
    forward_run,
    (blend: &NodeBlend<'_, T, I>, i0: usize, out: &mut [T], w_out: Option<&mut [T]>)
);

/// The node-weighted sum b [N, C] into `out`; with `weights` [N, K], the blend weights too.
pub fn node_weighted_sum_forward<T: Real, I: NodeIndex>(
    blend: &NodeBlend<'_, T, I>,
    out: &mut [T],
    weights: Option<&mut [T]>,
) -> Result<()> {
    forward(blend, out, weights, has_avx2())
}

fn forward<T: Real, I: NodeIndex>(
    blend: &NodeBlend<'_, T, I>,
    out: &mut [T],
    weights: Option<&mut [T]>,
    avx2: bool,
) -> Result<()> {
    let (n, _) = blend.validate()?;
    let (k, c) = (blend.neighbours, blend.channels);
    check_len("out", out, n * c)?;
    if let Some(w) = &weights {
        check_len("weights", w, n * k)?;
    }
    let task = |(chunk, out): (usize, &mut [T]), w: Option<&mut [T]>| {
        by_channels!(c, forward_run(avx2, blend, chunk * ROWS, out, w));
    };
    let chunks = out.par_chunks_mut(ROWS * c).enumerate();
    match weights {
        Some(w) => chunks
            .zip(w.par_chunks_mut(ROWS * k))
            .for_each(|(o, w)| task(o, Some(w))),
        None => chunks.for_each(|o| task(o, None)),
    }
    Ok(())
}

/// Gaussians per task of the backward, each task summing its node gradients apart: fixed by
/// the sizes alone, so that the sums do not depend on the thread count. At least 16 entries per
/// node and task, so that zeroing and reducing the tasks' node sums costs little next to them.
fn backward_rows(m: usize, k: usize) -> usize {
    (16 * m).div_ceil(k).max(1024)
}

/// Backward of the Gaussians from `i0`: dL/dx0 rows into `gx`, and their terms of the node
/// gradients added to `sums`, a row [dL/dtable (C), dL/dinv_r2, dL/dpositions (3)] per node.
#[inline(always)]
fn backward_task<T: Real, I: NodeIndex, const C: usize>(
    blend: &NodeBlend<'_, T, I>,
    grad_out: &[T],
    i0: usize,
    gx: &mut [T],
    sums: &mut [T],
) {
    let (k, c) = (blend.neighbours, if C > 0 { C } else { blend.channels });
    let width = c + 4;
    let half = T::from(0.5).unwrap();
    let two = T::from(2.0).unwrap();
    let mut s = Scratch::new(k);
    for (r, gx) in gx.chunks_exact_mut(3).enumerate() {
        let i = i0 + r;
        blend.row_weights(i, &mut s);
        let nodes = &blend.index[i * k..(i + 1) * k];
        let gb = &grad_out[i * c..(i + 1) * c];
        let mut dot = T::zero();
        for ((gw, &w), j) in s.gw.iter_mut().zip(&s.w).zip(nodes) {
            let g = dot4(gb, blend.row(j.get(), c));
            *gw = g;
            dot = dot + w * g;
        }
        let mut acc = [T::zero(); 3];
        for (slot, j) in nodes.iter().enumerate() {
            let j = j.get();
            let w = s.w[slot];
            let ga = w * (s.gw[slot] - dot);
            let gd2 = two * (ga * -(half * blend.inv_r2[j]));
            let d = s.diff[slot];
            let node = &mut sums[j * width..(j + 1) * width];
            let (gt, rest) = node.split_at_mut(c);
            for (g, &b) in gt.iter_mut().zip(gb) {
                *g = *g + w * b;
            }
            rest[0] = rest[0] + ga * -(half * s.d2[slot]);
            for a in 0..3 {
                let v = gd2 * d[a];
                acc[a] = acc[a] + v;
                rest[1 + a] = rest[1 + a] - v;
            }
        }
        gx.copy_from_slice(&acc);
    }
}

multiversion!(
    backward_task,
    backward_task_avx2,
    backward_run,
    (blend: &NodeBlend<'_, T, I>, grad_out: &[T], i0: usize, gx: &mut [T], sums: &mut [T])
);

/// The exact gradients of [`node_weighted_sum_forward`]'s b given `grad_out` = dL/db [N, C].
pub fn node_weighted_sum_backward<T: Real, I: NodeIndex>(
    blend: &NodeBlend<'_, T, I>,
    grad_out: &[T],
    grads: NodeBlendGradsMut<'_, T>,
) -> Result<()> {
    backward(blend, grad_out, grads, has_avx2())
}

fn backward<T: Real, I: NodeIndex>(
    blend: &NodeBlend<'_, T, I>,
    grad_out: &[T],
    grads: NodeBlendGradsMut<'_, T>,
    avx2: bool,
) -> Result<()> {
    let (n, m) = blend.validate()?;
    let (k, c) = (blend.neighbours, blend.channels);
    check_len("grad_out", grad_out, n * c)?;
    check_len("grad_x0", grads.x0, n * 3)?;
    check_len("grad_positions", grads.positions, m * 3)?;
    check_len("grad_inv_r2", grads.inv_r2, m)?;
    check_len("grad_table", grads.table, m * c)?;
    if n == 0 {
        for g in [grads.positions, grads.inv_r2, grads.table] {
            g.fill(T::zero());
        }
        return Ok(());
    }
    // Each task's node sums, a row [dL/dtable (C), dL/dinv_r2, dL/dpositions (3)] per node.
    let (rows, width) = (backward_rows(m, k), c + 4);
    let tasks = n.div_ceil(rows);
    let mut sums = vec![T::zero(); tasks * m * width];
    grads
        .x0
        .par_chunks_mut(rows * 3)
        .zip(sums.par_chunks_mut(m * width))
        .enumerate()
        .for_each(|(task, (gx, sums))| {
            by_channels!(
                c,
                backward_run(avx2, blend, grad_out, task * rows, gx, sums)
            );
        });

    // Per node: the tasks' sums added in task order.
    let sums = &sums;
    grads
        .table
        .par_chunks_mut(NODES * c)
        .zip(grads.positions.par_chunks_mut(NODES * 3))
        .zip(grads.inv_r2.par_chunks_mut(NODES))
        .enumerate()
        .for_each(|(chunk, ((gt, gp), gr))| {
            let j0 = chunk * NODES;
            gt.fill(T::zero());
            gp.fill(T::zero());
            gr.fill(T::zero());
            for task in 0..tasks {
                let base = (task * m + j0) * width;
                let part = &sums[base..base + gr.len() * width];
                for (((gt, gp), gr), part) in gt
                    .chunks_exact_mut(c)
                    .zip(gp.chunks_exact_mut(3))
                    .zip(gr.iter_mut())
                    .zip(part.chunks_exact(width))
                {
                    for (g, &p) in gt.iter_mut().zip(&part[..c]) {
                        *g = *g + p;
                    }
                    *gr = *gr + part[c];
                    for (g, &p) in gp.iter_mut().zip(&part[c + 1..]) {
                        *g = *g + p;
                    }
                }
            }
        });
    Ok(())
}

/// The kernels on their baseline (non-AVX2) copies whatever the CPU, for the tests that both
/// copies give the same bits.
#[doc(hidden)]
pub mod baseline {
    use super::*;

    /// [`node_weighted_sum_forward`] without AVX2.
    pub fn node_weighted_sum_forward<T: Real, I: NodeIndex>(
        blend: &NodeBlend<'_, T, I>,
        out: &mut [T],
        weights: Option<&mut [T]>,
    ) -> Result<()> {
        forward(blend, out, weights, false)
    }

    /// [`node_weighted_sum_backward`] without AVX2.
    pub fn node_weighted_sum_backward<T: Real, I: NodeIndex>(
        blend: &NodeBlend<'_, T, I>,
        grad_out: &[T],
        grads: NodeBlendGradsMut<'_, T>,
    ) -> Result<()> {
        backward(blend, grad_out, grads, false)
    }
}
