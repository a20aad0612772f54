//! Arrays and arguments between NumPy and the core: the float32/float64 dispatch, the
//! `bindings!` that writes a forward and its backward over their shared arguments once, flat
//! borrows of C-contiguous arrays (failing with the argument's name), freshly allocated outputs
//! and their mutable views, the splat, image and gradient arrays by name, and the counters dict.
//! Shared by every binding, so apart from all of them.

use numpy::{Element, PyArray1, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use pyo3::BoundObject;
use sync4d_raster as core;

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
            Err(pyo3::exceptions::PyValueError::new_err(concat!(
                $arg,
                ": expected a float32 or float64 array"
            )))
        }
    }};
}
pub(crate) use with_float_type;

/// `#[pyfunction]`s that share their leading arguments (a forward and its backward): each
/// `fn name(own: type, ...) { body }` becomes `pub(crate) fn name<'py>(py, pos..., kw..., own...,
/// threads) -> PyResult<PyObject>` with the Python signature `(pos..., *, kw..., own...,
/// threads)`, where `$py` (the GIL token), the positional arguments `$pos`, the keyword
/// arguments `$kw` and `$threads` are given once, first. Doc comments stay with each function.
macro_rules! bindings {
    ($shared:tt) => {};
    ($shared:tt $(#[$doc:meta])* fn $name:ident $own:tt $body:block $($rest:tt)*) => {
        bindings!(@one $shared $(#[$doc])* fn $name $own $body);
        bindings!($shared $($rest)*);
    };
    (
        @one ($py:ident, [$($pos:ident: $pty:ty),*], [$($kw:ident: $kty:ty),*], $threads:ident)
        $(#[$doc:meta])* fn $name:ident($($own:ident: $oty:ty),*) $body:block
    ) => {
        $(#[$doc])*
        #[pyo3::pyfunction]
        #[pyo3(signature = ($($pos,)* *, $($kw,)* $($own,)* $threads))]
        #[allow(clippy::too_many_arguments)]
        pub(crate) fn $name<'py>(
            $py: pyo3::Python<'py>,
            $($pos: $pty,)*
            $($kw: $kty,)*
            $($own: $oty,)*
            $threads: usize,
        ) -> pyo3::PyResult<pyo3::PyObject> $body
    };
}
pub(crate) use bindings;

/// Any Python object holding a NumPy array.
pub(crate) type AnyArr<'py> = Bound<'py, PyAny>;

/// Convert a Rust result into a Python object.
pub(crate) fn to_object<'py, V: IntoPyObject<'py>>(py: Python<'py>, v: V) -> PyResult<PyObject>
where
    PyErr: From<V::Error>,
{
    Ok(v.into_pyobject(py)?.into_any().unbind())
}

/// Borrow a contiguous array as a flat slice, or fail naming `arg`.
pub(crate) fn flat<'a, T: Element>(
    arr: &'a PyReadonlyArrayDyn<'_, T>,
    arg: &str,
) -> PyResult<&'a [T]> {
    arr.as_slice()
        .map_err(|_| PyValueError::new_err(format!("{arg}: must be C-contiguous")))
}

/// A new 1-D array of `len` zeros.
pub(crate) fn zeros<T: Element>(py: Python<'_>, len: usize) -> Bound<'_, PyArray1<T>> {
    PyArray1::zeros(py, len, false)
}

/// Mutable view of an array this module just allocated and has not handed to Python yet, so no
/// other reference to its data can exist.
#[allow(clippy::mut_from_ref)]
pub(crate) fn slice_mut<'a, T: Element>(a: &'a Bound<'_, PyArray1<T>>) -> &'a mut [T] {
    // SAFETY: the array was just created by us and is not shared with Python yet.
    unsafe { a.as_slice_mut().expect("fresh array is contiguous") }
}

pub(crate) type Arr<'py, T> = PyReadonlyArrayDyn<'py, T>;
pub(crate) type Out<'py, T> = Bound<'py, PyArray1<T>>;

/// Splat inputs borrowed from NumPy.
pub(crate) fn splats_of<'a, T: Element>(
    a: &'a SplatArrs<'_, T>,
    channels: usize,
) -> PyResult<core::Splats<'a, T>> {
    Ok(core::Splats {
        means2d: flat(&a.means2d, "means2d")?,
        conics: flat(&a.conics, "conics")?,
        depths: flat(&a.depths, "depths")?,
        opacities: flat(&a.opacities, "opacities")?,
        radii: flat(&a.radii, "radii")?,
        features: flat(&a.features, "features")?,
        channels,
    })
}

pub(crate) fn counters_dict(py: Python<'_>, c: core::Counters) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("visible", c.visible)?;
    d.set_item("intersections", c.intersections)?;
    d.set_item("evaluated", c.evaluated)?;
    d.set_item("blended", c.blended)?;
    Ok(d)
}

/// Splat arrays borrowed as element type `T` (radii as int32).
pub(crate) struct SplatArrs<'py, T: Element> {
    means2d: Arr<'py, T>,
    conics: Arr<'py, T>,
    depths: Arr<'py, T>,
    opacities: Arr<'py, T>,
    radii: Arr<'py, i32>,
    features: Arr<'py, T>,
}
pub(crate) type SplatGradOut<'py, T> = (
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
    Out<'py, T>,
);

pub(crate) fn alloc_splat_grads<T: Element>(
    py: Python<'_>,
    n: usize,
    ch: usize,
) -> SplatGradOut<'_, T> {
    (
        zeros(py, 2 * n),
        zeros(py, 3 * n),
        zeros(py, n),
        zeros(py, n),
        zeros(py, n * ch),
    )
}

pub(crate) fn splat_grads_mut<'a, T: Element>(
    o: &'a SplatGradOut<'_, T>,
) -> core::SplatGradsMut<'a, T> {
    core::SplatGradsMut {
        means2d: slice_mut(&o.0),
        conics: slice_mut(&o.1),
        depths: slice_mut(&o.2),
        opacities: slice_mut(&o.3),
        features: slice_mut(&o.4),
    }
}

/// Output images of one forward: features [H*W*C], alpha [H*W], depth [H*W], zeroed.
pub(crate) type ImageOut<'py, T> = (Out<'py, T>, Out<'py, T>, Out<'py, T>);

pub(crate) fn alloc_image<T: Element>(py: Python<'_>, npix: usize, ch: usize) -> ImageOut<'_, T> {
    (zeros(py, npix * ch), zeros(py, npix), zeros(py, npix))
}

pub(crate) fn image_mut<'a, T: Element>(o: &'a ImageOut<'_, T>) -> core::ImageMut<'a, T> {
    core::ImageMut {
        features: slice_mut(&o.0),
        alpha: slice_mut(&o.1),
        depth: slice_mut(&o.2),
    }
}

/// The backward's incoming image gradients as element type `T`.
pub(crate) struct ImageGradArrs<'py, T: Element> {
    features: Arr<'py, T>,
    alpha: Arr<'py, T>,
    depth: Arr<'py, T>,
}

/// Borrow the backward's incoming image gradients (features, alpha, depth).
pub(crate) fn image_grads<'a, T: Element>(
    g: &'a ImageGradArrs<'_, T>,
) -> PyResult<core::ImageGrads<'a, T>> {
    Ok(core::ImageGrads {
        features: flat(&g.features, "grad_features")?,
        alpha: flat(&g.alpha, "grad_alpha")?,
        depth: flat(&g.depth, "grad_depth")?,
    })
}

/// Splat arrays of unknown dtype, by name (the compositing bindings' keyword arguments).
pub(crate) struct SplatAny<'py> {
    pub(crate) means2d: AnyArr<'py>,
    pub(crate) conics: AnyArr<'py>,
    pub(crate) depths: AnyArr<'py>,
    pub(crate) opacities: AnyArr<'py>,
    pub(crate) radii: AnyArr<'py>,
    pub(crate) features: AnyArr<'py>,
}

/// Borrow splat arrays as element type `T` (radii as int32).
pub(crate) fn extract_splats<'py, T: Element>(s: &SplatAny<'py>) -> PyResult<SplatArrs<'py, T>> {
    Ok(SplatArrs {
        means2d: s.means2d.extract()?,
        conics: s.conics.extract()?,
        depths: s.depths.extract()?,
        opacities: s.opacities.extract()?,
        radii: s.radii.extract()?,
        features: s.features.extract()?,
    })
}

/// Incoming image gradients of unknown dtype, by name.
pub(crate) struct ImageGradAny<'py> {
    pub(crate) features: AnyArr<'py>,
    pub(crate) alpha: AnyArr<'py>,
    pub(crate) depth: AnyArr<'py>,
}

/// Borrow image gradients as element type `T`.
pub(crate) fn extract_image_grads<'py, T: Element>(
    g: &ImageGradAny<'py>,
) -> PyResult<ImageGradArrs<'py, T>> {
    Ok(ImageGradArrs {
        features: g.features.extract()?,
        alpha: g.alpha.extract()?,
        depth: g.depth.extract()?,
    })
}
