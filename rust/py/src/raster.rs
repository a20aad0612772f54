//! CPU rasterization bindings: `RasterContext`, the compositor (float32 fast path, float64
//! reference) with the reusable buffers its backward needs.

use numpy::Element;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::sync::Mutex;
use sync4d_raster as core;

use crate::arrays::{
    alloc_image, alloc_splat_grads, counters_dict, extract_image_grads, extract_splats, flat,
    image_grads, image_mut, splat_grads_mut, splats_of, to_object, with_float_type, AnyArr, Arr,
    ImageGradAny, ImageGradArrs, Out, SplatAny, SplatArrs, SplatGradOut,
};
use crate::runtime::{lock_recover, run};
use crate::settings::CompositeSettings;

/// (features, alpha, depth_accum, counters).
type ImageResult<'py, T> = (Out<'py, T>, Out<'py, T>, Out<'py, T>, Bound<'py, PyDict>);

/// The fast (float32) compositor with its reusable buffers: one per in-flight render. Keep it
/// from forward to backward; reuse it across iterations so large buffers are touched once.
#[pyclass(module = "sync4d._core")]
pub(crate) struct RasterContext {
    state: Mutex<core::RasterState>,
}

#[pymethods]
impl RasterContext {
    #[new]
    fn new() -> Self {
        RasterContext {
            state: Mutex::new(core::RasterState::new()),
        }
    }

    /// Composite splats given by name: `means2d`, `conics`, `depths`, `opacities`, `radii`
    /// (int32), `features` (`channels` per splat) and `background`, flat arrays, float32 (fast
    /// path) or float64 (reference), with `settings` (a `CompositeSettings`). Returns
    /// (features H*W*C, alpha H*W, depth_accum H*W, counters).
    #[pyo3(signature = (
        *, means2d, conics, depths, opacities, radii, features, channels, background, settings,
        threads
    ))]
    #[allow(clippy::too_many_arguments)]
    fn forward<'py>(
        &self,
        py: Python<'py>,
        means2d: AnyArr<'py>,
        conics: AnyArr<'py>,
        depths: AnyArr<'py>,
        opacities: AnyArr<'py>,
        radii: AnyArr<'py>,
        features: AnyArr<'py>,
        channels: usize,
        background: AnyArr<'py>,
        settings: CompositeSettings,
        threads: usize,
    ) -> PyResult<PyObject> {
        let splats = SplatAny {
            means2d,
            conics,
            depths,
            opacities,
            radii,
            features,
        };
        with_float_type!(splats.means2d, "means2d", |T| {
            let arrs = extract_splats::<T>(&splats)?;
            let bg = background.extract()?;
            let out = self.forward_typed::<T>(py, &arrs, channels, bg, &settings, threads)?;
            to_object(py, out)
        })
    }

    /// Backward of `forward`: the forward's arguments by the same names plus the incoming
    /// gradients `grad_features`, `grad_alpha`, `grad_depth`; returns dL/d(means2d, conics,
    /// depths, opacities, features). Inputs must be the forward's.
    #[pyo3(signature = (
        *, means2d, conics, depths, opacities, radii, features, channels, background, settings,
        grad_features, grad_alpha, grad_depth, threads
    ))]
    #[allow(clippy::too_many_arguments)]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        means2d: AnyArr<'py>,
        conics: AnyArr<'py>,
        depths: AnyArr<'py>,
        opacities: AnyArr<'py>,
        radii: AnyArr<'py>,
        features: AnyArr<'py>,
        channels: usize,
        background: AnyArr<'py>,
        settings: CompositeSettings,
        grad_features: AnyArr<'py>,
        grad_alpha: AnyArr<'py>,
        grad_depth: AnyArr<'py>,
        threads: usize,
    ) -> PyResult<PyObject> {
        let splats = SplatAny {
            means2d,
            conics,
            depths,
            opacities,
            radii,
            features,
        };
        let grads = ImageGradAny {
            features: grad_features,
            alpha: grad_alpha,
            depth: grad_depth,
        };
        with_float_type!(splats.means2d, "means2d", |T| {
            let arrs = extract_splats::<T>(&splats)?;
            let g = extract_image_grads::<T>(&grads)?;
            let bg = background.extract()?;
            let out = self.backward_typed::<T>(py, &arrs, channels, bg, &settings, &g, threads)?;
            to_object(py, out)
        })
    }

    /// Bytes held by this context's reusable buffers.
    fn nbytes(&self) -> usize {
        self.state.lock().map_or(0, |s| s.bytes())
    }
}

impl RasterContext {
    fn forward_typed<'py, T: core::Composite + Element>(
        &self,
        py: Python<'py>,
        splats: &SplatArrs<'py, T>,
        channels: usize,
        background: Arr<'py, T>,
        settings: &CompositeSettings,
        threads: usize,
    ) -> PyResult<ImageResult<'py, T>> {
        let sp = splats_of(splats, channels)?;
        let bg = flat(&background, "background")?;
        let img = alloc_image::<T>(py, settings.pixels(), channels);
        let out = image_mut(&img);
        let (width, height, bs) = (settings.width, settings.height, settings.blend());
        let state = &self.state;
        let counters = run(py, threads, || {
            let mut st = lock_recover(state);
            T::composite_forward(&sp, width, height, bg, &bs, &mut st, out)
        })?;
        Ok((img.0, img.1, img.2, counters_dict(py, counters)?))
    }

    #[allow(clippy::too_many_arguments)]
    fn backward_typed<'py, T: core::Composite + Element>(
        &self,
        py: Python<'py>,
        splats: &SplatArrs<'py, T>,
        channels: usize,
        background: Arr<'py, T>,
        settings: &CompositeSettings,
        grads: &ImageGradArrs<'py, T>,
        threads: usize,
    ) -> PyResult<SplatGradOut<'py, T>> {
        let sp = splats_of(splats, channels)?;
        let bg = flat(&background, "background")?;
        let v = image_grads(grads)?;
        let out = alloc_splat_grads::<T>(py, sp.len(), channels);
        let g = splat_grads_mut(&out);
        let (width, height, bs) = (settings.width, settings.height, settings.blend());
        let state = &self.state;
        run(py, threads, || {
            let mut st = lock_recover(state);
            T::composite_backward(&sp, width, height, bg, &bs, &mut st, &v, g)
        })?;
        Ok(out)
    }
}
