//! Projection on the device: the Gaussians and the camera uploaded,
//! [`GpuRasterizer::project_forward`] and its backward, and the camera in the layout of
//! project.wgsl's parameters. Apart from compositing, which starts from splats and needs none of
//! this.

use sync4d_raster::{
    Camera, GaussianGradsMut, Gaussians, ProjectSettings, ProjectionGrads, ProjectionMut,
    RasterError,
};

use super::kernels::grid;
use super::params::{ProjectParams, SPLAT_FLOATS, WG};
use super::rasterizer::GpuRasterizer;
use crate::error::Result;

impl GpuRasterizer {
    /// Upload the Gaussians and the projection parameters.
    fn gaussians_in(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
    ) -> Result<[wgpu::Buffer; 5]> {
        let n = gaussians.len();
        if n > (1 << 27) {
            return Err(
                RasterError::invalid("means", "too many Gaussians for the GPU path").into(),
            );
        }
        Ok([
            self.uniform(&project_params(camera, settings, n as u32)),
            self.upload("means", gaussians.means)?,
            self.upload("quats", gaussians.quats)?,
            self.upload("scales", gaussians.scales)?,
            self.upload("opacities", gaussians.opacities)?,
        ])
    }

    /// Project every Gaussian through `camera` (as [`sync4d_raster::project_forward`]);
    /// returns the number of visible Gaussians. Computed in f32 on the device, so outputs
    /// agree with the CPU path (f64 inside) to f32 rounding, and radii to +-1 pixel.
    pub fn project_forward(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
        out: ProjectionMut<'_, f32>,
    ) -> Result<usize> {
        gaussians.validate()?;
        camera.validate()?;
        settings.validate()?;
        let n = gaussians.len();
        out.check_len(n)?;
        if n == 0 {
            return Ok(0);
        }
        let [params, means, quats, scales, opac] =
            self.gaussians_in(gaussians, camera, settings)?;
        let splats = self.storage("projected", (n * SPLAT_FLOATS * 4) as u64)?;
        let radii = self.storage("projected_radii", (n * 8) as u64)?;
        let group = self.bind(
            &self.kernels.project,
            &[
                (0, &params),
                (1, &means),
                (2, &quats),
                (3, &scales),
                (4, &opac),
                (5, &splats),
                (6, &radii),
            ],
        );
        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        Self::dispatch(
            &mut enc,
            &self.kernels.project,
            &group,
            grid((n as u32).div_ceil(WG)),
        );
        self.gpu.queue.submit([enc.finish()]);
        let packed = self.read_f32(&splats, n * SPLAT_FLOATS)?;
        let rad: Vec<i32> = bytemuck::pod_collect_to_vec(&self.read(&radii, (n * 8) as u64)?);
        let mut visible = 0;
        for i in 0..n {
            let s = &packed[SPLAT_FLOATS * i..SPLAT_FLOATS * (i + 1)];
            out.means2d[2 * i] = s[0];
            out.means2d[2 * i + 1] = s[1];
            out.conics[3 * i..3 * i + 3].copy_from_slice(&s[2..5]);
            out.opacities[i] = s[5];
            out.depths[i] = s[6];
            out.radii[2 * i] = rad[2 * i];
            out.radii[2 * i + 1] = rad[2 * i + 1];
            visible += usize::from(rad[2 * i] > 0 && rad[2 * i + 1] > 0);
        }
        Ok(visible)
    }

    /// Backward of [`GpuRasterizer::project_forward`] (as [`sync4d_raster::project_backward`]):
    /// dL/d(means, quats, scales, opacities) from dL/d(projection outputs), in f32.
    pub fn project_backward(
        &mut self,
        gaussians: &Gaussians<'_, f32>,
        camera: &Camera,
        settings: &ProjectSettings,
        v_out: &ProjectionGrads<'_, f32>,
        grads: GaussianGradsMut<'_, f32>,
    ) -> Result<()> {
        gaussians.validate()?;
        camera.validate()?;
        settings.validate()?;
        let n = gaussians.len();
        v_out.validate(n)?;
        grads.check_len(n)?;
        if n == 0 {
            return Ok(());
        }
        let [params, means, quats, scales, opac] =
            self.gaussians_in(gaussians, camera, settings)?;
        let mut v = vec![0.0f32; n * 8];
        for i in 0..n {
            v[8 * i] = v_out.means2d[2 * i];
            v[8 * i + 1] = v_out.means2d[2 * i + 1];
            v[8 * i + 2..8 * i + 5].copy_from_slice(&v_out.conics[3 * i..3 * i + 3]);
            v[8 * i + 5] = v_out.depths[i];
            v[8 * i + 6] = v_out.opacities[i];
        }
        let v_buf = self.upload("v_projected", &v)?;
        let out = self.storage("gaussian_grads", (n * 12 * 4) as u64)?;
        let group = self.bind(
            &self.kernels.project_backward,
            &[
                (0, &params),
                (1, &means),
                (2, &quats),
                (3, &scales),
                (4, &opac),
                (7, &v_buf),
                (8, &out),
            ],
        );
        let mut enc = self
            .gpu
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
        Self::dispatch(
            &mut enc,
            &self.kernels.project_backward,
            &group,
            grid((n as u32).div_ceil(WG)),
        );
        self.gpu.queue.submit([enc.finish()]);
        let g = self.read_f32(&out, n * 12)?;
        for i in 0..n {
            let r = &g[12 * i..12 * i + 12];
            grads.means[3 * i..3 * i + 3].copy_from_slice(&r[0..3]);
            grads.quats[4 * i..4 * i + 4].copy_from_slice(&r[3..7]);
            grads.scales[3 * i..3 * i + 3].copy_from_slice(&r[7..10]);
            grads.opacities[i] = r[10];
        }
        Ok(())
    }
}

/// Camera and settings in the layout of project.wgsl's `Params`.
fn project_params(cam: &Camera, s: &ProjectSettings, n: u32) -> ProjectParams {
    let m = &cam.world_to_camera;
    let (w, h) = (cam.width as f64, cam.height as f64);
    let tan_fovx = 0.5 * w / cam.fx;
    let tan_fovy = 0.5 * h / cam.fy;
    let row = |r: usize| {
        [
            m[r][0] as f32,
            m[r][1] as f32,
            m[r][2] as f32,
            m[r][3] as f32,
        ]
    };
    ProjectParams {
        rot: [row(0), row(1), row(2)],
        intr: [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32],
        size: [
            w as f32,
            h as f32,
            s.eps2d as f32,
            f32::from(u8::from(s.antialiased)),
        ],
        lims: [
            ((w - cam.cx) / cam.fx + 0.3 * tan_fovx) as f32,
            (cam.cx / cam.fx + 0.3 * tan_fovx) as f32,
            ((h - cam.cy) / cam.fy + 0.3 * tan_fovy) as f32,
            (cam.cy / cam.fy + 0.3 * tan_fovy) as f32,
        ],
        clip: [s.near as f32, s.far.min(f32::MAX as f64) as f32, 0.0, 0.0],
        count: [n, 0, 0, 0],
    }
}
