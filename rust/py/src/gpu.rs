//! The wgpu backend's bindings: the process-wide GPU rasterizer opened on first use, the
//! adapter queries, and `WgpuContext` (float32 only), with its own error mapping (GPU errors as
//! `RuntimeError`s naming the backend). Apart from the CPU bindings, which never open a device.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Mutex, OnceLock};

use crate::arrays::{extract_image_grads, extract_splats, Arr};
use crate::composite::{
    backward_with, compositor_context, forward_with, BackwardArgs, CompositeArgs,
};
use crate::runtime::{lock_recover, to_py};

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

compositor_context!(
    /// The float32 compositor on the wgpu backend, with the device buffers its backward needs:
    /// one per in-flight render, like `RasterContext` (same method signatures; `threads` unused).
    WgpuContext(sync4d_gpu::GpuRasterState),
    forward:
    /// Composite float32 splats (see `RasterContext.forward`: the same keyword arguments).
    ,
    backward:
    /// Backward of `forward` (see `RasterContext.backward`: the same keyword arguments).
    ,
);

impl WgpuContext {
    /// `forward` on float32 arrays.
    fn forward_any(&self, py: Python<'_>, args: &CompositeArgs<'_>) -> PyResult<PyObject> {
        let state = &self.state;
        let arrs = extract_splats::<f32>(&args.splats).map_err(|_| float32_only())?;
        let bg: Arr<'_, f32> = args.background.extract().map_err(|_| float32_only())?;
        forward_with(py, (&arrs, &bg), args, |(sp, (w, h), bg, bs), out| {
            run_wgpu(py, |r| {
                r.rasterize_forward(&sp, w, h, bg, &bs, &mut lock_recover(state), out)
            })
        })
    }

    /// `backward` on float32 arrays.
    fn backward_any(&self, py: Python<'_>, args: &BackwardArgs<'_>) -> PyResult<PyObject> {
        let (call, state) = (&args.call, &self.state);
        let arrs = extract_splats::<f32>(&call.splats).map_err(|_| float32_only())?;
        let bg: Arr<'_, f32> = call.background.extract().map_err(|_| float32_only())?;
        let g = extract_image_grads::<f32>(&args.grads).map_err(|_| float32_only())?;
        backward_with(
            py,
            (&arrs, &bg, &g),
            call,
            |(sp, (w, h), bg, bs), v, out| {
                run_wgpu(py, |r| {
                    r.rasterize_backward(&sp, w, h, bg, &bs, &mut lock_recover(state), v, out)
                })
            },
        )
    }
}

fn float32_only() -> PyErr {
    PyValueError::new_err(
        "backend 'wgpu' composites float32 only; use backend='cpu' for float64 (gradient checks)",
    )
}
