//! Rendering a checkpoint: SH colours (3DGS convention: SH of the direction camera centre ->
//! mean, plus 0.5, clamped at 0) and the checkpoint's opacities, then the CPU or wgpu
//! rasterizer with the run's near plane and background.

use sync4d_gpu::{GpuRasterState, GpuRasterizer};
use sync4d_raster::{
    project_forward, rasterize_forward, sh_forward, BlendSettings, Camera, Gaussians, ImageMut,
    ProjectSettings, ProjectionMut, RasterState, Splats,
};

use crate::checkpoint::Checkpoint;
use crate::deform::Deformed;

/// Where rendering runs.
pub enum Backend {
    /// sync4d-raster on the CPU threads.
    Cpu(RasterState),
    /// sync4d-gpu on a wgpu adapter.
    Wgpu(Box<GpuRasterizer>, GpuRasterState),
}

/// An error while rendering (bad camera, adapter failure), as text for the command line.
pub type RenderError = String;

/// RGB image [H*W*3] in [0, 1] (before clamping) of `g` seen by `camera`.
pub fn render(
    ck: &Checkpoint,
    g: &Deformed,
    camera: &Camera,
    backend: &mut Backend,
) -> Result<Vec<f32>, RenderError> {
    let n = ck.n;
    let r = camera.rotation();
    let t = camera.translation();
    let centre = -(r.transpose() * t);
    let mut dirs = vec![0.0f32; 3 * n];
    for i in 0..n {
        for k in 0..3 {
            dirs[3 * i + k] = g.means[3 * i + k] - centre[k] as f32;
        }
    }
    let bases = ((ck.sh_degree + 1) * (ck.sh_degree + 1)) as usize;
    let mut colors = vec![0.0f32; 3 * n];
    sh_forward(ck.sh_degree, &dirs, &ck.sh, bases, 3, &mut colors).map_err(|e| e.to_string())?;
    for c in &mut colors {
        *c = (*c + 0.5).max(0.0);
    }
    let gaussians = Gaussians {
        means: &g.means,
        quats: &g.quats,
        scales: &g.scales,
        opacities: &ck.opacities,
    };
    let ps = ProjectSettings {
        near: ck.near,
        ..Default::default()
    };
    let (mut m2, mut co, mut de, mut op, mut ra) = (
        vec![0.0f32; 2 * n],
        vec![0.0f32; 3 * n],
        vec![0.0f32; n],
        vec![0.0f32; n],
        vec![0i32; 2 * n],
    );
    let out = ProjectionMut {
        means2d: &mut m2,
        conics: &mut co,
        depths: &mut de,
        opacities: &mut op,
        radii: &mut ra,
    };
    match backend {
        Backend::Cpu(_) => project_forward(&gaussians, camera, &ps, out).map(|_| ()),
        Backend::Wgpu(gpu, _) => gpu
            .project_forward(&gaussians, camera, &ps, out)
            .map(|_| ())
            .map_err(|e| match e {
                sync4d_gpu::GpuError::Raster(r) => r,
                other => sync4d_raster::RasterError::invalid("wgpu", other.to_string()),
            }),
    }
    .map_err(|e| e.to_string())?;
    let splats = Splats {
        means2d: &m2,
        conics: &co,
        depths: &de,
        opacities: &op,
        radii: &ra,
        features: &colors,
        channels: 3,
    };
    let npix = (camera.width * camera.height) as usize;
    let (mut img, mut alpha, mut depth) =
        (vec![0.0f32; 3 * npix], vec![0.0; npix], vec![0.0; npix]);
    let image = ImageMut {
        features: &mut img,
        alpha: &mut alpha,
        depth: &mut depth,
    };
    let bs = BlendSettings::default();
    let (w, h) = (camera.width, camera.height);
    match backend {
        Backend::Cpu(state) => rasterize_forward(&splats, w, h, &ck.background, &bs, state, image)
            .map(|_| ())
            .map_err(|e| e.to_string())?,
        Backend::Wgpu(gpu, state) => gpu
            .rasterize_forward(&splats, w, h, &ck.background, &bs, state, image)
            .map(|_| ())
            .map_err(|e| e.to_string())?,
    }
    Ok(img)
}
