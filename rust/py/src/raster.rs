//! CPU rasterization bindings: `RasterContext`, the compositor (float32 fast path, float64
//! reference) with the reusable buffers its backward needs.

use pyo3::prelude::*;
use sync4d_raster::{self as core, Composite as _};

use crate::arrays::{extract_image_grads, extract_splats, with_float_type};
use crate::composite::{
    backward_with, compositor_context, forward_with, BackwardArgs, CompositeArgs,
};
use crate::runtime::{lock_recover, run};

compositor_context!(
    /// The fast (float32) compositor with its reusable buffers: one per in-flight render. Keep it
    /// from forward to backward; reuse it across iterations so large buffers are touched once.
    RasterContext(core::RasterState),
    forward:
    /// Composite splats given by name: `means2d`, `conics`, `depths`, `opacities`, `radii`
    /// (int32), `features` (`channels` per splat) and `background`, flat arrays, float32 (fast
    /// path) or float64 (reference), with `settings` (a `CompositeSettings`). Returns
    /// (features H*W*C, alpha H*W, depth_accum H*W, counters).
    ,
    backward:
    /// Backward of `forward`: the forward's arguments by the same names plus the incoming
    /// gradients `grad_features`, `grad_alpha`, `grad_depth`; returns dL/d(means2d, conics,
    /// depths, opacities, features). Inputs must be the forward's.
    ,

    /// Bytes held by this context's reusable buffers.
    fn nbytes(&self) -> usize {
        self.state.lock().map_or(0, |s| s.bytes())
    }
);

impl RasterContext {
    /// `forward` on float32 or float64 arrays (the dtype of `means2d`).
    fn forward_any(&self, py: Python<'_>, args: &CompositeArgs<'_>) -> PyResult<PyObject> {
        let state = &self.state;
        with_float_type!(args.splats.means2d, "means2d", |T| {
            let arrs = extract_splats::<T>(&args.splats)?;
            let bg = args.background.extract()?;
            forward_with(py, (&arrs, &bg), args, |(sp, (w, h), bg, bs), out| {
                run(py, args.threads, || {
                    T::composite_forward(&sp, w, h, bg, &bs, &mut lock_recover(state), out)
                })
            })
        })
    }

    /// `backward` on float32 or float64 arrays (the dtype of `means2d`).
    fn backward_any(&self, py: Python<'_>, args: &BackwardArgs<'_>) -> PyResult<PyObject> {
        let (call, state) = (&args.call, &self.state);
        with_float_type!(call.splats.means2d, "means2d", |T| {
            let arrs = extract_splats::<T>(&call.splats)?;
            let g = extract_image_grads::<T>(&args.grads)?;
            let bg = call.background.extract()?;
            backward_with(
                py,
                (&arrs, &bg, &g),
                call,
                |(sp, (w, h), bg, bs), v, out| {
                    run(py, call.threads, || {
                        T::composite_backward(&sp, w, h, bg, &bs, &mut lock_recover(state), v, out)
                    })
                },
            )
        })
    }
}
