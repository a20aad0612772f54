//! Thin pyo3 bindings: `sync4d._core`. Arrays come in as NumPy views of torch tensors (no copies;
//! flat C-contiguous), the GIL is released while Rust works, `RasterError`s become `ValueError`s
//! naming the argument, and a Rust panic becomes a `RuntimeError` instead of crossing into Python.
//! Shapes are checked on the Python side (`sync4d/raster.py`); lengths again here by the core.
//!
//! One file per concern: `arrays` (NumPy arrays and argument conversion, and `bindings!`, the
//! forward and backward pairs with shared arguments), `runtime` (threads, GIL release, error and
//! panic mapping), `settings` (the settings objects the bindings take by name), `project`,
//! `composite` (what the two compositing contexts share), `raster` (CPU compositing), `gpu` (the
//! wgpu backend), `sh` and `loss` (the bindings; the loss itself is the sync4d-loss crate),
//! `motion` (the node motion kernels of sync4d-motion), and here the module's registration.
//! Every binding takes its settings, sizes, flags and `threads` by keyword (the compositing
//! bindings their arrays too).

mod arrays;
mod composite;
mod gpu;
mod loss;
mod motion;
mod project;
mod raster;
mod runtime;
mod settings;
mod sh;

use pyo3::prelude::*;
use sync4d_raster as core;

use gpu::{wgpu_adapter, wgpu_adapters, WgpuContext};
use loss::photometric_loss;
use motion::{
    linear_epilogue_backward, linear_epilogue_forward, node_weighted_sum_backward,
    node_weighted_sum_forward,
};
use project::{project_backward, project_forward};
use raster::RasterContext;
use runtime::default_threads;
use settings::{CompositeSettings, ProjectSettings};
use sh::{sh_backward, sh_forward};

/// Add each `#[pyfunction]` named to module `$m`.
macro_rules! add_functions {
    ($m:ident: $($f:ident),* $(,)?) => {
        $($m.add_function(wrap_pyfunction!($f, $m)?)?;)*
    };
}

/// The compiled core of sync4d.
#[pymodule]
fn _core(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<RasterContext>()?;
    m.add_class::<WgpuContext>()?;
    m.add_class::<ProjectSettings>()?;
    m.add_class::<CompositeSettings>()?;
    add_functions! { m:
        wgpu_adapter, wgpu_adapters, project_forward, project_backward, sh_forward, sh_backward,
        photometric_loss, node_weighted_sum_forward, node_weighted_sum_backward,
        linear_epilogue_forward, linear_epilogue_backward, default_threads,
    }
    m.add("TILE_SIZE", core::TILE_SIZE)?;
    m.add("ALPHA_MIN", core::ALPHA_MIN)?;
    m.add("T_MIN", core::T_MIN)?;
    // The defaults of `sync4d.raster`'s keyword arguments, read from the core's settings.
    let project = core::ProjectSettings::default();
    m.add("DEFAULT_NEAR", project.near)?;
    m.add("DEFAULT_FAR", project.far)?;
    m.add("DEFAULT_EPS2D", project.eps2d)?;
    let blend = core::BlendSettings::default();
    m.add("DEFAULT_ALPHA_MAX", blend.alpha_max)?;
    Ok(())
}
