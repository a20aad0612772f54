//! What the two compositing contexts (`RasterContext` on the CPU, `WgpuContext` on wgpu) have in
//! common: the context type and its Python surface (`new`, and `forward` and `backward` with one
//! keyword signature), written once by [`compositor_context!`], and the typed bodies around a
//! backend's call ([`forward_with`], [`backward_with`]: borrow the arrays, allocate the outputs,
//! call the backend, return the arrays). Each backend module says only how it dispatches dtypes
//! and runs its kernels.

use numpy::Element;
use pyo3::prelude::*;
use sync4d_raster::{self as core, ImageGrads, SplatGradsMut};
use sync4d_scalar::Real;

use crate::arrays::{
    alloc_image, alloc_splat_grads, counters_dict, flat, image_grads, image_mut, splat_grads_mut,
    splats_of, to_object, AnyArr, Arr, ImageGradAny, ImageGradArrs, SplatAny, SplatArrs,
};
use crate::settings::CompositeSettings;

/// The keyword arguments of a compositing call (`forward`), arrays of unknown dtype.
pub(crate) struct CompositeArgs<'py> {
    pub(crate) splats: SplatAny<'py>,
    pub(crate) channels: usize,
    pub(crate) background: AnyArr<'py>,
    pub(crate) settings: CompositeSettings,
    pub(crate) threads: usize,
}

/// The keyword arguments of `backward`: the forward's and the incoming image gradients.
pub(crate) struct BackwardArgs<'py> {
    pub(crate) call: CompositeArgs<'py>,
    pub(crate) grads: ImageGradAny<'py>,
}

/// A frame as the backends take it: splats, (width, height), background, blend settings.
pub(crate) type Frame<'a, T> = (
    core::Splats<'a, T>,
    (u32, u32),
    &'a [T],
    core::BlendSettings,
);

fn frame<'a, T: Element>(
    splats: &'a SplatArrs<'_, T>,
    background: &'a Arr<'_, T>,
    args: &CompositeArgs<'_>,
) -> PyResult<Frame<'a, T>> {
    let s = &args.settings;
    Ok((
        splats_of(splats, args.channels)?,
        (s.width, s.height),
        flat(background, "background")?,
        s.blend(),
    ))
}

/// Composite the borrowed (splats, background) over an image of `args`' size with `composite`
/// (the backend's forward; it releases the GIL): returns (features H*W*C, alpha H*W,
/// depth_accum H*W, counters).
pub(crate) fn forward_with<'py, T: Element>(
    py: Python<'py>,
    (splats, background): (&SplatArrs<'py, T>, &Arr<'py, T>),
    args: &CompositeArgs<'py>,
    composite: impl FnOnce(Frame<'_, T>, core::ImageMut<'_, T>) -> PyResult<core::Counters>,
) -> PyResult<PyObject> {
    let f = frame(splats, background, args)?;
    let img = alloc_image::<T>(py, args.settings.pixels(), args.channels);
    let counters = composite(f, image_mut(&img))?;
    to_object(py, (img.0, img.1, img.2, counters_dict(py, counters)?))
}

/// The backward of [`forward_with`] given the borrowed (splats, background, incoming image
/// gradients), with `composite` the backend's backward: returns dL/d(means2d, conics, depths,
/// opacities, features).
pub(crate) fn backward_with<'py, T: Real + Element>(
    py: Python<'py>,
    (splats, background, grads): (&SplatArrs<'py, T>, &Arr<'py, T>, &ImageGradArrs<'py, T>),
    args: &CompositeArgs<'py>,
    composite: impl FnOnce(Frame<'_, T>, &ImageGrads<'_, T>, SplatGradsMut<'_, T>) -> PyResult<()>,
) -> PyResult<PyObject> {
    let f = frame(splats, background, args)?;
    let v = image_grads(grads)?;
    let out = alloc_splat_grads::<T>(py, f.0.len(), args.channels);
    composite(f, &v, splat_grads_mut(&out))?;
    to_object(py, out)
}

/// A compositing context: `#[pyclass] $ctx { state: Mutex<$state> }` documented by its doc
/// comments, with `#[pymethods]` `new` (a fresh state), `forward` and `backward` (the keyword
/// signature both backends share, each documented by the doc comments given after its name;
/// they gather their arguments into a [`CompositeArgs`] or a [`BackwardArgs`] for the
/// context's own `forward_any` and `backward_any`), then `$extra`, the context's other methods.
macro_rules! compositor_context {
    (
        $(#[$doc:meta])*
        $ctx:ident($state:ty),
        forward: $(#[$fdoc:meta])*,
        backward: $(#[$bdoc:meta])*,
        $($extra:tt)*
    ) => {
        compositor_context!(
            @ [means2d, conics, depths, opacities, radii, features]
            [
                channels: usize,
                background: $crate::arrays::AnyArr<'py>,
                settings: $crate::settings::CompositeSettings
            ]
            $(#[$doc])* $ctx($state), [$(#[$fdoc])*], [$(#[$bdoc])*], $($extra)*
        );
    };
    (
        @ [$($splat:ident),*] [$($arg:ident: $ty:ty),*]
        $(#[$doc:meta])* $ctx:ident($state:ty), [$($fdoc:tt)*], [$($bdoc:tt)*], $($extra:tt)*
    ) => {
        $(#[$doc])*
        #[pyo3::pyclass(module = "sync4d._core")]
        pub(crate) struct $ctx {
            state: std::sync::Mutex<$state>,
        }

        #[pyo3::pymethods]
        #[allow(clippy::too_many_arguments)]
        impl $ctx {
            #[new]
            fn new() -> Self {
                $ctx {
                    state: std::sync::Mutex::new(<$state>::new()),
                }
            }

            $($fdoc)*
            #[pyo3(signature = (*, $($splat,)* $($arg,)* threads))]
            fn forward<'py>(
                &self,
                py: pyo3::Python<'py>,
                $($splat: $crate::arrays::AnyArr<'py>,)*
                $($arg: $ty,)*
                threads: usize,
            ) -> pyo3::PyResult<pyo3::PyObject> {
                let splats = $crate::arrays::SplatAny { $($splat),* };
                let args = $crate::composite::CompositeArgs {
                    splats, $($arg,)* threads
                };
                self.forward_any(py, &args)
            }

            $($bdoc)*
            #[pyo3(signature = (
                *, $($splat,)* $($arg,)* grad_features, grad_alpha, grad_depth, threads
            ))]
            fn backward<'py>(
                &self,
                py: pyo3::Python<'py>,
                $($splat: $crate::arrays::AnyArr<'py>,)*
                $($arg: $ty,)*
                grad_features: $crate::arrays::AnyArr<'py>,
                grad_alpha: $crate::arrays::AnyArr<'py>,
                grad_depth: $crate::arrays::AnyArr<'py>,
                threads: usize,
            ) -> pyo3::PyResult<pyo3::PyObject> {
                let splats = $crate::arrays::SplatAny { $($splat),* };
                let grads = $crate::arrays::ImageGradAny {
                    features: grad_features,
                    alpha: grad_alpha,
                    depth: grad_depth,
                };
                let call = $crate::composite::CompositeArgs {
                    splats, $($arg,)* threads
                };
                self.backward_any(py, &$crate::composite::BackwardArgs { call, grads })
            }

            $($extra)*
        }
    };
}
pub(crate) use compositor_context;
