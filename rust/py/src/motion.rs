//! Node motion bindings (sync4d-motion): `node_weighted_sum_forward` and
//! `node_weighted_sum_backward` (float32 or float64 values, int32 or int64 node indices),
//! `linear_epilogue_forward` and `linear_epilogue_backward` (float32 or float64).

use numpy::Element;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sync4d_motion::{
    self as motion, LinearEpilogue, LinearEpilogueGradsMut, LinearEpilogueOut, MotionError,
    NodeBlend, NodeBlendGradsMut, NodeIndex,
};
use sync4d_raster::RasterError;
use sync4d_scalar::Real;

use crate::arrays::{
    bindings, flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out,
};
use crate::runtime::run;

/// Call `$body` with `$I` bound to the element type of the index array `$probe` (int32 or
/// int64).
macro_rules! with_index_type {
    ($probe:expr, |$I:ident| $body:expr) => {{
        if $probe.downcast::<numpy::PyArrayDyn<i64>>().is_ok() {
            type $I = i64;
            $body
        } else if $probe.downcast::<numpy::PyArrayDyn<i32>>().is_ok() {
            type $I = i32;
            $body
        } else {
            Err(PyValueError::new_err(
                "index: expected an int32 or int64 array",
            ))
        }
    }};
}

/// Run a motion kernel as `run` does, its error as the `RasterError` that `run` turns into a
/// `ValueError` naming the argument.
fn run_motion<R: Send>(
    py: Python<'_>,
    threads: usize,
    f: impl FnOnce() -> motion::Result<R> + Send,
) -> PyResult<R> {
    run(py, threads, || {
        f().map_err(|e: MotionError| RasterError::invalid(e.arg(), e.msg()))
    })
}

/// Array `a` as `T`, the dtype of the call's `first` array, or a `ValueError` naming `name`.
fn same_dtype<'py, T: Element>(a: &AnyArr<'py>, name: &str, first: &str) -> PyResult<Arr<'py, T>> {
    a.extract()
        .map_err(|_| PyValueError::new_err(format!("{name}: expected an array of {first}'s dtype")))
}

/// The node arrays of one call, borrowed from NumPy as `T` (values) and `I` (indices).
struct Inputs<'py, T: Element, I: Element> {
    x0: Arr<'py, T>,
    positions: Arr<'py, T>,
    inv_r2: Arr<'py, T>,
    table: Arr<'py, T>,
    index: Arr<'py, I>,
}

/// Values of unknown dtype: (x0, positions, inv_r2, table, index).
type AnyInputs<'py> = (
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
);

impl<'py, T: Element, I: Element> Inputs<'py, T, I> {
    fn extract(a: &AnyInputs<'py>) -> PyResult<Self> {
        Ok(Inputs {
            x0: a.0.extract()?,
            positions: same_dtype(&a.1, "positions", "x0")?,
            inv_r2: same_dtype(&a.2, "inv_r2", "x0")?,
            table: same_dtype(&a.3, "table", "x0")?,
            index: a.4.extract()?,
        })
    }

    fn blend(&self, (neighbours, channels): (usize, usize)) -> PyResult<NodeBlend<'_, T, I>> {
        Ok(NodeBlend {
            x0: flat(&self.x0, "x0")?,
            positions: flat(&self.positions, "positions")?,
            inv_r2: flat(&self.inv_r2, "inv_r2")?,
            table: flat(&self.table, "table")?,
            index: flat(&self.index, "index")?,
            neighbours,
            channels,
        })
    }
}

fn forward_typed<'py, T: Real + Element, I: NodeIndex + Element>(
    py: Python<'py>,
    a: &AnyInputs<'py>,
    sizes: (usize, usize),
    want_weights: bool,
    threads: usize,
) -> PyResult<PyObject> {
    let inputs = Inputs::<T, I>::extract(a)?;
    let blend = inputs.blend(sizes)?;
    let (n, neighbours) = (blend.x0.len() / 3, blend.neighbours);
    let out: Out<'py, T> = zeros(py, n * blend.channels);
    let weights: Option<Out<'py, T>> = want_weights.then(|| zeros(py, n * neighbours));
    let (o, w) = (slice_mut(&out), weights.as_ref().map(|w| slice_mut(w)));
    run_motion(py, threads, || {
        motion::node_weighted_sum_forward(&blend, o, w)
    })?;
    to_object(py, (out, weights))
}

fn backward_typed<'py, T: Real + Element, I: NodeIndex + Element>(
    py: Python<'py>,
    a: &AnyInputs<'py>,
    sizes: (usize, usize),
    grad_out: &AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject> {
    let inputs = Inputs::<T, I>::extract(a)?;
    let blend = inputs.blend(sizes)?;
    let grad_out: Arr<'py, T> = same_dtype(grad_out, "grad_out", "x0")?;
    let (n, m) = (blend.x0.len() / 3, blend.positions.len() / 3);
    let (gx, gp): (Out<'py, T>, Out<'py, T>) = (zeros(py, n * 3), zeros(py, m * 3));
    let gr: Out<'py, T> = zeros(py, blend.inv_r2.len());
    let gt: Out<'py, T> = zeros(py, blend.table.len());
    let grads = NodeBlendGradsMut {
        x0: slice_mut(&gx),
        positions: slice_mut(&gp),
        inv_r2: slice_mut(&gr),
        table: slice_mut(&gt),
    };
    let gb = flat(&grad_out, "grad_out")?;
    run_motion(py, threads, || {
        motion::node_weighted_sum_backward(&blend, gb, grads)
    })?;
    to_object(py, (gx, gp, gr, gt))
}

bindings! {
    (
        py,
        [
            x0: AnyArr<'py>,
            positions: AnyArr<'py>,
            inv_r2: AnyArr<'py>,
            table: AnyArr<'py>,
            index: AnyArr<'py>
        ],
        [neighbours: usize, channels: usize],
        threads
    )

    /// b_i = sum_k w_ik table[index[i, k]] with w_i = softmax_k(-0.5 |x0_i - p_j|^2 inv_r2_j):
    /// flat x0 [N*3], positions [M*3], inv_r2 [M], table [M*C] (float32 or float64, one type),
    /// index [N*K] (int32 or int64). Returns (b [N*C], the weights [N*K] or None).
    fn node_weighted_sum_forward(want_weights: bool) {
        let a = (x0, positions, inv_r2, table, index);
        with_float_type!(a.0, "x0", |T| {
            with_index_type!(a.4, |I| {
                let sizes = (neighbours, channels);
                forward_typed::<T, I>(py, &a, sizes, want_weights, threads)
            })
        })
    }

    /// Backward of `node_weighted_sum_forward` given grad_out = dL/db [N*C]: returns
    /// (dL/dx0 [N*3], dL/dpositions [M*3], dL/dinv_r2 [M], dL/dtable [M*C]).
    fn node_weighted_sum_backward(grad_out: AnyArr<'py>) {
        let a = (x0, positions, inv_r2, table, index);
        with_float_type!(a.0, "x0", |T| {
            with_index_type!(a.4, |I| {
                let sizes = (neighbours, channels);
                backward_typed::<T, I>(py, &a, sizes, &grad_out, threads)
            })
        })
    }
}

/// The epilogue's arrays (blended, x0, q0, log_s0), borrowed from NumPy as `T`.
fn epilogue_arrays<'py, T: Element>(a: [&AnyArr<'py>; 4]) -> PyResult<[Arr<'py, T>; 4]> {
    Ok([
        same_dtype(a[0], "blended", "blended")?,
        same_dtype(a[1], "x0", "blended")?,
        same_dtype(a[2], "q0", "blended")?,
        same_dtype(a[3], "log_s0", "blended")?,
    ])
}

/// The epilogue's inputs as the kernel takes them.
fn epilogue<'a, T: Element>(a: &'a [Arr<'_, T>; 4]) -> PyResult<LinearEpilogue<'a, T>> {
    Ok(LinearEpilogue {
        blended: flat(&a[0], "blended")?,
        x0: flat(&a[1], "x0")?,
        q0: flat(&a[2], "q0")?,
        log_s0: flat(&a[3], "log_s0")?,
    })
}

/// Three zeroed arrays of N*3, N*4 and N*3 values (a mean, a quaternion and a scale per row).
fn zeros_343<T: Element>(py: Python<'_>, n: usize) -> (Out<'_, T>, Out<'_, T>, Out<'_, T>) {
    (zeros(py, n * 3), zeros(py, n * 4), zeros(py, n * 3))
}

fn epilogue_forward_typed<T: Real + Element>(
    py: Python<'_>,
    a: [&AnyArr<'_>; 4],
    threads: usize,
) -> PyResult<PyObject> {
    let arrays = epilogue_arrays::<T>(a)?;
    let e = epilogue(&arrays)?;
    let (means, quats, scales) = zeros_343::<T>(py, e.x0.len() / 3);
    let out = LinearEpilogueOut {
        means: slice_mut(&means),
        quats: slice_mut(&quats),
        scales: slice_mut(&scales),
    };
    run_motion(py, threads, || motion::linear_epilogue_forward(&e, out))?;
    to_object(py, (means, quats, scales))
}

fn epilogue_backward_typed<'py, T: Real + Element>(
    py: Python<'py>,
    a: [&AnyArr<'py>; 4],
    g: [&AnyArr<'py>; 3],
    threads: usize,
) -> PyResult<PyObject> {
    let arrays = epilogue_arrays::<T>(a)?;
    let e = epilogue(&arrays)?;
    let (gm, gq, gs): (Arr<'py, T>, Arr<'py, T>, Arr<'py, T>) = (
        same_dtype(g[0], "grad_means", "blended")?,
        same_dtype(g[1], "grad_quats", "blended")?,
        same_dtype(g[2], "grad_scales", "blended")?,
    );
    let (gm, gq, gs) = (
        flat(&gm, "grad_means")?,
        flat(&gq, "grad_quats")?,
        flat(&gs, "grad_scales")?,
    );
    let gb: Out<'py, T> = zeros(py, e.blended.len());
    let (gx, gq0, gl) = zeros_343::<T>(py, e.x0.len() / 3);
    let grads = LinearEpilogueGradsMut {
        blended: slice_mut(&gb),
        x0: slice_mut(&gx),
        q0: slice_mut(&gq0),
        log_s0: slice_mut(&gl),
    };
    run_motion(py, threads, || {
        motion::linear_epilogue_backward(&e, gm, gq, gs, grads)
    })?;
    to_object(py, (gb, gx, gq0, gl))
}

bindings! {
    (
        py,
        [blended: AnyArr<'py>, x0: AnyArr<'py>, q0: AnyArr<'py>, log_s0: AnyArr<'py>],
        [],
        threads
    )

    /// The linear blend's epilogue: flat blended [N*19], x0 [N*3], q0 [N*4], log_s0 [N*3]
    /// (float32 or float64, one type). Returns (means [N*3], unit quaternions [N*4], scales
    /// [N*3]).
    fn linear_epilogue_forward() {
        let a = [&blended, &x0, &q0, &log_s0];
        with_float_type!(blended, "blended", |T| epilogue_forward_typed::<T>(py, a, threads))
    }

    /// Backward of `linear_epilogue_forward` given dL/d(means [N*3], quats [N*4], scales
    /// [N*3]): returns (dL/dblended [N*19], dL/dx0 [N*3], dL/dq0 [N*4], dL/dlog_s0 [N*3]).
    fn linear_epilogue_backward(
        grad_means: AnyArr<'py>,
        grad_quats: AnyArr<'py>,
        grad_scales: AnyArr<'py>
    ) {
        let a = [&blended, &x0, &q0, &log_s0];
        let g = [&grad_means, &grad_quats, &grad_scales];
        with_float_type!(blended, "blended", |T| epilogue_backward_typed::<T>(py, a, g, threads))
    }
}
