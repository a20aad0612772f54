//! Projection bindings: `project_forward` and `project_backward` (float32 fast path, float64 for
//! gradient checks), with the camera built from the Python arguments.

use numpy::Element;
use pyo3::prelude::*;
use sync4d_raster as core;
use sync4d_raster::real::Real;

use crate::arrays::{flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out};
use crate::runtime::{run, to_py};

fn camera(
    viewmat: Vec<f64>,
    intr: (f64, f64, f64, f64),
    width: u32,
    height: u32,
) -> PyResult<core::Camera> {
    core::Camera::new(&viewmat, intr.0, intr.1, intr.2, intr.3, width, height).map_err(to_py)
}

/// (means2d, conics, depths, opacities, radii, visible count).
type ProjOut<'py, T> = (
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, i32>,
    usize,
);
/// Four gradient arrays.
type Grads4<'py, T> = (Out<'py, T>, Out<'py, T>, Out<'py, T>, Out<'py, T>);

#[allow(clippy::too_many_arguments)]
fn project_fwd<'py, T: Real + Element>(
    py: Python<'py>,
    means: Arr<'py, T>,
    quats: Arr<'py, T>,
    scales: Arr<'py, T>,
    opacities: Arr<'py, T>,
    viewmat: Vec<f64>,
    intrinsics: (f64, f64, f64, f64),
    width: u32,
    height: u32,
    settings: (f64, f64, f64, bool),
    threads: usize,
) -> PyResult<ProjOut<'py, T>> {
    let cam = camera(viewmat, intrinsics, width, height)?;
    let ps = core::ProjectSettings {
        near: settings.0,
        far: settings.1,
        eps2d: settings.2,
        antialiased: settings.3,
    };
    let g = core::Gaussians {
        means: flat(&means, "means")?,
        quats: flat(&quats, "quats")?,
        scales: flat(&scales, "scales")?,
        opacities: flat(&opacities, "opacities")?,
    };
    let n = g.len();
    let (m2, co, de, op, ra) = (
        zeros::<T>(py, 2 * n),
        zeros::<T>(py, 3 * n),
        zeros::<T>(py, n),
        zeros::<T>(py, n),
        zeros::<i32>(py, 2 * n),
    );
    let out = core::ProjectionMut {
        means2d: slice_mut(&m2),
        conics: slice_mut(&co),
        depths: slice_mut(&de),
        opacities: slice_mut(&op),
        radii: slice_mut(&ra),
    };
    let visible = run(py, threads, || core::project_forward(&g, &cam, &ps, out))?;
    Ok((m2, co, de, op, ra, visible))
}

#[allow(clippy::too_many_arguments)]
fn project_bwd<'py, T: Real + Element>(
    py: Python<'py>,
    means: Arr<'py, T>,
    quats: Arr<'py, T>,
    scales: Arr<'py, T>,
    opacities: Arr<'py, T>,
    viewmat: Vec<f64>,
    intrinsics: (f64, f64, f64, f64),
    width: u32,
    height: u32,
    settings: (f64, f64, f64, bool),
    grads: (Arr<'py, T>, Arr<'py, T>, Arr<'py, T>, Arr<'py, T>),
    threads: usize,
) -> PyResult<Grads4<'py, T>> {
    let cam = camera(viewmat, intrinsics, width, height)?;
    let ps = core::ProjectSettings {
        near: settings.0,
        far: settings.1,
        eps2d: settings.2,
        antialiased: settings.3,
    };
    let g = core::Gaussians {
        means: flat(&means, "means")?,
        quats: flat(&quats, "quats")?,
        scales: flat(&scales, "scales")?,
        opacities: flat(&opacities, "opacities")?,
    };
    let v = core::ProjectionGrads {
        means2d: flat(&grads.0, "grad_means2d")?,
        conics: flat(&grads.1, "grad_conics")?,
        depths: flat(&grads.2, "grad_depths")?,
        opacities: flat(&grads.3, "grad_opacities")?,
    };
    let n = g.len();
    let (gm, gq, gs, go) = (
        zeros::<T>(py, 3 * n),
        zeros::<T>(py, 4 * n),
        zeros::<T>(py, 3 * n),
        zeros::<T>(py, n),
    );
    let out = core::GaussianGradsMut {
        means: slice_mut(&gm),
        quats: slice_mut(&gq),
        scales: slice_mut(&gs),
        opacities: slice_mut(&go),
    };
    run(py, threads, || {
        core::project_backward(&g, &cam, &ps, &v, out)
    })?;
    Ok((gm, gq, gs, go))
}

/// Project Gaussians (float32: fast path; float64: for gradient checks). Returns (means2d,
/// conics, depths, opacities, radii, visible) as flat arrays.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub(crate) fn project_forward<'py>(
    py: Python<'py>,
    means: AnyArr<'py>,
    quats: AnyArr<'py>,
    scales: AnyArr<'py>,
    opacities: AnyArr<'py>,
    viewmat: Vec<f64>,
    intrinsics: (f64, f64, f64, f64),
    width: u32,
    height: u32,
    settings: (f64, f64, f64, bool),
    threads: usize,
) -> PyResult<PyObject> {
    with_float_type!(means, "means", |T| {
        let out = project_fwd::<T>(
            py,
            means.extract()?,
            quats.extract()?,
            scales.extract()?,
            opacities.extract()?,
            viewmat,
            intrinsics,
            width,
            height,
            settings,
            threads,
        )?;
        to_object(py, out)
    })
}

/// Backward of the projection: returns dL/d(means, quats, scales, opacities).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
pub(crate) fn project_backward<'py>(
    py: Python<'py>,
    means: AnyArr<'py>,
    quats: AnyArr<'py>,
    scales: AnyArr<'py>,
    opacities: AnyArr<'py>,
    viewmat: Vec<f64>,
    intrinsics: (f64, f64, f64, f64),
    width: u32,
    height: u32,
    settings: (f64, f64, f64, bool),
    grads: (AnyArr<'py>, AnyArr<'py>, AnyArr<'py>, AnyArr<'py>),
    threads: usize,
) -> PyResult<PyObject> {
    with_float_type!(means, "means", |T| {
        let g = (
            grads.0.extract()?,
            grads.1.extract()?,
            grads.2.extract()?,
            grads.3.extract()?,
        );
        let out = project_bwd::<T>(
            py,
            means.extract()?,
            quats.extract()?,
            scales.extract()?,
            opacities.extract()?,
            viewmat,
            intrinsics,
            width,
            height,
            settings,
            g,
            threads,
        )?;
        to_object(py, out)
    })
}
