//! Pinhole camera: OpenCV axes (x right, y down, z forward), world-to-camera 4x4, intrinsics in
//! pixels. Validated once per call so the kernels can assume a sane camera.

use crate::error::{RasterError, Result};
use glam::{DMat3, DVec3};

/// A pinhole camera. `world_to_camera` is row-major; its last row must be `[0, 0, 0, 1]` and its
/// upper 3x3 a rotation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    /// Row-major 4x4 world-to-camera transform (OpenCV axes).
    pub world_to_camera: [[f64; 4]; 4],
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel centres sit at integer + 0.5).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

/// Largest supported image side, pixels.
pub const MAX_IMAGE_SIDE: u32 = 16384;

impl Camera {
    /// Build a camera from a row-major 4x4 world-to-camera matrix (16 values) and intrinsics.
    pub fn new(
        viewmat: &[f64],
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
    ) -> Result<Self> {
        if viewmat.len() != 16 {
            return Err(RasterError::invalid(
                "viewmat",
                format!("expected a 4x4 matrix (16 values), got {}", viewmat.len()),
            ));
        }
        let mut m = [[0.0; 4]; 4];
        for (r, row) in m.iter_mut().enumerate() {
            row.copy_from_slice(&viewmat[r * 4..r * 4 + 4]);
        }
        let cam = Camera {
            world_to_camera: m,
            fx,
            fy,
            cx,
            cy,
            width,
            height,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// Check the camera: finite entries, rigid world-to-camera, positive focal lengths and a
    /// non-empty image no larger than [`MAX_IMAGE_SIDE`].
    pub fn validate(&self) -> Result<()> {
        let flat: Vec<f64> = self.world_to_camera.iter().flatten().copied().collect();
        if flat.iter().any(|v| !v.is_finite()) {
            return Err(RasterError::invalid("viewmat", "contains NaN or inf"));
        }
        let last = self.world_to_camera[3];
        if last != [0.0, 0.0, 0.0, 1.0] {
            return Err(RasterError::invalid(
                "viewmat",
                format!("last row must be [0, 0, 0, 1], got {last:?}"),
            ));
        }
        let r = self.rotation();
        let err = (r * r.transpose() - DMat3::IDENTITY).to_cols_array();
        let max_err = err.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        if max_err > 1e-3 || r.determinant() < 0.0 {
            return Err(RasterError::invalid(
                "viewmat",
                format!(
                    "upper 3x3 must be a rotation (orthonormal, det +1); |R R^T - I| = {max_err:.2e}, det = {:.4}",
                    r.determinant()
                ),
            ));
        }
        for (name, v) in [("K (fx)", self.fx), ("K (fy)", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(RasterError::invalid(
                    name,
                    format!("focal length must be finite and > 0, got {v}"),
                ));
            }
        }
        for v in [self.cx, self.cy] {
            if !v.is_finite() {
                return Err(RasterError::invalid(
                    "K",
                    "principal point contains NaN or inf",
                ));
            }
        }
        for (name, v) in [("width", self.width), ("height", self.height)] {
            if v == 0 || v > MAX_IMAGE_SIDE {
                return Err(RasterError::invalid(
                    name,
                    format!("image side must be in 1..={MAX_IMAGE_SIDE}, got {v}"),
                ));
            }
        }
        Ok(())
    }

    /// The world-to-camera rotation (upper 3x3).
    pub fn rotation(&self) -> DMat3 {
        let m = &self.world_to_camera;
        DMat3::from_cols(
            DVec3::new(m[0][0], m[1][0], m[2][0]),
            DVec3::new(m[0][1], m[1][1], m[2][1]),
            DVec3::new(m[0][2], m[1][2], m[2][2]),
        )
    }

    /// The world-to-camera translation.
    pub fn translation(&self) -> DVec3 {
        let m = &self.world_to_camera;
        DVec3::new(m[0][3], m[1][3], m[2][3])
    }

    /// Number of 16x16 tiles along x and y.
    pub fn tile_grid(&self) -> (u32, u32) {
        (
            self.width.div_ceil(crate::TILE_SIZE),
            self.height.div_ceil(crate::TILE_SIZE),
        )
    }
}
