//! The wgpu backend's bindings: the process-wide GPU rasterizer opened on first use, the
//! adapter queries, and `WgpuContext` (float32 only), with its own error mapping (GPU errors as
//! `RuntimeError`s naming the backend). Apart from the CPU bindings, which never open a device.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Mutex, OnceLock};

use crate::arrays::{
    alloc_image, alloc_splat_grads, counters_dict, extract_image_grads, extract_splats, flat,
    image_grads, image_mut, splat_grads_mut, splats_of, to_object, AnyArr, Arr, ImageGradAny,
    SplatAny,
};
use crate::runtime::{lock_recover, to_py};
use crate::settings::CompositeSettings;

/// The process-wide wgpu rasterizer (kernels compiled once), opened on first use on the adapter
/// `AdapterChoice::Auto` picks (a discrete, then integrated GPU, then a CPU driver such as
/// lavapipe); the error text when none opens.
fn wgpu_rasterizer() -> PyResult<&'static Mutex<sync4d_gpu::GpuRasterizer>> {
    static GPU: OnceLock<Result<Mutex<sync4d_gpu::GpuRasterizer>, String>> = OnceLock::new();
    GPU.get_or_init(|| {
        sync4d_gpu::GpuDevice::new(sync4d_gpu::AdapterChoice::Auto)
            .map(|d| Mutex::new(sync4d_gpu::GpuRasterizer::new(d)))
            .map_err(|e| e.to_string())
    })
    .as_ref()
    .map_err(|e| PyRuntimeError::new_err(format!("backend 'wgpu': {e}")))
}

/// Run `f` on the shared wgpu rasterizer without the GIL, mapping errors and panics.
fn run_wgpu<T: Send>(
    py: Python<'_>,
    f: impl FnOnce(&mut sync4d_gpu::GpuRasterizer) -> sync4d_gpu::Result<T> + Send,
) -> PyResult<T> {
    let gpu = wgpu_rasterizer()?;
    let out = py.allow_threads(move || {
        catch_unwind(AssertUnwindSafe(move || {
            let mut r = lock_recover(gpu);
            f(&mut r)
        }))
    });
    match out {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(sync4d_gpu::GpuError::Raster(e))) => Err(to_py(e)),
        Ok(Err(e)) => Err(PyRuntimeError::new_err(format!("backend 'wgpu': {e}"))),
        Err(_) => Err(PyRuntimeError::new_err(
            "sync4d wgpu rasterizer internal error (please report with the inputs that caused it)",
        )),
    }
}

/// The adapter the wgpu backend runs on, opening it if needed ("name (kind, API, driver)");
/// RuntimeError naming what was found and what to install when none opens.
#[pyfunction]
pub(crate) fn wgpu_adapter() -> PyResult<String> {
    let gpu = wgpu_rasterizer()?;
    let r = lock_recover(gpu);
    Ok(r.device().adapter.to_string())
}

/// Adapters wgpu can see, best first, as (name, kind) with kind one of "discrete",
/// "integrated", "virtual", "cpu", "other". Opens no device.
#[pyfunction]
pub(crate) fn wgpu_adapters(py: Python<'_>) -> Vec<(String, &'static str)> {
    py.allow_threads(|| {
        sync4d_gpu::list_adapters()
            .into_iter()
            .map(|a| (a.name, a.kind))
            .collect()
    })
}

/// The float32 compositor on the wgpu backend, with the device buffers its backward needs:
/// one per in-flight render, like `RasterContext` (same method signatures; `threads` unused).
#[pyclass(module = "sync4d._core")]
pub(crate) struct WgpuContext {
    state: Mutex<sync4d_gpu::GpuRasterState>,
}

#[pymethods]
impl WgpuContext {
    #[new]
    fn new() -> Self {
        WgpuContext {
            state: Mutex::new(sync4d_gpu::GpuRasterState::new()),
        }
    }

    /// Composite float32 splats (see `RasterContext.forward`: the same keyword arguments).
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
        let _ = threads;
        let splats = SplatAny {
            means2d,
            conics,
            depths,
            opacities,
            radii,
            features,
        };
        let arrs = extract_splats::<f32>(&splats).map_err(|_| float32_only())?;
        let sp = splats_of(&arrs, channels)?;
        let bg: Arr<'py, f32> = background.extract().map_err(|_| float32_only())?;
        let bg = flat(&bg, "background")?;
        let img = alloc_image::<f32>(py, settings.pixels(), channels);
        let out = image_mut(&img);
        let (width, height, bs) = (settings.width, settings.height, settings.blend());
        let state = &self.state;
        let counters = run_wgpu(py, |r| {
            let mut st = lock_recover(state);
            r.rasterize_forward(&sp, width, height, bg, &bs, &mut st, out)
        })?;
        to_object(py, (img.0, img.1, img.2, counters_dict(py, counters)?))
    }

    /// Backward of `forward` (see `RasterContext.backward`: the same keyword arguments).
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
        let _ = threads;
        let splats = SplatAny {
            means2d,
            conics,
            depths,
            opacities,
            radii,
            features,
        };
        let arrs = extract_splats::<f32>(&splats).map_err(|_| float32_only())?;
        let sp = splats_of(&arrs, channels)?;
        let bg: Arr<'py, f32> = background.extract().map_err(|_| float32_only())?;
        let bg = flat(&bg, "background")?;
        let grads = ImageGradAny {
            features: grad_features,
            alpha: grad_alpha,
            depth: grad_depth,
        };
        let g = extract_image_grads::<f32>(&grads).map_err(|_| float32_only())?;
        let v = image_grads(&g)?;
        let out = alloc_splat_grads::<f32>(py, sp.len(), channels);
        let gm = splat_grads_mut(&out);
        let (width, height, bs) = (settings.width, settings.height, settings.blend());
        let state = &self.state;
        run_wgpu(py, |r| {
            let mut st = lock_recover(state);
            r.rasterize_backward(&sp, width, height, bg, &bs, &mut st, &v, gm)
        })?;
        to_object(py, out)
    }
}

fn float32_only() -> PyErr {
    PyValueError::new_err(
        "backend 'wgpu' composites float32 only; use backend='cpu' for float64 (gradient checks)",
    )
}
