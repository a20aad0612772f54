//! The linear epilogue: central finite differences of the f64 kernel for every input, a unit
//! quaternion out, and the argument checks.

use sync4d_motion::{
    linear_epilogue_backward, linear_epilogue_forward, LinearEpilogue, LinearEpilogueGradsMut,
    LinearEpilogueOut, MotionError, LINEAR_COLUMNS,
};

/// A seeded value in [-1, 1) from an index (no dependency on a generator crate).
fn value(seed: u64, i: usize) -> f64 {
    let mut z = seed.wrapping_add((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 52) as f64 - 1.0
}

struct Case {
    blended: Vec<f64>,
    x0: Vec<f64>,
    q0: Vec<f64>,
    log_s0: Vec<f64>,
}

impl Case {
    fn new(n: usize) -> Self {
        let mut blended: Vec<f64> = (0..n * LINEAR_COLUMNS).map(|i| 0.3 * value(1, i)).collect();
        for row in blended.chunks_exact_mut(LINEAR_COLUMNS) {
            row[0] += 1.0;
            row[4] += 1.0;
            row[8] += 1.0;
            row[12] += 1.0;
        }
        Case {
            blended,
            x0: (0..n * 3).map(|i| value(2, i)).collect(),
            q0: (0..n * 4).map(|i| value(3, i)).collect(),
            log_s0: (0..n * 3).map(|i| value(4, i) - 2.0).collect(),
        }
    }

    fn epilogue(&self) -> LinearEpilogue<'_, f64> {
        LinearEpilogue {
            blended: &self.blended,
            x0: &self.x0,
            q0: &self.q0,
            log_s0: &self.log_s0,
        }
    }

    /// Input `k`: blended, x0, q0, log_s0.
    fn input(&mut self, k: usize) -> &mut Vec<f64> {
        match k {
            0 => &mut self.blended,
            1 => &mut self.x0,
            2 => &mut self.q0,
            _ => &mut self.log_s0,
        }
    }

    /// L = sum of outputs times fixed weights.
    fn loss(&self, w: &[f64]) -> f64 {
        let n = self.x0.len() / 3;
        let (mut m, mut q, mut s) = (vec![0.0; n * 3], vec![0.0; n * 4], vec![0.0; n * 3]);
        let out = LinearEpilogueOut {
            means: &mut m,
            quats: &mut q,
            scales: &mut s,
        };
        linear_epilogue_forward(&self.epilogue(), out).unwrap();
        m.iter()
            .chain(&q)
            .chain(&s)
            .zip(w)
            .map(|(a, b)| a * b)
            .sum()
    }
}

#[test]
fn backward_matches_central_differences() {
    let n = 5;
    let mut case = Case::new(n);
    let w: Vec<f64> = (0..n * 10).map(|i| value(5, i)).collect();
    let (gm, rest) = w.split_at(n * 3);
    let (gq, gs) = rest.split_at(n * 4);
    let mut g = [
        vec![0.0; n * LINEAR_COLUMNS],
        vec![0.0; n * 3],
        vec![0.0; n * 4],
        vec![0.0; n * 3],
    ];
    {
        let [gb, gx, gq0, gl] = &mut g;
        let grads = LinearEpilogueGradsMut {
            blended: gb,
            x0: gx,
            q0: gq0,
            log_s0: gl,
        };
        linear_epilogue_backward(&case.epilogue(), gm, gq, gs, grads).unwrap();
    }
    let eps = 1e-6;
    for (input, grad) in (0..4).zip(&g) {
        for (i, &analytic) in grad.iter().enumerate() {
            let orig = case.input(input)[i];
            case.input(input)[i] = orig + eps;
            let up = case.loss(&w);
            case.input(input)[i] = orig - eps;
            let down = case.loss(&w);
            case.input(input)[i] = orig;
            let fd = (up - down) / (2.0 * eps);
            assert!(
                (fd - analytic).abs() <= 1e-6 * (1.0 + fd.abs()),
                "input {input} entry {i}: analytic {analytic} vs finite difference {fd}"
            );
        }
    }
}

#[test]
fn quaternions_out_are_unit_and_bad_lengths_are_named() {
    let case = Case::new(3);
    let (mut m, mut q, mut s) = (vec![0.0; 9], vec![0.0; 12], vec![0.0; 9]);
    let out = LinearEpilogueOut {
        means: &mut m,
        quats: &mut q,
        scales: &mut s,
    };
    linear_epilogue_forward(&case.epilogue(), out).unwrap();
    for r in q.chunks_exact(4) {
        let norm = r.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((norm - 1.0).abs() < 1e-12);
    }
    assert!(s.iter().all(|&v| v > 0.0));
    let bad = LinearEpilogue {
        q0: &case.q0[..8],
        ..case.epilogue()
    };
    let out = LinearEpilogueOut {
        means: &mut m,
        quats: &mut q,
        scales: &mut s,
    };
    let err = linear_epilogue_forward(&bad, out).unwrap_err();
    assert!(matches!(
        err,
        MotionError::InvalidArgument { arg: "q0", .. }
    ));
}
