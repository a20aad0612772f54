//! Spherical-harmonics bindings: `sh_forward` and `sh_backward` (float32 or float64).

use numpy::Element;
use pyo3::prelude::*;
use sync4d_raster as core;
use sync4d_raster::real::Real;

use crate::arrays::{flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out};
use crate::runtime::run;

fn sh_fwd<'py, T: Real + Element>(
    py: Python<'py>,
    degree: u32,
    dirs: Arr<'py, T>,
    coeffs: Arr<'py, T>,
    bases: usize,
    channels: usize,
    threads: usize,
) -> PyResult<Out<'py, T>> {
    let d = flat(&dirs, "dirs")?;
    let c = flat(&coeffs, "coeffs")?;
    let out = zeros::<T>(py, (d.len() / 3) * channels);
    let o = slice_mut(&out);
    run(py, threads, || {
        core::sh_forward(degree, d, c, bases, channels, o)
    })?;
    Ok(out)
}

#[allow(clippy::too_many_arguments)]
fn sh_bwd<'py, T: Real + Element>(
    py: Python<'py>,
    degree: u32,
    dirs: Arr<'py, T>,
    coeffs: Arr<'py, T>,
    bases: usize,
    channels: usize,
    grad_out: Arr<'py, T>,
    threads: usize,
) -> PyResult<(Out<'py, T>, Out<'py, T>)> {
    let d = flat(&dirs, "dirs")?;
    let c = flat(&coeffs, "coeffs")?;
    let v = flat(&grad_out, "grad_out")?;
    let (vd, vc) = (zeros::<T>(py, d.len()), zeros::<T>(py, c.len()));
    let (vds, vcs) = (slice_mut(&vd), slice_mut(&vc));
    run(py, threads, || {
        core::sh_backward(degree, d, c, bases, channels, v, vds, vcs)
    })?;
    Ok((vd, vc))
}

/// Spherical-harmonics colours: dirs N*3, coeffs N*K*C (float32 or float64) → N*C.
#[pyfunction]
#[pyo3(signature = (degree, dirs, coeffs, *, bases, channels, threads))]
pub(crate) fn sh_forward<'py>(
    py: Python<'py>,
    degree: u32,
    dirs: AnyArr<'py>,
    coeffs: AnyArr<'py>,
    bases: usize,
    channels: usize,
    threads: usize,
) -> PyResult<PyObject> {
    with_float_type!(dirs, "dirs", |T| {
        let out = sh_fwd::<T>(
            py,
            degree,
            dirs.extract()?,
            coeffs.extract()?,
            bases,
            channels,
            threads,
        )?;
        to_object(py, out)
    })
}

/// Backward of the SH evaluation: returns (dL/d dirs, dL/d coeffs).
#[pyfunction]
#[pyo3(signature = (degree, dirs, coeffs, *, bases, channels, grad_out, threads))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn sh_backward<'py>(
    py: Python<'py>,
    degree: u32,
    dirs: AnyArr<'py>,
    coeffs: AnyArr<'py>,
    bases: usize,
    channels: usize,
    grad_out: AnyArr<'py>,
    threads: usize,
) -> PyResult<PyObject> {
    with_float_type!(dirs, "dirs", |T| {
        let out = sh_bwd::<T>(
            py,
            degree,
            dirs.extract()?,
            coeffs.extract()?,
            bases,
            channels,
            grad_out.extract()?,
            threads,
        )?;
        to_object(py, out)
    })
}
