//! Thin pyo3 bindings: `sync4d._core`. Arrays come in as NumPy views of torch tensors (no copies;
//! flat C-contiguous), the GIL is released while Rust works, `RasterError`s become `ValueError`s
//! naming the argument, and a Rust panic becomes a `RuntimeError` instead of crossing into Python.
//! Shapes are checked on the Python side (`sync4d/raster.py`); lengths again here by the core.

use numpy::{Element, PyArray1, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use pyo3::BoundObject;
use std::collections::HashMap;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::{Arc, Mutex, OnceLock};
use sync4d_raster::real::Real;
use sync4d_raster::{self as core, RasterError};

/// Call `$body` with the type alias `$T` bound to the element type of array `$probe`
/// (float32 or float64), so one generic implementation serves both dtypes.
macro_rules! with_float_type {
    ($probe:expr, $arg:literal, |$T:ident| $body:expr) => {{
        if $probe.downcast::<numpy::PyArrayDyn<f32>>().is_ok() {
            #[allow(dead_code)]
            type $T = f32;
            $body
        } else if $probe.downcast::<numpy::PyArrayDyn<f64>>().is_ok() {
            #[allow(dead_code)]
            type $T = f64;
            $body
        } else {
            Err(PyValueError::new_err(concat!(
                $arg,
                ": expected a float32 or float64 array"
            )))
        }
    }};
}

/// Any Python object holding a NumPy array.
type AnyArr<'py> = Bound<'py, PyAny>;

/// Convert a Rust result into a Python object.
fn to_object<'py, V: IntoPyObject<'py>>(py: Python<'py>, v: V) -> PyResult<PyObject>
where
    PyErr: From<V::Error>,
{
    Ok(v.into_pyobject(py)?.into_any().unbind())
}

/// Rayon pools by thread count, built once and reused (0 = rayon's global pool).
fn pool(threads: usize) -> PyResult<Option<Arc<rayon::ThreadPool>>> {
    if threads == 0 {
        return Ok(None);
    }
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<rayon::ThreadPool>>>> = OnceLock::new();
    let mut pools = POOLS
        .get_or_init(|| Mutex::new(HashMap::new()))
        .lock()
        .map_err(|_| PyRuntimeError::new_err("sync4d: thread-pool registry poisoned"))?;
    if let Some(p) = pools.get(&threads) {
        return Ok(Some(p.clone()));
    }
    let p = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| {
            PyRuntimeError::new_err(format!("sync4d: cannot start {threads} threads: {e}"))
        })?;
    let p = Arc::new(p);
    pools.insert(threads, p.clone());
    Ok(Some(p))
}

/// Run `f` without the GIL on a pool of `threads` threads, mapping errors and panics.
fn run<T: Send>(
    py: Python<'_>,
    threads: usize,
    f: impl FnOnce() -> core::Result<T> + Send,
) -> PyResult<T> {
    let pool = pool(threads)?;
    let out = py.allow_threads(move || {
        catch_unwind(AssertUnwindSafe(move || match pool {
            Some(p) => p.install(f),
            None => f(),
        }))
    });
    match out {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(to_py(e)),
        Err(panic) => {
            let msg = panic
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| panic.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "unknown panic".into());
            Err(PyRuntimeError::new_err(format!(
                "sync4d rasterizer internal error (please report with the inputs that caused it): {msg}"
            )))
        }
    }
}

fn to_py(e: RasterError) -> PyErr {
    PyValueError::new_err(e.to_string())
}

/// Borrow a contiguous array as a flat slice, or fail naming `arg`.
fn flat<'a, T: Element>(arr: &'a PyReadonlyArrayDyn<'_, T>, arg: &str) -> PyResult<&'a [T]> {
    arr.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{arg}: must be C-contiguous")))
}

/// A new 1-D array of `len` zeros.
fn zeros<'py, T: Element>(py: Python<'py>, len: usize) -> Bound<'py, PyArray1<T>> {
    PyArray1::zeros(py, len, false)
}

/// Mutable view of an array this module just allocated and has not handed to Python yet, so no
/// other reference to its data can exist.
#[allow(clippy::mut_from_ref)]
fn slice_mut<'a, T: Element>(a: &'a Bound<'_, PyArray1<T>>) -> &'a mut [T] {
    // SAFETY: the array was just created by us and is not shared with Python yet.
    unsafe { a.as_slice_mut().expect("fresh array is contiguous") }
}

fn camera(
    viewmat: Vec<f64>,
    intr: (f64, f64, f64, f64),
    width: u32,
    height: u32,
) -> PyResult<core::Camera> {
    core::Camera::new(&viewmat, intr.0, intr.1, intr.2, intr.3, width, height).map_err(to_py)
}

type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;
type Out<'py, T> = Bound<'py, PyArray1<T>>;
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
/// (features, alpha, depth_accum, counters).
type ImageResult<'py, T> = (Out<'py, T>, Out<'py, T>, Out<'py, T>, Bound<'py, PyDict>);

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

/// Splat inputs borrowed from NumPy.
fn splats_of<'a, T: Element>(
    a: &'a SplatArrs<'_, T>,
    channels: usize,
) -> PyResult<core::Splats<'a, T>> {
    Ok(core::Splats {
        means2d: flat(&a.0, "means2d")?,
        conics: flat(&a.1, "conics")?,
        depths: flat(&a.2, "depths")?,
        opacities: flat(&a.3, "opacities")?,
        radii: flat(&a.4, "radii")?,
        features: flat(&a.5, "features")?,
        channels,
    })
}

fn counters_dict<'py>(py: Python<'py>, c: core::Counters) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("visible", c.visible)?;
    d.set_item("intersections", c.intersections)?;
    d.set_item("evaluated", c.evaluated)?;
    d.set_item("blended", c.blended)?;
    Ok(d)
}

type SplatArrs<'py, T> = (
    Arr<'py, T>,
    Arr<'py, T>,
    Arr<'py, T>,
    Arr<'py, T>,
    Arr<'py, i32>,
    Arr<'py, T>,
);
type SplatGradOut<'py, T> = (
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
);

fn alloc_splat_grads<'py, T: Element>(
    py: Python<'py>,
    n: usize,
    ch: usize,
) -> SplatGradOut<'py, T> {
    (
        zeros(py, 2 * n),
        zeros(py, 3 * n),
        zeros(py, n),
        zeros(py, n),
        zeros(py, n * ch),
    )
}

fn splat_grads_mut<'a, T: Element>(o: &'a SplatGradOut<'_, T>) -> core::SplatGradsMut<'a, T> {
    core::SplatGradsMut {
        means2d: slice_mut(&o.0),
        conics: slice_mut(&o.1),
        depths: slice_mut(&o.2),
        opacities: slice_mut(&o.3),
        features: slice_mut(&o.4),
    }
}

/// Output images of one forward: features [H*W*C], alpha [H*W], depth [H*W], zeroed.
type ImageOut<'py, T> = (Out<'py, T>, Out<'py, T>, Out<'py, T>);

fn alloc_image<'py, T: Element>(py: Python<'py>, npix: usize, ch: usize) -> ImageOut<'py, T> {
    (zeros(py, npix * ch), zeros(py, npix), zeros(py, npix))
}

fn image_mut<'a, T: Element>(o: &'a ImageOut<'_, T>) -> core::ImageMut<'a, T> {
    core::ImageMut {
        features: slice_mut(&o.0),
        alpha: slice_mut(&o.1),
        depth: slice_mut(&o.2),
    }
}

/// Borrow the backward's incoming image gradients (features, alpha, depth).
fn image_grads<'a, T: Element>(
    g: &'a (Arr<'_, T>, Arr<'_, T>, Arr<'_, T>),
) -> PyResult<core::ImageGrads<'a, T>> {
    Ok(core::ImageGrads {
        features: flat(&g.0, "grad_features")?,
        alpha: flat(&g.1, "grad_alpha")?,
        depth: flat(&g.2, "grad_depth")?,
    })
}

/// The fast (float32) compositor with its reusable buffers: one per in-flight render. Keep it
/// from forward to backward; reuse it across iterations so large buffers are touched once.
#[pyclass(module = "sync4d._core")]
struct RasterContext {
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

    /// Composite splats: `splats` = (means2d, conics, depths, opacities, radii, features) flat
    /// arrays, float32 (fast path) or float64 (reference). Returns (features H*W*C, alpha H*W,
    /// depth_accum H*W, counters).
    #[allow(clippy::too_many_arguments)]
    fn forward<'py>(
        &self,
        py: Python<'py>,
        splats: SplatAny<'py>,
        channels: usize,
        background: AnyArr<'py>,
        width: u32,
        height: u32,
        alpha_max: f64,
        threads: usize,
    ) -> PyResult<PyObject> {
        with_float_type!(splats.0, "means2d", |T| {
            let arrs = extract_splats::<T>(&splats)?;
            let out = self.forward_typed::<T>(
                py,
                &arrs,
                channels,
                background.extract()?,
                width,
                height,
                alpha_max,
                threads,
            )?;
            to_object(py, out)
        })
    }

    /// Backward of `forward`: returns dL/d(means2d, conics, depths, opacities, features).
    /// Inputs must be the forward's.
    #[allow(clippy::too_many_arguments)]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        splats: SplatAny<'py>,
        channels: usize,
        background: AnyArr<'py>,
        width: u32,
        height: u32,
        alpha_max: f64,
        grads: (AnyArr<'py>, AnyArr<'py>, AnyArr<'py>),
        threads: usize,
    ) -> PyResult<PyObject> {
        with_float_type!(splats.0, "means2d", |T| {
            let arrs = extract_splats::<T>(&splats)?;
            let g = (grads.0.extract()?, grads.1.extract()?, grads.2.extract()?);
            let out = self.backward_typed::<T>(
                py,
                &arrs,
                channels,
                background.extract()?,
                width,
                height,
                alpha_max,
                g,
                threads,
            )?;
            to_object(py, out)
        })
    }

    /// Bytes held by this context's reusable buffers.
    fn nbytes(&self) -> usize {
        self.state.lock().map(|s| s.bytes()).unwrap_or(0)
    }
}

impl RasterContext {
    #[allow(clippy::too_many_arguments)]
    fn forward_typed<'py, T: core::Composite + Element>(
        &self,
        py: Python<'py>,
        splats: &SplatArrs<'py, T>,
        channels: usize,
        background: Arr<'py, T>,
        width: u32,
        height: u32,
        alpha_max: f64,
        threads: usize,
    ) -> PyResult<ImageResult<'py, T>> {
        let sp = splats_of(splats, channels)?;
        let bg = flat(&background, "background")?;
        let img = alloc_image::<T>(py, width as usize * height as usize, channels);
        let out = image_mut(&img);
        let bs = core::BlendSettings { alpha_max };
        let state = &self.state;
        let counters = run(py, threads, || {
            let mut st = state.lock().unwrap_or_else(|p| p.into_inner());
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
        width: u32,
        height: u32,
        alpha_max: f64,
        grads: (Arr<'py, T>, Arr<'py, T>, Arr<'py, T>),
        threads: usize,
    ) -> PyResult<SplatGradOut<'py, T>> {
        let sp = splats_of(splats, channels)?;
        let bg = flat(&background, "background")?;
        let v = image_grads(&grads)?;
        let out = alloc_splat_grads::<T>(py, sp.len(), channels);
        let g = splat_grads_mut(&out);
        let bs = core::BlendSettings { alpha_max };
        let state = &self.state;
        run(py, threads, || {
            let mut st = state.lock().unwrap_or_else(|p| p.into_inner());
            T::composite_backward(&sp, width, height, bg, &bs, &mut st, &v, g)
        })?;
        Ok(out)
    }
}

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
            let mut r = gpu.lock().unwrap_or_else(|p| p.into_inner());
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
fn wgpu_adapter() -> PyResult<String> {
    let gpu = wgpu_rasterizer()?;
    let r = gpu.lock().unwrap_or_else(|p| p.into_inner());
    Ok(r.device().adapter.to_string())
}

/// Adapters wgpu can see, best first, as (name, kind) with kind one of "discrete",
/// "integrated", "virtual", "cpu", "other". Opens no device.
#[pyfunction]
fn wgpu_adapters(py: Python<'_>) -> Vec<(String, &'static str)> {
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
struct WgpuContext {
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

    /// Composite float32 splats (see `RasterContext.forward`).
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (splats, channels, background, width, height, alpha_max, threads))]
    fn forward<'py>(
        &self,
        py: Python<'py>,
        splats: SplatAny<'py>,
        channels: usize,
        background: AnyArr<'py>,
        width: u32,
        height: u32,
        alpha_max: f64,
        threads: usize,
    ) -> PyResult<PyObject> {
        let _ = threads;
        let arrs = extract_splats::<f32>(&splats).map_err(|_| float32_only())?;
        let sp = splats_of(&arrs, channels)?;
        let bg: Arr<'py, f32> = background.extract().map_err(|_| float32_only())?;
        let bg = flat(&bg, "background")?;
        let img = alloc_image::<f32>(py, width as usize * height as usize, channels);
        let out = image_mut(&img);
        let bs = core::BlendSettings { alpha_max };
        let state = &self.state;
        let counters = run_wgpu(py, |r| {
            let mut st = state.lock().unwrap_or_else(|p| p.into_inner());
            r.rasterize_forward(&sp, width, height, bg, &bs, &mut st, out)
        })?;
        to_object(py, (img.0, img.1, img.2, counters_dict(py, counters)?))
    }

    /// Backward of `forward` (see `RasterContext.backward`).
    #[allow(clippy::too_many_arguments)]
    #[pyo3(signature = (splats, channels, background, width, height, alpha_max, grads, threads))]
    fn backward<'py>(
        &self,
        py: Python<'py>,
        splats: SplatAny<'py>,
        channels: usize,
        background: AnyArr<'py>,
        width: u32,
        height: u32,
        alpha_max: f64,
        grads: (AnyArr<'py>, AnyArr<'py>, AnyArr<'py>),
        threads: usize,
    ) -> PyResult<PyObject> {
        let _ = threads;
        let arrs = extract_splats::<f32>(&splats).map_err(|_| float32_only())?;
        let sp = splats_of(&arrs, channels)?;
        let bg: Arr<'py, f32> = background.extract().map_err(|_| float32_only())?;
        let bg = flat(&bg, "background")?;
        let g: (Arr<'py, f32>, Arr<'py, f32>, Arr<'py, f32>) = (
            grads.0.extract().map_err(|_| float32_only())?,
            grads.1.extract().map_err(|_| float32_only())?,
            grads.2.extract().map_err(|_| float32_only())?,
        );
        let v = image_grads(&g)?;
        let out = alloc_splat_grads::<f32>(py, sp.len(), channels);
        let gm = splat_grads_mut(&out);
        let bs = core::BlendSettings { alpha_max };
        let state = &self.state;
        run_wgpu(py, |r| {
            let mut st = state.lock().unwrap_or_else(|p| p.into_inner());
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

/// Splat arrays of unknown dtype: (means2d, conics, depths, opacities, radii, features).
type SplatAny<'py> = (
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
    AnyArr<'py>,
);

/// Borrow splat arrays as element type `T` (radii as int32).
fn extract_splats<'py, T: Element>(s: &SplatAny<'py>) -> PyResult<SplatArrs<'py, T>> {
    Ok((
        s.0.extract()?,
        s.1.extract()?,
        s.2.extract()?,
        s.3.extract()?,
        s.4.extract()?,
        s.5.extract()?,
    ))
}

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

/// Project Gaussians (float32: fast path; float64: for gradient checks). Returns (means2d,
/// conics, depths, opacities, radii, visible) as flat arrays.
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn project_forward<'py>(
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
fn project_backward<'py>(
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

/// Spherical-harmonics colours: dirs N*3, coeffs N*K*C (float32 or float64) → N*C.
#[pyfunction]
fn sh_forward<'py>(
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
#[allow(clippy::too_many_arguments)]
fn sh_backward<'py>(
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

fn loss_typed<'py, T: Real + Element>(
    py: Python<'py>,
    pred: Arr<'py, T>,
    target: Arr<'py, T>,
    shape: (usize, usize, usize),
    weights: core::LossWeights,
    want_grad: bool,
    threads: usize,
) -> PyResult<PyObject> {
    let (x, y) = (flat(&pred, "pred")?, flat(&target, "target")?);
    let grad = want_grad.then(|| zeros::<T>(py, x.len()));
    let g = grad.as_ref().map(|a| slice_mut(a));
    let (h, w, c) = shape;
    let t = run(py, threads, || {
        core::photometric_loss(x, y, h, w, c, &weights, g)
    })?;
    to_object(py, (t.loss, t.mean_abs, t.ssim, grad))
}

/// Training loss l1 * mean|pred - target| + dssim * (1 - SSIM) / 2 of [height, width, channels]
/// images (flat float32 or float64 arrays of one type), SSIM over `window` x `window` reflect-
/// padded box means. Returns (loss, mean_abs, ssim, dL/d pred or None).
#[pyfunction]
#[allow(clippy::too_many_arguments)]
fn photometric_loss<'py>(
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
    let weights = core::LossWeights { l1, dssim, window };
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

/// Number of threads rayon's global pool uses.
#[pyfunction]
fn default_threads() -> usize {
    rayon::current_num_threads()
}

/// The compiled core of sync4d.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RasterContext>()?;
    m.add_class::<WgpuContext>()?;
    m.add_function(wrap_pyfunction!(wgpu_adapter, m)?)?;
    m.add_function(wrap_pyfunction!(wgpu_adapters, m)?)?;
    m.add_function(wrap_pyfunction!(project_forward, m)?)?;
    m.add_function(wrap_pyfunction!(project_backward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_forward, m)?)?;
    m.add_function(wrap_pyfunction!(sh_backward, m)?)?;
    m.add_function(wrap_pyfunction!(photometric_loss, m)?)?;
    m.add_function(wrap_pyfunction!(default_threads, m)?)?;
    m.add("TILE_SIZE", core::TILE_SIZE)?;
    Ok(())
}
