//! Node motion bindings (sync4d-motion): `node_weighted_sum_forward` and
//! `node_weighted_sum_backward` (float32 or float64 values, int32 or int64 node indices),
//! `linear_epilogue_forward` and `linear_epilogue_backward` (float32 or float64).

use numpy::Element;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sync4d_motion::{
    self as motion, LinearEpilogue, LinearEpilogueGradsMut, LinearEpilogueOut, MotionError,
    NodeBlend, NodeBlendGradsMut, NodeIndex, Real,
};
use sync4d_raster::RasterError;

use crate::arrays::{flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out};
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

/// A kernel's error as the `RasterError` that `run` turns into a `ValueError` naming the
/// argument.
fn to_raster(e: MotionError) -> RasterError {
    RasterError::invalid(e.arg(), e.msg())
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
        let same = |name: &'static str| {
            move |_| PyValueError::new_err(format!("{name}: expected an array of x0's dtype"))
        };
        Ok(Inputs {
            x0: a.0.extract()?,
            positions: a.1.extract().map_err(same("positions"))?,
            inv_r2: a.2.extract().map_err(same("inv_r2"))?,
            table: a.3.extract().map_err(same("table"))?,
            index: a.4.extract()?,
        })
    }

    fn blend(&self, neighbours: usize, channels: usize) -> PyResult<NodeBlend<'_, T, I>> {
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

fn forward_typed<'py, T, I>(
    py: Python<'py>,
    a: &AnyInputs<'py>,
    neighbours: usize,
    channels: usize,
    want_weights: bool,
    threads: usize,
) -> PyResult<PyObject>
where
    T: Real + Element,
    I: NodeIndex + Element,
{
    let inputs = Inputs::<T, I>::extract(a)?;
    let blend = inputs.blend(neighbours, channels)?;
    let n = blend.x0.len() / 3;
    let out: Out<'py, T> = zeros(py, n * channels);
    let weights: Option<Out<'py, T>> = want_weights.then(|| zeros(py, n * neighbours));
    let (o, w) = (slice_mut(&out), weights.as_ref().map(|w| slice_mut(w)));
    run(py, threads, || {
        motion::node_weighted_sum_forward(&blend, o, w).map_err(to_raster)
    })?;
    to_object(py, (out, weights))
}

#[allow(clippy::too_many_arguments)]
fn backward_typed<'py, T, I>(
    py: Python<'py>,
    a: &AnyInputs<'py>,
    neighbours: usize,
    channels: usize,
    grad_out: &AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject>
where
    T: Real + Element,
    I: NodeIndex + Element,
{
    let inputs = Inputs::<T, I>::extract(a)?;
    let blend = inputs.blend(neighbours, channels)?;
    let grad_out: Arr<'py, T> = grad_out
        .extract()
        .map_err(|_| PyValueError::new_err("grad_out: expected an array of x0's dtype"))?;
    let gb = flat(&grad_out, "grad_out")?;
    let (n, m) = (blend.x0.len() / 3, blend.positions.len() / 3);
    let gx: Out<'py, T> = zeros(py, n * 3);
    let gp: Out<'py, T> = zeros(py, m * 3);
    let gr: Out<'py, T> = zeros(py, blend.inv_r2.len());
    let gt: Out<'py, T> = zeros(py, blend.table.len());
    let grads = NodeBlendGradsMut {
        x0: slice_mut(&gx),
        positions: slice_mut(&gp),
        inv_r2: slice_mut(&gr),
        table: slice_mut(&gt),
    };
    run(py, threads, || {
        motion::node_weighted_sum_backward(&blend, gb, grads).map_err(to_raster)
    })?;
    to_object(py, (gx, gp, gr, gt))
}

/// b_i = sum_k w_ik table[index[i, k]] with w_i = softmax_k(-0.5 |x0_i - p_j|^2 inv_r2_j):
/// flat x0 [N*3], positions [M*3], inv_r2 [M], table [M*C] (float32 or float64, one type),
/// index [N*K] (int32 or int64). Returns (b [N*C], the weights [N*K] or None).
#[pyfunction]
#[pyo3(signature = (
    x0, positions, inv_r2, table, index, *, neighbours, channels, want_weights, threads
))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn node_weighted_sum_forward<'py>(
    py: Python<'py>,
    x0: AnyArr<'py>,
    positions: AnyArr<'py>,
    inv_r2: AnyArr<'py>,
    table: AnyArr<'py>,
    index: AnyArr<'py>,
    neighbours: usize,
    channels: usize,
    want_weights: bool,
    threads: usize,
) -> PyResult<PyObject> {
    let a = (x0, positions, inv_r2, table, index);
    with_float_type!(a.0, "x0", |T| {
        with_index_type!(a.4, |I| {
            forward_typed::<T, I>(py, &a, neighbours, channels, want_weights, threads)
        })
    })
}

/// Backward of `node_weighted_sum_forward` given grad_out = dL/db [N*C]: returns
/// (dL/dx0 [N*3], dL/dpositions [M*3], dL/dinv_r2 [M], dL/dtable [M*C]).
#[pyfunction]
#[pyo3(signature = (
    x0, positions, inv_r2, table, index, *, neighbours, channels, grad_out, threads
))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn node_weighted_sum_backward<'py>(
    py: Python<'py>,
    x0: AnyArr<'py>,
    positions: AnyArr<'py>,
    inv_r2: AnyArr<'py>,
    table: AnyArr<'py>,
    index: AnyArr<'py>,
    neighbours: usize,
    channels: usize,
    grad_out: AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject> {
    let a = (x0, positions, inv_r2, table, index);
    with_float_type!(a.0, "x0", |T| {
        with_index_type!(a.4, |I| {
            backward_typed::<T, I>(py, &a, neighbours, channels, &grad_out, threads)
        })
    })
}

/// The epilogue's arrays of one call, borrowed from NumPy as `T`.
struct EpilogueInputs<'py, T: Element> {
    blended: Arr<'py, T>,
    x0: Arr<'py, T>,
    q0: Arr<'py, T>,
    log_s0: Arr<'py, T>,
}

impl<'py, T: Element> EpilogueInputs<'py, T> {
    fn extract(a: [&AnyArr<'py>; 4]) -> PyResult<Self> {
        let get = |i: usize, name: &str| {
            a[i].extract::<Arr<'py, T>>().map_err(|_| {
                PyValueError::new_err(format!("{name}: expected an array of blended's dtype"))
            })
        };
        Ok(EpilogueInputs {
            blended: get(0, "blended")?,
            x0: get(1, "x0")?,
            q0: get(2, "q0")?,
            log_s0: get(3, "log_s0")?,
        })
    }

    fn epilogue(&self) -> PyResult<LinearEpilogue<'_, T>> {
        Ok(LinearEpilogue {
            blended: flat(&self.blended, "blended")?,
            x0: flat(&self.x0, "x0")?,
            q0: flat(&self.q0, "q0")?,
            log_s0: flat(&self.log_s0, "log_s0")?,
        })
    }
}

fn epilogue_forward_typed<'py, T: Real + Element>(
    py: Python<'py>,
    a: [&AnyArr<'py>; 4],
    threads: usize,
) -> PyResult<PyObject> {
    let inputs = EpilogueInputs::<T>::extract(a)?;
    let e = inputs.epilogue()?;
    let n = e.x0.len() / 3;
    let (means, quats, scales): (Out<'py, T>, Out<'py, T>, Out<'py, T>) =
        (zeros(py, n * 3), zeros(py, n * 4), zeros(py, n * 3));
    let out = LinearEpilogueOut {
        means: slice_mut(&means),
        quats: slice_mut(&quats),
        scales: slice_mut(&scales),
    };
    run(py, threads, || {
        motion::linear_epilogue_forward(&e, out).map_err(to_raster)
    })?;
    to_object(py, (means, quats, scales))
}

fn epilogue_backward_typed<'py, T: Real + Element>(
    py: Python<'py>,
    a: [&AnyArr<'py>; 4],
    g: [&AnyArr<'py>; 3],
    threads: usize,
) -> PyResult<PyObject> {
    let inputs = EpilogueInputs::<T>::extract(a)?;
    let e = inputs.epilogue()?;
    let grad = |i: usize, name: &str| {
        g[i].extract::<Arr<'py, T>>().map_err(|_| {
            PyValueError::new_err(format!("{name}: expected an array of blended's dtype"))
        })
    };
    let (gm, gq, gs) = (
        grad(0, "grad_means")?,
        grad(1, "grad_quats")?,
        grad(2, "grad_scales")?,
    );
    let (gm, gq, gs) = (
        flat(&gm, "grad_means")?,
        flat(&gq, "grad_quats")?,
        flat(&gs, "grad_scales")?,
    );
    let n = e.x0.len() / 3;
    let gb: Out<'py, T> = zeros(py, e.blended.len());
    let (gx, gq0, gl): (Out<'py, T>, Out<'py, T>, Out<'py, T>) =
        (zeros(py, n * 3), zeros(py, n * 4), zeros(py, n * 3));
    let grads = LinearEpilogueGradsMut {
        blended: slice_mut(&gb),
        x0: slice_mut(&gx),
        q0: slice_mut(&gq0),
        log_s0: slice_mut(&gl),
    };
    run(py, threads, || {
        motion::linear_epilogue_backward(&e, gm, gq, gs, grads).map_err(to_raster)
    })?;
    to_object(py, (gb, gx, gq0, gl))
}

/// The linear blend's epilogue: flat blended [N*19], x0 [N*3], q0 [N*4], log_s0 [N*3]
/// (float32 or float64, one type). Returns (means [N*3], unit quaternions [N*4], scales [N*3]).
#[pyfunction]
#[pyo3(signature = (blended, x0, q0, log_s0, *, threads))]
pub(crate) fn linear_epilogue_forward<'py>(
    py: Python<'py>,
    blended: AnyArr<'py>,
    x0: AnyArr<'py>,
    q0: AnyArr<'py>,
    log_s0: AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject> {
    let a = [&blended, &x0, &q0, &log_s0];
    with_float_type!(blended, "blended", |T| epilogue_forward_typed::<T>(
        py, a, threads
    ))
}

/// Backward of `linear_epilogue_forward` given dL/d(means [N*3], quats [N*4], scales [N*3]):
/// returns (dL/dblended [N*19], dL/dx0 [N*3], dL/dq0 [N*4], dL/dlog_s0 [N*3]).
#[pyfunction]
#[pyo3(signature = (
    blended, x0, q0, log_s0, *, grad_means, grad_quats, grad_scales, threads
))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn linear_epilogue_backward<'py>(
    py: Python<'py>,
    blended: AnyArr<'py>,
    x0: AnyArr<'py>,
    q0: AnyArr<'py>,
    log_s0: AnyArr<'py>,
    grad_means: AnyArr<'py>,
    grad_quats: AnyArr<'py>,
    grad_scales: AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject> {
    let a = [&blended, &x0, &q0, &log_s0];
    let g = [&grad_means, &grad_quats, &grad_scales];
    with_float_type!(blended, "blended", |T| epilogue_backward_typed::<T>(
        py, a, g, threads
    ))
}
