//! Spherical-harmonics bindings: `sh_forward` and `sh_backward` (float32 or float64).

use numpy::Element;
use pyo3::prelude::*;
use sync4d_raster as core;
use sync4d_scalar::Real;

use crate::arrays::{
    bindings, flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out,
};
use crate::runtime::run;

fn sh_fwd<'py, T: Real + Element>(
    py: Python<'py>,
    degree: u32,
    dirs: Arr<'py, T>,
    coeffs: Arr<'py, T>,
    (bases, channels): (usize, usize),
    threads: usize,
) -> PyResult<Out<'py, T>> {
    let (d, c) = (flat(&dirs, "dirs")?, flat(&coeffs, "coeffs")?);
    let out = zeros::<T>(py, (d.len() / 3) * channels);
    let o = slice_mut(&out);
    run(py, threads, || {
        core::sh_forward(degree, d, c, bases, channels, o)
    })?;
    Ok(out)
}

/// (dirs, coeffs, grad_out) as `T`.
type ShGradArrs<'py, T> = (Arr<'py, T>, Arr<'py, T>, Arr<'py, T>);

fn sh_bwd<'py, T: Real + Element>(
    py: Python<'py>,
    degree: u32,
    (dirs, coeffs, grad_out): ShGradArrs<'py, T>,
    (bases, channels): (usize, usize),
    threads: usize,
) -> PyResult<(Out<'py, T>, Out<'py, T>)> {
    let (d, c) = (flat(&dirs, "dirs")?, flat(&coeffs, "coeffs")?);
    let v = flat(&grad_out, "grad_out")?;
    let (vd, vc) = (zeros::<T>(py, d.len()), zeros::<T>(py, c.len()));
    let (vds, vcs) = (slice_mut(&vd), slice_mut(&vc));
    run(py, threads, || {
        core::sh_backward(degree, d, c, bases, channels, v, vds, vcs)
    })?;
    Ok((vd, vc))
}

bindings! {
    (
        py,
        [degree: u32, dirs: AnyArr<'py>, coeffs: AnyArr<'py>],
        [bases: usize, channels: usize],
        threads
    )

    /// Spherical-harmonics colours: dirs N*3, coeffs N*K*C (float32 or float64) → N*C.
    fn sh_forward() {
        with_float_type!(dirs, "dirs", |T| {
            let sizes = (bases, channels);
            let out = sh_fwd::<T>(py, degree, dirs.extract()?, coeffs.extract()?, sizes, threads)?;
            to_object(py, out)
        })
    }

    /// Backward of the SH evaluation: returns (dL/d dirs, dL/d coeffs).
    fn sh_backward(grad_out: AnyArr<'py>) {
        with_float_type!(dirs, "dirs", |T| {
            let arrays = (dirs.extract()?, coeffs.extract()?, grad_out.extract()?);
            let out = sh_bwd::<T>(py, degree, arrays, (bases, channels), threads)?;
            to_object(py, out)
        })
    }
}
