//! Projection bindings: `project_forward` and `project_backward` (float32 fast path, float64 for
//! gradient checks), with the camera built from the Python arguments.

use numpy::Element;
use pyo3::prelude::*;
use sync4d_raster as core;
use sync4d_scalar::Real;

use crate::arrays::{
    bindings, flat, slice_mut, to_object, with_float_type, zeros, AnyArr, Arr, Out,
};
use crate::runtime::{run, to_py};
use crate::settings::ProjectSettings;

/// The Gaussians of a projection call, as element type `T`.
struct GaussianArrs<'py, T: Element> {
    means: Arr<'py, T>,
    quats: Arr<'py, T>,
    scales: Arr<'py, T>,
    opacities: Arr<'py, T>,
}

impl<'py, T: Real + Element> GaussianArrs<'py, T> {
    fn extract(
        means: &AnyArr<'py>,
        quats: &AnyArr<'py>,
        scales: &AnyArr<'py>,
        opacities: &AnyArr<'py>,
    ) -> PyResult<Self> {
        Ok(GaussianArrs {
            means: means.extract()?,
            quats: quats.extract()?,
            scales: scales.extract()?,
            opacities: opacities.extract()?,
        })
    }

    fn gaussians(&self) -> PyResult<core::Gaussians<'_, T>> {
        Ok(core::Gaussians {
            means: flat(&self.means, "means")?,
            quats: flat(&self.quats, "quats")?,
            scales: flat(&self.scales, "scales")?,
            opacities: flat(&self.opacities, "opacities")?,
        })
    }
}

/// The gradients of a projection's outputs, as element type `T`.
struct ProjectionGradArrs<'py, T: Element> {
    means2d: Arr<'py, T>,
    conics: Arr<'py, T>,
    depths: Arr<'py, T>,
    opacities: Arr<'py, T>,
}

impl<T: Real + Element> ProjectionGradArrs<'_, T> {
    fn grads(&self) -> PyResult<core::ProjectionGrads<'_, T>> {
        Ok(core::ProjectionGrads {
            means2d: flat(&self.means2d, "grad_means2d")?,
            conics: flat(&self.conics, "grad_conics")?,
            depths: flat(&self.depths, "grad_depths")?,
            opacities: flat(&self.opacities, "grad_opacities")?,
        })
    }
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

fn project_fwd<'py, T: Real + Element>(
    py: Python<'py>,
    arrs: &GaussianArrs<'py, T>,
    cam: &core::Camera,
    settings: &ProjectSettings,
    threads: usize,
) -> PyResult<ProjOut<'py, T>> {
    let ps = settings.core();
    let g = arrs.gaussians()?;
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
    let visible = run(py, threads, || core::project_forward(&g, cam, &ps, out))?;
    Ok((m2, co, de, op, ra, visible))
}

fn project_bwd<'py, T: Real + Element>(
    py: Python<'py>,
    arrs: &GaussianArrs<'py, T>,
    cam: &core::Camera,
    settings: &ProjectSettings,
    grads: &ProjectionGradArrs<'py, T>,
    threads: usize,
) -> PyResult<Grads4<'py, T>> {
    let ps = settings.core();
    let g = arrs.gaussians()?;
    let v = grads.grads()?;
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
        core::project_backward(&g, cam, &ps, &v, out)
    })?;
    Ok((gm, gq, gs, go))
}

bindings! {
    (
        py,
        [
            means: AnyArr<'py>,
            quats: AnyArr<'py>,
            scales: AnyArr<'py>,
            opacities: AnyArr<'py>
        ],
        [
            viewmat: Vec<f64>, fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32,
            settings: ProjectSettings
        ],
        threads
    )

    /// Project Gaussians (float32: fast path; float64: for gradient checks) through the pinhole
    /// camera `viewmat` (row-major world-to-camera 4x4), `fx`, `fy`, `cx`, `cy`, `width` x
    /// `height` with `settings` (a `ProjectSettings`). Returns (means2d, conics, depths,
    /// opacities, radii, visible) as flat arrays.
    fn project_forward() {
        with_float_type!(means, "means", |T| {
            let arrs = GaussianArrs::<T>::extract(&means, &quats, &scales, &opacities)?;
            // Built after the arrays are extracted, as before: the same error wins when several
            // arguments are wrong.
            let cam = core::Camera::new(&viewmat, fx, fy, cx, cy, width, height).map_err(to_py)?;
            to_object(py, project_fwd::<T>(py, &arrs, &cam, &settings, threads)?)
        })
    }

    /// Backward of the projection (the forward's arguments by the same names, plus the outputs'
    /// gradients `grad_means2d`, `grad_conics`, `grad_depths`, `grad_opacities`): returns
    /// dL/d(means, quats, scales, opacities).
    fn project_backward(
        grad_means2d: AnyArr<'py>,
        grad_conics: AnyArr<'py>,
        grad_depths: AnyArr<'py>,
        grad_opacities: AnyArr<'py>
    ) {
        with_float_type!(means, "means", |T| {
            let grads = ProjectionGradArrs::<T> {
                means2d: grad_means2d.extract()?,
                conics: grad_conics.extract()?,
                depths: grad_depths.extract()?,
                opacities: grad_opacities.extract()?,
            };
            let arrs = GaussianArrs::<T>::extract(&means, &quats, &scales, &opacities)?;
            let cam = core::Camera::new(&viewmat, fx, fy, cx, cy, width, height).map_err(to_py)?;
            to_object(py, project_bwd::<T>(py, &arrs, &cam, &settings, &grads, threads)?)
        })
    }
}
