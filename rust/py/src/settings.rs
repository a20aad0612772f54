//! The settings objects the bindings take by name instead of positional tuples:
//! `ProjectSettings` (the projection's culling planes, 2D blur and antialiasing) and
//! `CompositeSettings` (the compositing stage's image size and alpha clamp). Both are frozen
//! and built with keyword arguments only, so every value is named at the call site; ranges are
//! checked by the core when a call uses them (the same `ValueError`s as before).

use pyo3::prelude::*;
use sync4d_raster as core;

/// Settings of the projection stage: `ProjectSettings(near=..., far=..., eps2d=...,
/// antialiased=...)` (see `sync4d.raster.project_gaussians`).
#[pyclass(module = "sync4d._core", frozen, eq)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ProjectSettings {
    /// Gaussians with camera depth `z <= near` are culled.
    #[pyo3(get)]
    near: f64,
    /// Gaussians with `z >= far` are culled from rasterization.
    #[pyo3(get)]
    far: f64,
    /// Screen-space blur added to the 2D covariance, pixels squared.
    #[pyo3(get)]
    eps2d: f64,
    /// Whether opacities are compensated for the blur (antialiased 3DGS).
    #[pyo3(get)]
    antialiased: bool,
}

#[pymethods]
impl ProjectSettings {
    #[new]
    #[pyo3(signature = (*, near, far, eps2d, antialiased))]
    fn new(near: f64, far: f64, eps2d: f64, antialiased: bool) -> Self {
        ProjectSettings {
            near,
            far,
            eps2d,
            antialiased,
        }
    }

    fn __repr__(&self) -> String {
        let aa = if self.antialiased { "True" } else { "False" };
        format!(
            "ProjectSettings(near={:?}, far={:?}, eps2d={:?}, antialiased={aa})",
            self.near, self.far, self.eps2d
        )
    }
}

impl ProjectSettings {
    /// The core's projection settings.
    pub(crate) fn core(&self) -> core::ProjectSettings {
        core::ProjectSettings {
            near: self.near,
            far: self.far,
            eps2d: self.eps2d,
            antialiased: self.antialiased,
        }
    }
}

/// Settings of the compositing stage: `CompositeSettings(width=..., height=..., alpha_max=...)`
/// (see `sync4d.raster.rasterize_to_pixels`).
#[pyclass(module = "sync4d._core", frozen, eq)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct CompositeSettings {
    /// Image width, pixels.
    #[pyo3(get)]
    pub(crate) width: u32,
    /// Image height, pixels.
    #[pyo3(get)]
    pub(crate) height: u32,
    /// Per-splat alpha clamp.
    #[pyo3(get)]
    pub(crate) alpha_max: f64,
}

#[pymethods]
impl CompositeSettings {
    #[new]
    #[pyo3(signature = (*, width, height, alpha_max))]
    fn new(width: u32, height: u32, alpha_max: f64) -> Self {
        CompositeSettings {
            width,
            height,
            alpha_max,
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "CompositeSettings(width={}, height={}, alpha_max={:?})",
            self.width, self.height, self.alpha_max
        )
    }
}

impl CompositeSettings {
    /// The core's blend settings.
    pub(crate) fn blend(&self) -> core::BlendSettings {
        core::BlendSettings {
            alpha_max: self.alpha_max,
        }
    }

    /// Pixels of the image.
    pub(crate) fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
}
