//! The training loss binding: `photometric_loss` (L1 and D-SSIM, with its gradient on request).

use numpy::Element;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use sync4d_loss::{photometric_loss as loss, LossWeights};
use sync4d_scalar::Real;

use crate::arrays::{flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr};
use crate::runtime::run;

fn loss_typed<'py, T: Real + Element>(
    py: Python<'py>,
    pred: Arr<'py, T>,
    target: Arr<'py, T>,
    shape: (usize, usize, usize),
    weights: LossWeights,
    want_grad: bool,
    threads: usize,
) -> PyResult<PyObject> {
    let (x, y) = (flat(&pred, "pred")?, flat(&target, "target")?);
    let grad = want_grad.then(|| zeros::<T>(py, x.len()));
    let g = grad.as_ref().map(|a| slice_mut(a));
    let (h, w, c) = shape;
    let t = run(py, threads, || loss(x, y, h, w, c, &weights, g))?;
    to_object(py, (t.loss, t.mean_abs, t.ssim, grad))
}

/// Training loss l1 * mean|pred - target| + dssim * (1 - SSIM) / 2 of [height, width, channels]
/// images (flat float32 or float64 arrays of one type), SSIM over `window` x `window` reflect-
/// padded box means. Every argument after the images by name. Returns (loss, mean_abs, ssim,
/// dL/d pred or None).
#[pyfunction]
#[pyo3(signature = (
    pred, target, *, height, width, channels, l1, dssim, window, want_grad, threads
))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn photometric_loss<'py>(
    py: Python<'py>,
    pred: AnyArr<'py>,
    target: AnyArr<'py>,
    height: usize,
    width: usize,
    channels: usize,
    l1: f64,
    dssim: f64,
    window: usize,
    want_grad: bool,
    threads: usize,
) -> PyResult<PyObject> {
    let weights = LossWeights { l1, dssim, window };
    with_float_type!(pred, "pred", |T| {
        let target = target.extract().map_err(|_| {
            PyValueError::new_err("target: expected an array of the same dtype as pred")
        })?;
        loss_typed::<T>(
            py,
            pred.extract()?,
            target,
            (height, width, channels),
            weights,
            want_grad,
            threads,
        )
    })
}
